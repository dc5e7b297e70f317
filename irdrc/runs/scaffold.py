"""The one run scaffold: everything around a recipe's work, the same for every recipe and learner.

A ``Run`` owns its directory — created before any work, locked while the run lives (a second run
into it is refused, naming the first), with the composed config under ``.hydra/`` and every printed
line in ``<recipe>.log`` — the torch threads, the logger, the progress display, SIGINT/SIGTERM
(stop after the current batch, save, say how to go on), periodic and final checkpoints, and the
finishing of the directory (``summary.json`` and the line naming every file written).
"""

from __future__ import annotations

import contextlib
import fcntl
import hashlib
import io
import os
import shutil
import signal
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any, TextIO

from irdrc.runs.compose import Composed, recipe_call
from irdrc.runs.results import atomic_write, atomic_write_text, write_summary
from irdrc.runs.sections import Logger
from irdrc.runs.signals import RunInterrupted, RunSignals, StopFlag, stop_on_signals

BOOKKEEPING = (".hydra", ".lock", "config.yaml")
"""What the scaffold itself keeps in a run directory (besides the log)."""

NOT_VERBATIM = (
    "note: {name}'s checkpoint holds its networks, optimiser, counters and history, not the data "
    "it learns from nor its env rows' states: the resumed run starts its rows afresh on a random "
    "stream of its own, so its numbers differ from an uninterrupted run's"
)
"""What a resumed run of the shared training loop says (``Run.training``)."""


class _Tee:
    """``sys.stdout`` for the length of a run: what is printed also goes to the run's log."""

    def __init__(self, stream: Any, log: Any) -> None:
        self.stream, self.log = stream, log

    def write(self, text: str) -> int:
        self.log.write(text)
        return self.stream.write(text)

    def flush(self) -> None:
        self.log.flush()
        self.stream.flush()

    def __getattr__(self, name: str) -> Any:  # isatty, fileno, encoding: the terminal's
        return getattr(self.stream, name)


def quoted(path: Path) -> str:
    """A path as a command-line value (quoted when it holds more than plain characters)."""
    text = str(path)
    plain = all(c.isalnum() or c in "_-./" for c in text)
    return text if plain else "'" + text.replace("'", "'\\''") + "'"


def python_command() -> str:
    """The python that runs this process, as a user types it: relative to the working directory
    when it lies below it (``.venv/bin/python``), else its full path."""
    exe = Path(sys.executable)
    try:
        return str(exe.relative_to(Path.cwd()))
    except ValueError:
        return str(exe)


def resume_hint(recipe: str, directory: Path) -> str:
    """How to go on from the checkpoint in ``directory`` ('' when there is none)."""
    path = directory / "checkpoint.pt"
    if not path.is_file():
        return ""
    return f"; go on with: {python_command()} {recipe_call(recipe)} resume={quoted(path)}"


def quiet_libraries() -> None:
    """What a run prints is about the run: TorchRL's storage line (INFO) and its note on a last
    partial batch (the run's own record counts those frames) are left out."""
    import logging
    import warnings

    os.environ.setdefault("RL_LOGGING_LEVEL", "WARNING")  # read when TorchRL is first imported
    logging.getLogger("torchrl").setLevel(logging.WARNING)  # … or it is imported already
    warnings.filterwarnings("ignore", message="total_frames .* is not exactly divisible")


