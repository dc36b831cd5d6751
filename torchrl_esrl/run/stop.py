"""Stopping a run cleanly on a signal: SIGTERM and SIGINT (and submitit's SIGUSR2) ask the run to
stop at its next step boundary, with a checkpoint where one is due (docs/runs.md)."""
from __future__ import annotations

import signal
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any

STOP_GRACE_S = 20  # a signalled run that reaches no step boundary in this time stops at once


class Stopped(BaseException):
    """A run stopped by a signal (a BaseException, like KeyboardInterrupt: no ``except Exception`` swallows it)."""

    def __init__(self, signum: int, at_once: bool = False, where: str = "", written: Path | None = None):
        super().__init__(signal.Signals(signum).name)
        self.signum, self.at_once, self.where, self.written = signum, at_once, where, written


class StopOnSignal:
    """SIGTERM and SIGINT (and submitit's SIGUSR2, where submitit handles it) ask the run to stop
    at its next step boundary (:meth:`check`); after :data:`STOP_GRACE_S` seconds without one, or
    on a second signal, :class:`Stopped` is raised at once in the main thread."""

    SIGNALS = (signal.SIGTERM, signal.SIGINT)

    def __init__(self):
        self.signum: int | None = None
        self.previous: dict[int, Any] = {}

    def install(self) -> StopOnSignal:
        if threading.current_thread() is not threading.main_thread():
            return self  # signals are delivered to the main thread only
        usr2 = signal.getsignal(signal.SIGUSR2)
        chained = (signal.SIGUSR2,) if callable(usr2) else ()  # submitit's requeue, called after the stop
        for signum in (*self.SIGNALS, *chained):
            self.previous[signum] = signal.signal(signum, self._handle)
        self.previous[signal.SIGALRM] = signal.signal(signal.SIGALRM, self._grace_over)
        return self

    def uninstall(self) -> None:
        signal.setitimer(signal.ITIMER_REAL, 0)
        for signum, handler in self.previous.items():
            signal.signal(signum, handler)
        self.previous = {}

    def _handle(self, signum, _frame) -> None:
        if self.signum is not None:
            raise Stopped(self.signum, at_once=True)
        self.signum = signum
        signal.setitimer(signal.ITIMER_REAL, STOP_GRACE_S)

    def _grace_over(self, _signum, _frame) -> None:
        if self.signum is not None:
            raise Stopped(self.signum, at_once=True)

    @property
    def requested(self) -> bool:
        return self.signum is not None

    def check(self, where: str | Callable[[], str], before_stop: Callable[[], Path | None] | None = None) -> None:
        """A step boundary: if a stop was asked for, ``before_stop()`` (a checkpoint) and :class:`Stopped`.
        Off the main thread (the background ES generations), only :class:`Stopped`. ``where``: the
        point in words, or a function giving them, called only on a stop (a hot loop's stop points)."""
        if self.signum is None:
            return
        written = None
        if threading.current_thread() is threading.main_thread():
            signal.setitimer(signal.ITIMER_REAL, 0)  # the checkpoint write is not cut short
            if before_stop is not None:
                written = before_stop()
        raise Stopped(self.signum, where=where() if callable(where) else where, written=written)

    def hand_over(self) -> None:
        """After the stop is recorded: the handler this one replaced for the signal, if it was
        chained (submitit's checkpoint-and-requeue for SIGUSR2, which exits)."""
        previous = self.previous.get(self.signum)
        if self.signum == signal.SIGUSR2 and callable(previous):
            previous(self.signum, None)
