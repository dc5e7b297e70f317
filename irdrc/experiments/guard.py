"""Work is never lost: periodic atomic checkpoints, SIGINT/SIGTERM handled between batches, and a
resume that refuses a checkpoint of another configuration before it touches anything."""

from __future__ import annotations

import contextlib
import copy
import io
import signal
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import torch

from irdrc.agents.base import EPISODE_FIELDS, progress_fields
from irdrc.experiments.results import atomic_write, write_rows_csv

RESUME_MAY_DIFFER = (
    "algo.total_frames",
    "eval.",
    "logger.",
    "progress",
    "resume",
    "device",
    "num_threads",
    "compare.",
    "cache_dir",
    "checkpoint.",
    "hydra.",
)
"""Config keys a resumed run may change (where and how long it runs, not what it learns)."""


class RunInterrupted(Exception):
    """A run stopped by SIGINT/SIGTERM after saving what it had; the message says how to go on,
    ``code`` is the exit status (128 + the signal's number)."""

    def __init__(self, message: str, code: int = 130) -> None:
        super().__init__(message)
        self.code = code


def flatten(node: Any, prefix: str = "") -> dict[str, Any]:
    """A nested config as ``{dotted key: leaf value}``."""
    if isinstance(node, dict):
        out: dict[str, Any] = {}
        for k, v in node.items():
            out.update(flatten(v, f"{prefix}{k}."))
        return out
    return {prefix[:-1]: node}


def _covered(key: str, explicit: frozenset[str]) -> bool:
    """Whether the command line set ``key`` (itself, or a group or section holding it)."""
    return any(key == e or key.startswith(e + ".") for e in explicit)


def _select(node: Any, key: str) -> Any:
    for part in key.split("."):
        if not isinstance(node, dict) or part not in node:
            return "<absent>"
        node = node[part]
    return node


def _assign(node: dict[str, Any], key: str, value: Any) -> None:
    *parents, last = key.split(".")
    for part in parents:
        node = node.setdefault(part, {})
    node[last] = value


def resumed_config(
    path: Path, saved: dict[str, Any], current: dict[str, Any], explicit: frozenset[str]
) -> dict[str, Any]:
    """The configuration of a run resumed from the checkpoint at ``path``: the checkpoint's own
    (``saved``), except what the command line set on purpose (``explicit``: dotted keys, groups
    such as ``env`` or ``algo`` included), which ``current`` gives — so ``resume=PATH`` alone
    continues the run exactly as it was started, and ``algo.total_frames=…`` extends it.

    Raises:
        ValueError: naming every key the command line set to another value that a resumed run
            may not change (what it learns; see ``RESUME_MAY_DIFFER``).
    """
    explicit = frozenset(k for k in explicit if not k.startswith("hydra"))
    clash = []
    for key in sorted(explicit):
        if key.startswith(RESUME_MAY_DIFFER) or key in ("resume", "progress", "device"):
            continue
        old, new = _select(saved, key), _select(current, key)
        if old != new:
            if isinstance(old, dict) and isinstance(new, dict):
                a, b = flatten(old, key + "."), flatten(new, key + ".")
                clash += [
                    f"{k}: {a.get(k, '<absent>')} → {b.get(k, '<absent>')}"
                    for k in sorted(set(a) | set(b))
                    if a.get(k) != b.get(k)
                ]
            else:
                clash.append(f"{key}: {old} → {new}")
    if clash:
        raise ValueError(
            f"resume={path} was trained with another configuration; these keys differ "
            f"(checkpoint → this run): {'; '.join(clash)}. A resumed run keeps the checkpoint's "
            "configuration: leave them out"
        )
    out = copy.deepcopy(current)
    for key, value in flatten(saved).items():
        if not _covered(key, explicit) and key not in ("resume", "progress", "device"):
            _assign(out, key, value)
    return out


def load_resume(cfg: Any, explicit: frozenset[str]) -> tuple[dict[str, Any] | None, Any]:
    """The checkpoint a run resumes from (``resume=PATH``; ``None`` without one) and the run's
    configuration (``resumed_config``: the checkpoint's, with what ``explicit`` set), checked
    before anything is written.

    Raises:
        ValueError: the checkpoint is unreadable, its configuration clashes with the command
            line, or it has nothing left to train.
    """
    from omegaconf import OmegaConf

    from irdrc.agents.dqn import load_checkpoint

    if not cfg.get("resume"):
        return None, cfg
    path = Path(str(cfg.resume)).expanduser()
    state = load_checkpoint(path)
    current = OmegaConf.to_container(cfg, resolve=True)
    merged = OmegaConf.create(resumed_config(path, state["config"], current, explicit))
    total = int(merged.algo.total_frames)
    if int(state["frames"]) >= total:
        raise ValueError(
            f"resume={path} is at {state['frames']} env steps, algo.total_frames={total}: "
            "nothing left to train; raise algo.total_frames to train it longer"
        )
    return state, merged


def explicit_keys() -> frozenset[str]:
    """The keys the running Hydra app's command line set (empty outside one)."""
    from irdrc.experiments.grid import override_key

    try:
        from hydra.core.hydra_config import HydraConfig

        task = HydraConfig.get().overrides.task
    except Exception:
        return frozenset()
    return frozenset(override_key(o) for o in task)


def save_checkpoint(out: Path, state: dict[str, Any], config: dict[str, Any]) -> None:
    """``checkpoint.pt`` (atomically), with the run's metrics and episodes so far beside it."""
    # The checkpoint last: once it exists, the files it goes with exist too.
    history = state.get("history", [])
    write_rows_csv(out / "metrics.csv", history, progress_fields(history))
    write_rows_csv(out / "episode_rewards.csv", state.get("episode_rewards", []), EPISODE_FIELDS)
    buf = io.BytesIO()
    torch.save({**state, "config": config}, buf)
    data = buf.getvalue()
    atomic_write(out / "checkpoint.pt", lambda f: f.write(data))


class StopFlag:
    """Set by SIGINT/SIGTERM while a run trains: the learner stops after its current batch.

    A second SIGINT interrupts at once (``KeyboardInterrupt``).
    """

    def __init__(self) -> None:
        self.signal: int | None = None

    def __call__(self) -> bool:
        return self.signal is not None

    def _handle(self, signum, frame) -> None:
        if self.signal is not None and signum == signal.SIGINT:
            raise KeyboardInterrupt
        self.signal = signum
        name = signal.Signals(signum).name
        print(f"\n{name}: stopping after this batch and saving (again to stop at once)", flush=True)


@contextlib.contextmanager
def stop_on_signals() -> Iterator[StopFlag]:
    """Within the block, SIGINT and SIGTERM set the yielded flag instead of killing the process
    (only in the main thread; elsewhere the flag is never set)."""
    flag = StopFlag()
    if threading.current_thread() is not threading.main_thread():
        yield flag
        return
    previous = {s: signal.signal(s, flag._handle) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield flag
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)
