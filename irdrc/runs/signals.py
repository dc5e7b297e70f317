"""SIGINT and SIGTERM in a run: during training a flag the learner reads after each batch (it stops,
checkpoints and says how to go on); in any other phase an exception raised where the run is, so
that phase writes what it can (the run-wide handler ``Run.open`` installs)."""

from __future__ import annotations

import contextlib
import signal
import threading
from collections.abc import Iterator
from typing import Any


class RunInterrupted(Exception):
    """A run stopped by SIGINT/SIGTERM after saving what it had; the message says how to go on,
    ``code`` is the exit status (128 + the signal's number)."""

    def __init__(self, message: str, code: int = 130) -> None:
        super().__init__(message)
        self.code = code


class StopFlag:
    """Set by SIGINT/SIGTERM while a run trains: the learner stops after its current batch.
    A second SIGINT interrupts at once (``KeyboardInterrupt``)."""

    def __init__(self) -> None:
        self.signal: int | None = None

    def __call__(self) -> bool:
        return self.signal is not None

    def _handle(self, signum: int, frame: Any) -> None:
        if self.signal is not None and signum == signal.SIGINT:
            raise KeyboardInterrupt
        self.signal = signum
        name = signal.Signals(signum).name
        print(f"\n{name}: stopping after this batch and saving (again to stop at once)", flush=True)


class Signalled(BaseException):
    """SIGINT or SIGTERM outside training (the run-wide handler of ``Run.open``): raised where the
    run is, so the phase it interrupts can write what it has; ``signum`` is the signal."""

    def __init__(self, signum: int) -> None:
        super().__init__(signal.Signals(signum).name)
        self.signum = signum


class RunSignals:
    """The run-wide handler: the first SIGINT/SIGTERM raises ``Signalled`` where the run is; a
    later one is noted and waits for the files the first lets the run write (a second SIGINT
    interrupts at once)."""

    def __init__(self) -> None:
        self.signum: int | None = None
        self.previous: dict[int, Any] = {}

    def install(self) -> None:
        """Take SIGINT and SIGTERM (in the main thread only), keeping the handlers before."""
        if threading.current_thread() is threading.main_thread():
            self.previous = {
                s: signal.signal(s, self._handle) for s in (signal.SIGINT, signal.SIGTERM)
            }

    def restore(self) -> None:
        """Give SIGINT and SIGTERM back to the handlers they had before ``install``."""
        for s, handler in self.previous.items():
            signal.signal(s, handler)
        self.previous = {}

    def _handle(self, signum: int, frame: Any) -> None:
        if self.signum is None:
            self.signum = signum
            raise Signalled(signum)
        if signum == signal.SIGINT:
            raise KeyboardInterrupt


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
