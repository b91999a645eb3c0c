"""Whether a cache folder or a cached file can be trusted before anything is loaded from it
(owner, mode, the parents' sticky bit, the content's SHA-256): :mod:`.build`'s checks."""

from __future__ import annotations

import hashlib
import os
import stat
from pathlib import Path


def _mode(st: os.stat_result) -> str:
    return f"mode {stat.S_IMODE(st.st_mode):04o}"


def folder_problem(folder: Path) -> str | None:
    """Why ``folder`` (an existing directory) cannot hold trusted libraries, else ``None``.

    It must be owned by this user and writable by no one else; each parent must be owned by
    this user or root and, if others can write it, have the sticky bit (as ``/tmp``).
    """
    me = os.geteuid()
    real = folder.resolve()
    st = os.stat(real)
    if not stat.S_ISDIR(st.st_mode):
        return f"cache folder {str(folder)!r} is not a folder"
    if st.st_uid != me:
        return f"cache folder {str(folder)!r} is owned by user id {st.st_uid}, not by you"
    if st.st_mode & 0o022:
        return f"cache folder {str(folder)!r} is writable by other users ({_mode(st)})"
    for parent in real.parents:
        pst = os.stat(parent)
        if pst.st_uid not in (0, me):
            return (
                f"cache folder {str(folder)!r}: its parent {str(parent)!r} is owned by user "
                f"id {pst.st_uid}"
            )
        if pst.st_mode & 0o002 and not pst.st_mode & stat.S_ISVTX:
            return (
                f"cache folder {str(folder)!r}: its parent {str(parent)!r} is writable by "
                f"other users ({_mode(pst)})"
            )
    return None


def file_problem(path: Path) -> str | None:
    """Why the existing file ``path`` cannot be trusted (a link, another user's, writable by
    others), else ``None``."""
    st = os.lstat(path)
    if not stat.S_ISREG(st.st_mode):
        return "is not a regular file"
    if st.st_uid != os.geteuid():
        return f"is owned by user id {st.st_uid}, not by you"
    if st.st_mode & 0o022:
        return f"is writable by other users ({_mode(st)})"
    return None


def sha256_of(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()
