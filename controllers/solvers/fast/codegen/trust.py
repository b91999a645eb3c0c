"""Whether a cache folder or a cached library can be trusted before anything is loaded from
it (owner, mode, the parents' sticky bit, the record's key and the content's SHA-256, then a
load in a short-lived child process): :mod:`.build`'s checks."""

from __future__ import annotations

import hashlib
import json
import os
import signal
import stat
import subprocess
import sys
from pathlib import Path

CHECK_TIMEOUT = 60.0  # [s] for the child process that checks a library before it is loaded

# The check of a library in a child process: loads it (its constructors run there, and a
# damaged file crashes the child only), then checks its symbols, its key and its sizes.
_CHECK = """
import ctypes, sys
path, key, symbols, dims = sys.argv[1], sys.argv[2], sys.argv[3], sys.argv[4]
lib = ctypes.CDLL(path)
missing = [s for s in symbols.split(",") if s and not hasattr(lib, s)]
if missing:
    print("it lacks the symbol(s) " + ", ".join(missing)); sys.exit(3)
if not hasattr(lib, "lfm_cache_key"):
    print("it records no key (built by another version)"); sys.exit(3)
lib.lfm_cache_key.restype = ctypes.c_char_p
found = lib.lfm_cache_key().decode("ascii", "replace")
if found != key:
    print("it was built for the key " + found[:40]); sys.exit(3)
if dims:
    d = (ctypes.c_long * 4)()
    lib.lfm_dims(d)
    if ",".join(map(str, d)) != dims:
        print("it is of a system of sizes " + ",".join(map(str, d)) + ", not " + dims)
        sys.exit(3)
print("ok")
"""


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


def check_in_child(path: Path, key: str, symbols: tuple[str, ...], dims: str) -> str | None:
    """Load ``path`` in a short-lived child process and check its symbols, key and sizes:
    why it fails (a crash named by its signal), else ``None``."""
    cmd = [sys.executable, "-I", "-S", "-c", _CHECK, str(path), key, ",".join(symbols), dims]
    try:
        out = subprocess.run(
            cmd, capture_output=True, text=True, timeout=CHECK_TIMEOUT, check=False
        )
    except subprocess.TimeoutExpired:
        return f"its check did not end within {CHECK_TIMEOUT:g} s"
    except OSError as err:
        return f"its check could not run ({err})"
    if out.returncode == 0 and out.stdout.strip() == "ok":
        return None
    if out.returncode < 0:
        try:
            name = signal.Signals(-out.returncode).name
        except ValueError:
            name = f"signal {-out.returncode}"
        return f"it crashed the process that loaded it ({name})"
    lines = (out.stdout.strip() or out.stderr.strip() or "it does not load").splitlines()
    return lines[-1][:300]


def library_problem(
    path: Path, record: Path, key: str, symbols: tuple[str, ...], dims: str
) -> str | None:
    """Why the cached library ``path`` must not be loaded, else ``None`` (see the module
    docstring: owner and mode, the record's key and content hash, the check in a child)."""
    try:
        problem = file_problem(path)
        if problem is not None:
            return problem
        if not os.path.lexists(record):
            return "has no record of its build"
        problem = file_problem(record)
    except OSError as err:
        return f"cannot be read ({err.strerror or err})"
    if problem is not None:
        return f"has a record that {problem}"
    try:
        saved = json.loads(record.read_text())
        recorded_key, digest = saved["key"], saved["sha256"]
    except (OSError, ValueError, KeyError, TypeError):
        return "has a damaged record"
    if recorded_key != key:
        return "has the record of another library"
    try:
        actual = sha256_of(path)
    except OSError as err:
        return f"cannot be read ({err.strerror or err})"
    if actual != digest:
        return "is damaged (its content differs from the SHA-256 recorded when it was built)"
    problem = check_in_child(path, key, symbols, dims)
    return None if problem is None else f"fails its check in a child process: {problem}"
