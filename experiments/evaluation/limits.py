"""The time limit of one episode: it ends, as an error row naming the limit, in any executor.

:class:`EpisodeLimit` raises :class:`EpisodeTimeout` (a ``BaseException``) at the limit in the
episode's thread (``SIGALRM`` in the main thread, an asynchronous exception otherwise;
:func:`check_deadline` raises it again where a library swallowed it), and runs ``on_stuck``
in a watchdog thread ``grace`` seconds later if the episode is stuck in native code.
"""

from __future__ import annotations

import ctypes
import math
import signal
import threading
import time
from collections.abc import Callable
from typing import Any

#: What the row of an episode ended at its limit says after ``EpisodeTimeout:``.
LIMIT_SETTINGS = "--episode-timeout, evaluation.episode_timeout"


class EpisodeTimeout(BaseException):  # noqa: N818 (named as the row shows it)
    """An episode ran past its time limit (raised in the thread that runs it)."""


def grace_time(seconds: float) -> float:
    """[s] after the limit before an episode that did not return counts as stuck:
    a tenth of the limit, at least 2 s and at most 30 s."""
    return min(30.0, max(2.0, 0.1 * seconds))


def timeout_text(seconds: float) -> str:
    """The error of an episode ended at its limit (one line, for its row)."""
    return (
        f"EpisodeTimeout: the episode ran longer than its limit of {seconds:g} s ({LIMIT_SETTINGS})"
    )


def check_limit(seconds: Any, name: str = "episode_timeout") -> float | None:
    """``None`` for no limit (``None`` or 0), else ``seconds`` as a positive float.

    Raises:
        ValueError: naming ``name``, for a negative, non-finite or non-numeric value.
    """
    if seconds is None:
        return None
    if isinstance(seconds, bool) or not isinstance(seconds, (int, float)):
        raise ValueError(f"{name}={seconds!r}: must be a number of seconds > 0 (or 0/None: none)")
    value = float(seconds)
    if not math.isfinite(value) or value < 0.0:
        raise ValueError(f"{name}={seconds!r}: must be a number of seconds > 0 (or 0/None: none)")
    return value or None


_CURRENT = threading.local()  # the limit armed in this thread


def check_deadline() -> None:
    """Raise :class:`EpisodeTimeout` if the limit armed in this thread has passed (between
    an episode's steps: a library may have swallowed the one raised at the limit)."""
    limit = getattr(_CURRENT, "limit", None)
    if limit is not None and limit.active and time.monotonic() >= limit.deadline:
        limit.expired = True
        raise EpisodeTimeout()


def _raise_in_thread(ident: int, exc: type[BaseException] | None) -> None:
    """Raise ``exc`` asynchronously in the thread ``ident`` (``None`` clears a pending one)."""
    obj = ctypes.py_object(exc) if exc is not None else None
    ctypes.pythonapi.PyThreadState_SetAsyncExc(ctypes.c_ulong(ident), obj)


class EpisodeLimit:
    """Context: a wall-clock limit of ``seconds`` [s] (``None``: none) on the code inside;
    ``on_stuck`` runs in a watchdog thread ``grace`` [s] (default :func:`grace_time`) after it.
    """

    def __init__(
        self,
        seconds: float | None,
        on_stuck: Callable[[], Any] | None = None,
        grace: float | None = None,
    ) -> None:
        self.seconds = seconds
        self.on_stuck = on_stuck
        self.grace = grace_time(seconds or 0.0) if grace is None else grace
        self.active = False
        self.expired = False
        self.deadline = math.inf
        self._lock = threading.Lock()
        self._timers: list[threading.Timer] = []
        self._previous: Any = None

    def __enter__(self) -> EpisodeLimit:
        if not self.seconds:
            return self
        self.thread = threading.current_thread()
        self.main = self.thread is threading.main_thread()
        self.deadline = time.monotonic() + self.seconds
        self.active = True
        _CURRENT.limit = self
        if self.main:
            self._previous = signal.signal(signal.SIGALRM, self._on_alarm)
            signal.setitimer(signal.ITIMER_REAL, self.seconds)
        else:
            self._start_timer(self.seconds, self._interrupt)
        if self.on_stuck is not None:
            self._start_timer(self.seconds + self.grace, self._stuck)
        return self

    def _start_timer(self, seconds: float, action: Callable[[], None]) -> None:
        timer = threading.Timer(seconds, action)
        timer.daemon = True
        timer.start()
        self._timers.append(timer)

    def _on_alarm(self, signum: int, frame: Any) -> None:
        if self.active:
            self.expired = True
            raise EpisodeTimeout()

    def _interrupt(self) -> None:
        with self._lock:
            if self.active:
                self.expired = True
                _raise_in_thread(self.thread.ident, EpisodeTimeout)

    def _stuck(self) -> None:
        with self._lock:
            if not self.active:
                return
        self.on_stuck()

    def __exit__(self, *exc: Any) -> None:
        if not self.seconds:
            return
        with self._lock:
            self.active = False
            if not self.main and self.expired:
                _raise_in_thread(self.thread.ident, None)  # one not delivered yet
        for timer in self._timers:
            timer.cancel()
        if self.main:
            signal.setitimer(signal.ITIMER_REAL, 0.0)
            previous = self._previous if self._previous is not None else signal.SIG_DFL
            signal.signal(signal.SIGALRM, previous)
        _CURRENT.limit = None
