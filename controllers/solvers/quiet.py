"""Third-party solvers print nothing: their output is discarded at its source.

qpOASES prints its licence banner whenever CasADi creates a qpOASES instance (every new
memory of a qpOASES conic or of an ``sqpmethod`` that uses it), whatever ``printLevel`` says:
the banner comes from the instance's constructor, before CasADi hands it the options. CasADi
sends its C++ output through Python's ``sys.stdout``, not straight to the file descriptor, so
a block-buffered ``sys.stdout`` (a pipe or a file, without ``PYTHONUNBUFFERED``) kept the
banner in its buffer past a redirect of descriptor 1 alone and wrote it out afterwards: 211
banners for ten episodes of ``robust`` and ``pf`` on the paper's world when the output went to
a file, none on a terminal. :func:`silenced_output` therefore discards both levels: Python's
``sys.stdout`` (what CasADi writes) and the C-level descriptor 1, with C's ``stdout`` buffer
flushed before it is restored (what a library writes with ``printf``).

Descriptor 1 and ``sys.stdout`` belong to the whole process, so a lock makes concurrent
sections (Dask's worker threads) one section: the first to enter redirects, the last to
leave restores.
"""

from __future__ import annotations

import contextlib
import ctypes
import io
import os
import sys
import threading
from collections.abc import Iterator

_LOCK = threading.Lock()
_STATE = {"depth": 0, "stdout": None, "fd": -1}  # the open sections, what they replaced
_DEVNULL: list[int] = []  # the descriptor of os.devnull, opened once per process
_FFLUSH: list = []  # C's fflush, looked up once per process


class _Discard(io.TextIOBase):
    """A text stream that drops what it is given (Python's ``sys.stdout`` in a section)."""

    def write(self, text: str) -> int:
        return len(text)

    def writable(self) -> bool:
        return True


def _devnull() -> int:
    if not _DEVNULL:
        _DEVNULL.append(os.open(os.devnull, os.O_WRONLY))
    return _DEVNULL[0]


def _flush_c_stdout() -> None:
    """Flush C's ``stdout`` buffer (what native code wrote with ``printf``)."""
    if not _FFLUSH:
        try:
            _FFLUSH.append(ctypes.CDLL(None).fflush)
        except (OSError, AttributeError):  # no C library to call (not expected on POSIX)
            _FFLUSH.append(None)
    if _FFLUSH[0] is not None:
        _FFLUSH[0](None)


def _enter() -> None:
    with contextlib.suppress(AttributeError, OSError, ValueError):
        sys.stdout.flush()  # what was printed before the section stays printed
    _STATE["stdout"] = sys.stdout
    sys.stdout = _Discard()
    _flush_c_stdout()
    try:
        _STATE["fd"] = os.dup(1)
        os.dup2(_devnull(), 1)
    except OSError:  # descriptor 1 closed: nothing native can print there anyway
        _STATE["fd"] = -1


def _leave() -> None:
    _flush_c_stdout()  # into os.devnull, not into the restored stdout
    saved = _STATE["fd"]
    if saved >= 0:
        os.dup2(saved, 1)
        os.close(saved)
    sys.stdout = _STATE["stdout"]
    _STATE["stdout"], _STATE["fd"] = None, -1


@contextlib.contextmanager
def silenced_output() -> Iterator[None]:
    """Discard what is written to standard output inside the block, by Python code, by
    CasADi's plugins (through ``sys.stdout``) and by native code (descriptor 1); standard
    error is left alone, so warnings and errors still show. Sections nest, and sections of
    several threads overlap into one."""
    with _LOCK:
        if _STATE["depth"] == 0:
            _enter()
        _STATE["depth"] += 1
    try:
        yield
    finally:
        with _LOCK:
            _STATE["depth"] -= 1
            if _STATE["depth"] == 0:
                _leave()


__all__ = ["silenced_output"]
