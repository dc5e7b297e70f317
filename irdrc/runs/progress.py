"""Progress with an ETA for long loops and learners' runs (a bar in a terminal, plain lines in a
log file), and the run's scalar logging hooks."""

from __future__ import annotations

import math
import os
import sys
import time
from typing import Any

from tqdm import tqdm

from irdrc.core.checks import grouped
from irdrc.runs.tracking import log_scalars


class Ticker:
    """Counts ``total`` units of work and prints ``[label] i/total (p %), elapsed, ETA`` at most
    every ``every_seconds`` (and at the end when anything was printed)."""

    def __init__(self, total: int, label: str, every_seconds: float = 5.0) -> None:
        self.total, self.label, self.every = max(1, int(total)), label, every_seconds
        self.done = 0
        self.start = self.last = time.perf_counter()
        self.printed = False

    def tick(self, n: int = 1) -> None:
        """Count ``n`` more units; print a line if the last one is old enough."""
        self.done += n
        now = time.perf_counter()
        if now - self.last >= self.every or (self.printed and self.done >= self.total):
            self.last, self.printed = now, True
            elapsed = now - self.start
            eta = elapsed / self.done * max(0, self.total - self.done)
            print(
                f"[{self.label}] {self.done}/{self.total} ({self.done / self.total:.0%}), "
                f"elapsed {elapsed:.0f} s, ETA {eta:.0f} s",
                flush=True,
            )


class Heartbeat:
    """Prints ``[label] text, elapsed N s`` at most every ``every_seconds`` while long work runs
    whose length is not known in advance (a solver's sweeps)."""

    def __init__(self, label: str, every_seconds: float = 5.0) -> None:
        self.label, self.every = label, every_seconds
        self.start = self.last = time.perf_counter()

    def beat(self, text: str) -> None:
        """Print ``text`` if the last line is old enough."""
        now = time.perf_counter()
        if now - self.last >= self.every:
            self.last = now
            print(f"[{self.label}] {text}, {now - self.start:.0f} s", flush=True)


LP_NOTICE_STATES = 1000
"""Beyond this many states the constrained optimum's LP (one HiGHS call, no progress of its own)
is announced before it starts: it takes under a second at the paper's 352 states, 5-10 s at 1 312
(a queue of 40) and minutes at a few thousand with slower chains (162 s at 1 968)."""


def lp_notice(num_states: int, hint: str = "") -> None:
    """Say that a long LP is starting (``LP_NOTICE_STATES``), so that a quiet terminal is not taken
    for a hung one; ``hint``, a faster way where there is one, follows."""
    if num_states > LP_NOTICE_STATES:
        print(
            f"[lp] solving the constrained optimum over {grouped(num_states)} states (one solver "
            "call with no progress of its own: minutes or more at this size; Ctrl-C stops it at "
            f"once{'; ' + hint if hint else ''}) …",
            flush=True,
        )


def busy() -> str:
    """``, machine busy: …`` when more processes want the CPUs than there are (the 1-minute load
    average above the cores), which slows a run; '' otherwise."""
    cores = os.cpu_count() or 1
    try:
        load = os.getloadavg()[0]
    except OSError:
        return ""
    return f", machine busy: load {load:.1f} on {cores} cores" if load > cores + 0.5 else ""


class RunProgress:
    """Progress of a learner's run, and its logging hooks (learner 0 is the one logged as ``eval/…``).

    On a terminal: a bar. Otherwise (a log file): one plain line per tenth of the run, with the ETA.
    """

    def __init__(
        self, total: int, enabled: bool, logger: Any, label: str, unit: str = "env steps"
    ) -> None:
        self.total, self.enabled, self.logger, self.label = total, enabled, logger, label
        self.unit = unit
        self.tty = sys.stdout.isatty()
        self.bar: tqdm | None = None
        self.ratio = math.nan
        self.min_ratio = math.nan
        self.start = time.perf_counter()
        self.next_line = 0.1
        self.pending: int | None = None  # env step of a plain line waiting for its evaluation
        self.ratio_steps: int | None = None  # env step of the latest evaluation

    def resumed(self, history: list[dict[str, Any]]) -> None:
        """A resumed run's lines start from its last evaluation (learner 0's), not from none."""
        mine = [r for r in history if int(r.get("learner", 0)) == 0]
        if mine:
            self.ratio, self.ratio_steps = mine[-1]["optimality_ratio"], mine[-1]["env_steps"]

    def on_start(self, info: dict[str, Any]) -> None:
        """Print what the learner built (``Hooks.on_start``), a line per fact."""
        for key, value in info.items():
            print(f"{key.replace('_', ' ')}: {value}", flush=True)

    def on_batch(self, info: dict[str, Any]) -> None:
        """After a batch (``Hooks.on_batch``): move the bar or print a line, log the scalars."""
        steps = info["env_steps"]
        if self.pending is not None:  # no evaluation came at the pending line's env step
            self._line(self.pending)
        if self.enabled and self.tty:
            if self.bar is None:
                unit = self.unit.split()[0] + " step"
                self.bar = tqdm(total=self.total, unit=unit, dynamic_ncols=True)
            self.bar.update(steps - self.bar.n)
            self._postfix()
        elif self.enabled and steps >= self.next_line * self.total:
            # printed after this step's evaluation, if one comes, so the ratio is this step's
            self.pending = steps
            self.next_line = math.floor(steps / self.total * 10 + 1) / 10
        scalars = {f"train/{k}": v for k, v in info.items() if k != "env_steps"}
        log_scalars(self.logger, scalars, steps)

    def _line(self, steps: int) -> None:
        """One plain progress line: the env steps, the latest evaluation's ratio and where it was."""
        self.pending = None
        elapsed = time.perf_counter() - self.start
        eta = max(0.0, elapsed / steps * (self.total - steps)) if steps else math.nan
        at = f" at {self.ratio_steps}" if self.ratio_steps not in (None, steps) else ""
        print(
            f"[{self.label}] {steps}/{self.total} {self.unit} ({steps / self.total:.0%}), "
            f"ratio {self.ratio:.4f}{at}, {elapsed:.0f} s, ETA {eta:.0f} s{busy()}",
            flush=True,
        )

    def _postfix(self) -> None:
        if self.bar is None:
            return
        post = {"opt": f"{self.ratio:.4f}"}
        if not math.isnan(self.min_ratio):
            post["min"] = f"{self.min_ratio:.4f}"
        self.bar.set_postfix(post, refresh=False)

    def on_eval(self, records: list[dict[str, Any]]) -> None:
        """After an exact evaluation (``Hooks.on_eval``): show its ratio, log its metrics."""
        first = records[0]
        self.ratio = first["optimality_ratio"]
        if len(records) > 1:
            self.min_ratio = min(r["optimality_ratio"] for r in records)
        step = first["env_steps"]
        self.ratio_steps = step
        if self.pending is not None and step >= self.pending:
            self._line(self.pending)
        if self.bar is not None:
            self._postfix()
        skip = ("learner", "env_steps", "episodes", "wall_seconds", "updates")
        log_scalars(self.logger, {f"eval/{k}": v for k, v in first.items() if k not in skip}, step)
        log_scalars(
            self.logger,
            {"time/wall_seconds": first["wall_seconds"], "time/updates": first["updates"]},
            step,
        )

    def close(self) -> None:
        """Print a line still pending and close the bar."""
        if self.pending is not None:
            self._line(self.pending)
        if self.bar is not None:
            self.bar.close()
