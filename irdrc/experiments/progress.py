"""Plain progress lines with an ETA for long loops (readable in a terminal and in a log file)."""

from __future__ import annotations

import time


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
