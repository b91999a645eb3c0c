"""Ctrl-C and SIGTERM that stop a long run, even where a library swallows them.

Python turns Ctrl-C into ``KeyboardInterrupt`` raised wherever the interpreter is, and
some libraries the project runs catch it there:

* CasADi's Python bindings try an argument's type conversions in turn (calling back into
  Python) and clear the error of a failed one, KeyboardInterrupt included, so a Ctrl-C
  landing in a conversion is lost and the expression is built as if nothing happened;
* CasADi's IPOPT interface checks for Ctrl-C between iterations and ends the solve with a
  status instead of an error, so the caller sees one more failed solve and goes on.

Under :func:`remember_interrupts` the handlers of SIGINT and SIGTERM also record the
signal, and long loops call :func:`raise_if_interrupted` between their steps (an episode
step, a benchmark solve), which raises ``KeyboardInterrupt`` again if one was received.
The command lines enter it around their whole run (:func:`experiments.cli.one_line_errors`)
and :func:`experiments.evaluation.run.evaluate` around its own.
"""

from __future__ import annotations

import signal
import threading
from typing import Any

_RECEIVED: list[int] = []  # signals received under the outermost context (main thread)
_DEPTH = [0]  # nesting depth of remember_interrupts in the main thread


def raise_if_interrupted() -> None:
    """Raise ``KeyboardInterrupt`` if a Ctrl-C or SIGTERM came under :func:`remember_interrupts`.

    For the points between a long run's steps, and for ``except Exception`` blocks that
    would otherwise record a converted interrupt as an ordinary error.
    """
    if _RECEIVED:
        raise KeyboardInterrupt(f"signal {_RECEIVED[0]}")


class remember_interrupts:  # noqa: N801 (a context manager used like a function)
    """Context: Ctrl-C and SIGTERM raise ``KeyboardInterrupt`` and are remembered.

    So ``kill PID`` ends a run the same clean way as Ctrl-C, and an interrupt a library
    swallowed is raised again by :func:`raise_if_interrupted`. Ctrl-C is taken over only
    from Python's default handler (an ignored one, as in pool workers, or a user's own
    stays). Nested uses share the outermost one's record; outside the main thread it does
    nothing. The previous handlers come back and the record is cleared on leaving the
    outermost context.
    """

    def __enter__(self) -> remember_interrupts:
        self.previous: dict[int, Any] = {}
        self.active = threading.current_thread() is threading.main_thread()
        if not self.active:
            return self
        _DEPTH[0] += 1
        if _DEPTH[0] > 1:
            return self
        _RECEIVED.clear()
        self.previous[signal.SIGTERM] = signal.signal(signal.SIGTERM, _record_and_raise)
        if signal.getsignal(signal.SIGINT) is signal.default_int_handler:
            self.previous[signal.SIGINT] = signal.signal(signal.SIGINT, _record_and_raise)
        return self

    def __exit__(self, *exc: Any) -> None:
        if not self.active:
            return
        _DEPTH[0] -= 1
        for signum, handler in self.previous.items():
            signal.signal(signum, handler)
        if _DEPTH[0] == 0:
            _RECEIVED.clear()


def _record_and_raise(signum: int, frame: Any) -> None:
    _RECEIVED.append(signum)
    raise KeyboardInterrupt(f"signal {signum}")


__all__ = ["raise_if_interrupted", "remember_interrupts"]
