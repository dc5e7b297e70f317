"""Work is never lost: periodic atomic checkpoints, SIGINT/SIGTERM handled between batches, and a
resume that refuses a checkpoint of another configuration before it touches anything."""

from __future__ import annotations

import contextlib
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


def resume_differences(saved: dict[str, Any], current: dict[str, Any]) -> list[str]:
    """``key: saved → current`` for every config value that differs and may not (see
    ``RESUME_MAY_DIFFER``)."""
    a, b = flatten(saved), flatten(current)
    out = []
    for key in sorted(set(a) | set(b)):
        if key.startswith(RESUME_MAY_DIFFER) or key in ("resume", "progress", "device"):
            continue
        if a.get(key, "<absent>") != b.get(key, "<absent>"):
            out.append(f"{key}: {a.get(key, '<absent>')} → {b.get(key, '<absent>')}")
    return out


def check_resume(path: Path, state: dict[str, Any], current: dict[str, Any]) -> None:
    """Refuse to resume ``state`` (loaded from ``path``) under a different configuration.

    Raises:
        ValueError: naming every differing key.
    """
    diffs = resume_differences(state["config"], current)
    if diffs:
        raise ValueError(
            f"resume={path} was trained with another configuration; these keys differ "
            f"(checkpoint → this run): {'; '.join(diffs)}"
        )


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
