"""One run per folder: an operating-system lock on ``DIR/.lock`` (:class:`FolderLock`), and
who holds it (:func:`folder_in_use`), for the results folders of the evaluation and the
training folders of ``lfm-train``."""

from __future__ import annotations

import fcntl
import os
import socket
import time
from pathlib import Path
from typing import Any


class ResultsFolderError(ValueError):
    """The results folder cannot be used (e.g. it holds results of another config)."""


_LOCK = ".lock"  # the owner's pid and host while a run writes into the folder


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True  # another user's live process
    return True


def _lock_owner(fd: int) -> tuple[bool, str]:
    """Whether the lock file names a live owner (a live process of this host, or one of
    another host), and a text naming it for a message."""
    try:
        parts = os.pread(fd, 200, 0).decode(errors="replace").split()
    except OSError:
        parts = []
    if len(parts) == 2 and parts[0].isdigit():
        alive = parts[1] != socket.gethostname() or _pid_alive(int(parts[0]))
        return alive, f"process {parts[0]} on {parts[1]}"
    return False, "another process"


def folder_in_use(out: str | os.PathLike) -> str | None:
    """Who holds the lock of the folder ``out`` (a text naming the process), or ``None``
    when no run writes into it. Looks without taking the lock for more than a moment
    (a run that starts meanwhile tries again: :meth:`FolderLock.acquire`)."""
    try:
        fd = os.open(Path(out) / _LOCK, os.O_RDONLY | os.O_NOFOLLOW)
    except OSError:
        return None  # no lock file: no owner
    try:
        fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
    except BlockingIOError:
        return _lock_owner(fd)[1]
    except OSError:
        return None
    finally:
        os.close(fd)  # (releases a lock taken)
    return None


class FolderLock:
    """Ownership of a folder by one process: ``flock`` on ``out/.lock``, released by the kernel
    however the owner ends; the file names ``<pid> <host>`` for the :class:`ResultsFolderError`
    another process gets (``what`` names the folder, ``hint`` advises).
    """

    def __init__(
        self,
        out: Path,
        what: str = "results folder",
        hint: str = "wait for that run to end or choose another output folder",
    ) -> None:
        self.path = Path(out) / _LOCK
        self.what, self.hint = what, hint
        self.text = f"{os.getpid()} {socket.gethostname()}\n"
        self._fd: int | None = None

    def acquire(self) -> FolderLock:
        """Take the lock, or raise :class:`ResultsFolderError` naming its owner (a lock whose
        file names no live owner yet is tried again for a moment).
        """
        folder = str(self.path.parent)
        for attempt in range(40):
            fd = os.open(self.path, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW, 0o644)
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                alive, owner = _lock_owner(fd)
                os.close(fd)
                if not alive and attempt < 39:
                    time.sleep(0.01)
                    continue
                raise ResultsFolderError(
                    f"{self.what} {folder!r} is in use by {owner} (lock file "
                    f"{str(self.path)!r}); {self.hint}"
                ) from None
            except BaseException:
                os.close(fd)
                raise
            # Its previous owner may have removed the file between our open and our lock:
            # the lock then holds a file no other process can find. Try again.
            try:
                current = os.stat(self.path)
                mine = os.fstat(fd)
                same = (current.st_dev, current.st_ino) == (mine.st_dev, mine.st_ino)
            except FileNotFoundError:
                same = False
            if not same:
                os.close(fd)
                continue
            os.ftruncate(fd, 0)
            os.pwrite(fd, self.text.encode(), 0)
            self._fd = fd
            return self
        raise ResultsFolderError(f"{self.what} {folder!r}: cannot take its lock {self.path}")

    def release(self) -> None:
        """Remove the lock file and release the lock (nothing if not held)."""
        if self._fd is None:
            return
        try:
            self.path.unlink(missing_ok=True)  # while still holding it
        finally:
            os.close(self._fd)
            self._fd = None

    def __enter__(self) -> FolderLock:
        return self.acquire()

    def __exit__(self, *exc: Any) -> None:
        self.release()