class Run:
    """One run of a recipe: its directory and what every run needs around its work (see the
    module docstring). ``open`` creates and locks the directory; ``close`` releases it.

    Attributes:
        recipe: the recipe's name (its config file, its log ``<recipe>.log``).
        dir: the run directory.
        composed: the composed config (plain ``cfg``, group choices, the command line).
        resume_state: the checkpoint a resumed run goes on from (None: a fresh run).
    """

    def __init__(
        self,
        recipe: str,
        composed: Composed,
        directory: Path,
        resume_state: dict[str, Any] | None = None,
    ) -> None:
        self.recipe, self.composed, self.dir = recipe, composed, Path(directory)
        self.resume_state = resume_state
        self.stop: StopFlag | None = None
        self.logger: Any = None  # the tracking backend's logger (make_logger), once open
        self._lock: TextIO | None = None
        self._log: TextIO | None = None
        self._stdout: TextIO | None = None
        self._created: list[Path] = []
        self.signals = RunSignals()
        self._had: set[str] = set()

    # -- the directory --------------------------------------------------------------------------

    @property
    def scenario(self) -> str:
        """The scenario's name (``Composed.scenario``; a resumed run keeps its first name)."""
        if self.resume_state is not None and self.resume_state.get("scenario"):
            return str(self.resume_state["scenario"])
        return self.composed.scenario

    def open(self) -> Run:
        """Create (or reuse) the directory, lock it, record the config, start the log.

        Raises:
            ValueError: the directory cannot be created, or another run holds it.
        """
        fresh = [p for p in (self.dir, *self.dir.parents) if not p.exists()]
        self._had = {p.name for p in self.dir.iterdir()} if self.dir.is_dir() else set()
        try:
            self.dir.mkdir(parents=True, exist_ok=True)
            lock = open(self.dir / ".lock", "a+")  # noqa: SIM115 - held for the run's life
        except OSError as err:
            raise ValueError(
                f"hydra.run.dir={self.dir}: cannot create the run directory there "
                f"({err.strerror or err}); choose another with hydra.run.dir=…"
            ) from None
        self._created = fresh
        self._lock = lock
        try:
            fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            lock.seek(0)
            holder = lock.read().strip() or "another process"
            lock.close()
            self._lock = None
            raise ValueError(
                f"hydra.run.dir={self.dir} is in use by {holder}: two runs would mix their files; "
                "wait for it to finish or choose another hydra.run.dir"
            ) from None
        lock.seek(0)
        lock.truncate()
        lock.write(f"process {os.getpid()} (python {recipe_call(self.recipe)})\n")
        lock.flush()
        self._record()
        log = open(self.dir / f"{self.recipe}.log", "a", encoding="utf-8")  # noqa: SIM115
        self._log, self._stdout = log, sys.stdout
        sys.stdout = _Tee(sys.stdout, log)
        quiet_libraries()
        self.signals.install()
        return self

    def _record(self) -> None:
        """``.hydra/``: the composed config, the command line, and the job (what Hydra writes)."""
        from omegaconf import OmegaConf

        c = self.composed
        hydra = {
            "hydra": {
                "job": {"name": self.recipe},
                "runtime": {"choices": c.choices, "output_dir": str(self.dir)},
                "overrides": {"task": c.task},
            }
        }
        for name, node in (("config", c.cfg), ("overrides", c.task), ("hydra", hydra)):
            atomic_write_text(self.dir / ".hydra" / f"{name}.yaml", OmegaConf.to_yaml(node))
        atomic_write_text(self.dir / "config.yaml", OmegaConf.to_yaml(c.cfg))

    def log_line(self, text: str) -> None:
        """Write ``text`` to the run's log only (what goes to stderr is kept there too)."""
        if self._log is not None:
            self._log.write(text.rstrip("\n") + "\n")
            self._log.flush()

    def close(self, refused: bool = False) -> None:
        """Stop the log and release the lock; a refused run leaves no trace: what the scaffold
        created goes (a directory that held something before is left as it was, but for the log)."""
        self.signals.restore()
        if self._stdout is not None:
            sys.stdout = self._stdout
            self._stdout = None
        if self._log is not None:
            self._log.close()
            self._log = None
        if self._lock is not None:
            with contextlib.suppress(OSError):
                (self.dir / ".lock").unlink()
            self._lock.close()
            self._lock = None
        if refused and self.dir.is_dir():
            mine = {*BOOKKEEPING, f"{self.recipe}.log"} | ({"logs"} - self._had)  # the logger's
            if not {p.name for p in self.dir.iterdir()} - mine:
                for name in mine:
                    path = self.dir / name
                    shutil.rmtree(path, ignore_errors=True) if path.is_dir() else path.unlink(
                        missing_ok=True
                    )
                for d in self._created:
                    with contextlib.suppress(OSError):
                        d.rmdir()

    # -- around the work ------------------------------------------------------------------------

    max_threads: int | None = None
    """At most this many torch threads per run (None: no cap); a sweep's trial sets its CPUs."""

    @classmethod
    def threads(cls, n: int) -> None:
        """torch's threads for this run (one is fastest for small networks here), at most the
        machine's cores and ``Run.max_threads`` (a trial given one CPU runs on one thread)."""
        import torch

        cap = min(os.cpu_count() or 1, cls.max_threads or 4096)
        torch.set_num_threads(max(1, min(int(n), cap)))

    def make_logger(self, cfg: Logger, name: str) -> Any:
        """The run's logger (``logger=…``), named ``scenario__name__seed`` (``tracking.run_name``:
        a long scenario shortened); None for ``none``."""
        from irdrc.runs.tracking import make_logger, run_name

        seed = self.composed.cfg.get("seed", 0)
        self.logger = make_logger(
            cfg.backend,
            run_name(self.scenario, name, seed),
            self.dir / "logs",
            project=cfg.project,
            mode=cfg.mode,
            config=self.composed.cfg,
        )
        return self.logger

    def train(self, cfg: Any, train: Any, scorer: Any) -> Any:
        """A single-vehicle learner's ``train`` (``irdrc.agents.dqn.train``, ``sac.train``) on its
        recipe's ``cfg`` (``sections.OneVehicleLearning``), inside ``training``: progress,
        checkpoints and the stop, resumed from this run's checkpoint; returns its record."""
        with self.training(
            cfg.algo.total_frames, cfg.algo.name, checkpoint=cfg.checkpoint
        ) as hooks:
            return train(
                cfg.params,
                cfg.algo,
                seed=cfg.seed,
                device=cfg.device,
                scorer=scorer,
                eval_every_frames=cfg.eval.every_frames,
                hooks=hooks,
                resume=self.resume_state,
            )

    @contextlib.contextmanager
    def training(
        self,
        total: int,
        label: str,
        *,
        checkpoint: Any = None,
        unit: str = "env steps",
        verbatim: bool = False,
    ) -> Iterator[Any]:
        """The hooks a learner reports through while it trains: progress (a bar in a terminal,
        plain lines in a log) and the logger, a checkpoint as ``checkpoint`` (a
        ``sections.Checkpoint``; None: at the end only) paces it, and a stop after the current
        batch on SIGINT/SIGTERM. A resumed run says where it goes on from, and, unless its
        checkpoint holds everything it draws from (``verbatim``: Q-learning, the one-stream
        learners), that its numbers differ from an uninterrupted run's (``NOT_VERBATIM``)."""
        from irdrc.agents.base import Hooks
        from irdrc.runs.progress import RunProgress

        if self.resume_state is not None:
            state = self.resume_state
            print(
                f"resumed from {Path(self.composed.cfg['resume']).expanduser()} at "
                f"{state.get('env_steps', state['frames'])} {unit}; training to {total}, "
                f"files in {self.dir}",
                flush=True,
            )
            if not verbatim:
                print(NOT_VERBATIM.format(name=label), flush=True)
        enabled = bool(self.composed.cfg.get("progress", True))
        progress = RunProgress(total, enabled, self.logger, label, unit)
        if self.resume_state is not None:
            progress.resumed(self.resume_state.get("history", []))
        with stop_on_signals() as stop:
            self.stop = stop
            yield Hooks(
                on_eval=progress.on_eval,
                on_batch=progress.on_batch,
                on_start=progress.on_start,
                on_checkpoint=self.checkpoint,
                checkpoint_every_frames=int(checkpoint.every_frames) if checkpoint else 0,
                checkpoint_every_seconds=float(checkpoint.every_seconds) if checkpoint else 0.0,
                should_stop=stop,
            )
            progress.close()

    def checkpoint(self, state: dict[str, Any] | None) -> None:
        """``checkpoint.pt`` (atomically), with the run's config and scenario, and its metrics and
        episodes so far beside it (written first: once the checkpoint exists, they do too); None
        (a learner without a resumable state): nothing."""
        if state is None:
            return
        import torch

        from irdrc.agents.base import DIGEST_SUFFIX, EPISODE_FIELDS
        from irdrc.runs.results import write_metrics_csv, write_rows_csv

        write_metrics_csv(self.dir / "metrics.csv", state.get("history", []))
        write_rows_csv(
            self.dir / "episode_rewards.csv", state.get("episode_rewards", []), EPISODE_FIELDS
        )
        buf = io.BytesIO()
        full = {
            "scenario": self.scenario,
            **state,
            "config": self.composed.cfg,
            "recipe": self.recipe,
        }
        torch.save(full, buf)
        data = buf.getvalue()
        digest = hashlib.sha256(data).hexdigest()
        side = (self.dir / "checkpoint.pt").with_suffix(DIGEST_SUFFIX)
        previous = side.read_text().split()[:1] if side.is_file() else []
        atomic_write_text(side, "\n".join([digest, *previous]) + "\n")  # both, while it changes
        atomic_write(self.dir / "checkpoint.pt", lambda f: f.write(data))
        atomic_write_text(side, digest + "\n")

    def finish(
        self,
        summary: dict[str, Any] | None,
        *,
        interrupted_at: int | None = None,
        unit: str = "env steps",
    ) -> None:
        """Write ``summary.json`` (when given), close the logger (W&B: say how to upload an offline
        run), name every file the run wrote, and — for a run a signal stopped at
        ``interrupted_at`` — raise ``RunInterrupted`` with the command that goes on."""
        if summary is not None:
            write_summary(self.dir / "summary.json", summary)
        if self.logger is not None and type(self.logger).__name__ == "WandbLogger":
            sync_dir = Path(self.logger.experiment.dir).parent
            self.logger.experiment.finish()
            if "offline" in str(sync_dir.name):
                print(f"W&B: offline run in {sync_dir}; upload it with: wandb sync {sync_dir}")
        skip = {".hydra", ".lock", f"{self.recipe}.log"}
        files = sorted(
            p.name + ("/" if p.is_dir() else "")
            for p in self.dir.iterdir()
            if p.name not in skip and not p.name.startswith(".")
        )
        print(f"\nwrote {', '.join(files)} to {self.dir}", flush=True)
        if interrupted_at is None and self.signals.signum is not None:
            signum = self.signals.signum
            raise RunInterrupted(
                f"stopped by {signal.Signals(signum).name} after training: every file is written "
                f"in {self.dir}, without what the signal cut short",
                code=128 + int(signum),
            )
        if interrupted_at is not None:
            signum = (self.stop.signal if self.stop else None) or signal.SIGINT
            how = (
                f"go on with: {python_command()} {recipe_call(self.recipe)} resume="
                f"{quoted(self.dir / 'checkpoint.pt')} (it goes on in the same directory with the "
                "same configuration)"
            )
            raise RunInterrupted(
                f"stopped by {signal.Signals(signum).name} at {interrupted_at} {unit}; the files "
                f"so far are in {self.dir}; {how}",
                code=128 + int(signum),
            )
