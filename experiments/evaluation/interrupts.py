"""Ctrl-C and SIGTERM that stop a long run, even where a library swallows them (CasADi's
bindings clear a ``KeyboardInterrupt`` in type conversions; its IPOPT ends a solve with a
status): under :func:`remember_interrupts` the signal is recorded, and long loops call
:func:`raise_if_interrupted` between steps.
"""

from __future__ import annotations

import signal
import threading
from typing import Any

_RECEIVED: list[int] = []  # signals received under the outermost context (main thread)
_DEPTH = [0]  # nesting depth of remember_interrupts in the main thread


def raise_if_interrupted() -> None:
    """Raise ``KeyboardInterrupt`` if a Ctrl-C or SIGTERM came under :func:`remember_interrupts`."""
    if _RECEIVED:
        raise KeyboardInterrupt(f"signal {_RECEIVED[0]}")


class remember_interrupts:  # noqa: N801 (a context manager used like a function)
    """Context: Ctrl-C (over Python's default handler only) and SIGTERM raise ``KeyboardInterrupt``
    and are remembered; nested uses share the outermost record; nothing outside the main thread.
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
