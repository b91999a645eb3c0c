"""The build of one cached C library, as a process of its own (run by :mod:`.build`).

Started with ``python -I -S`` (it imports the standard library only, nothing from the
working folder or the site) in a session of its own, so neither Ctrl-C nor the end of the
process that asked for the library stops it: a library once started is built to its end and
installed in the cache, atomically, even when the episode that asked for it was cancelled or
stopped waiting (:data:`~.build.COMPILE_WAIT`).

    python -I -S builder_process.py FOLDER NAME C_FILE STALE REQUEST

``FOLDER/NAME.lock`` is taken exclusively for the build (its content: this process's pid and
the build's start, for the processes that wait for it); ``C_FILE`` (the source, written by
the asker in ``FOLDER``) becomes ``NAME.c``, the library ``NAME.so`` with its record
``NAME.json`` (the key and the SHA-256), each written under a temporary name and renamed
into place, the record first. ``STALE`` is what the asker saw at ``NAME.so`` (``-`` for
nothing): a library there now that is not that file and whose record matches was built by
another process meanwhile, and is kept. ``REQUEST`` is JSON: the compiler command, the
builds to try (flags, libraries) and the timeout of one compiler run [s].

Prints one line: ``ok built`` or ``ok cached`` (built by another process meanwhile;
exit 0), ``error: ...`` (the compiler failed, exit 3) or ``oserror: ...`` (the folder
cannot be written, exit 4).
"""

from __future__ import annotations

import fcntl
import hashlib
import json
import os
import re
import subprocess
import sys
import time


def _digest(path: str) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def identity(path: str) -> str:
    """A file's identity (device, inode, size, modification time), ``-`` when absent."""
    try:
        st = os.stat(path)
    except OSError:
        return "-"
    return f"{st.st_dev}:{st.st_ino}:{st.st_size}:{st.st_mtime_ns}"


def _built_meanwhile(target: str, record: str, key: str, stale: str) -> bool:
    """Whether another process installed a library at ``target`` since the asker looked."""
    if identity(target) in ("-", stale):
        return False
    try:
        with open(record) as fh:
            saved = json.load(fh)
        return saved["key"] == key and saved["sha256"] == _digest(target)
    except (OSError, ValueError, KeyError, TypeError):
        return False


def _compiler_error(output: str) -> str:
    lines = [line.strip() for line in output.strip().splitlines() if line.strip()]
    line = next((x for x in lines if "error" in x.lower()), lines[0] if lines else "no output")
    return re.sub(r"^\S+:\d+:(\d+:)?\s*", "", line)[:300]


def _compile(c_file: str, tmp: str, request: dict) -> list[str]:
    """Compile ``c_file`` to ``tmp`` with the first build of ``request`` that works; its
    flags and libraries. Raises RuntimeError with the compiler's first error line."""
    compiler, timeout = request["compiler"], float(request["timeout"])
    out = None
    for flags, libs in request["builds"]:
        cmd = [*compiler, *flags, c_file, "-o", tmp, *libs, "-lm"]
        try:
            out = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)
        except (OSError, subprocess.TimeoutExpired) as err:
            raise RuntimeError(f"compiler {compiler[0]!r} failed to run: {err}") from err
        if out.returncode == 0:
            return [*flags, *libs]
    why = _compiler_error(out.stderr or out.stdout) if out is not None else "no build to try"
    raise RuntimeError(f"compilation with {compiler[0]!r} failed: {why}")


def build(folder: str, name: str, c_file: str, stale: str, request: dict) -> bool:
    """The build (module docstring); the caller holds nothing, this takes the key's lock.
    ``False`` when another process had built the library meanwhile."""
    target = os.path.join(folder, f"{name}.so")
    record = os.path.join(folder, f"{name}.json")
    key = name.rpartition("_")[2]
    tag = f"{os.getpid()}-{os.urandom(4).hex()}"
    tmp = os.path.join(folder, f"{name}.{tag}.so.tmp")
    record_tmp = os.path.join(folder, f"{name}.{tag}.json.tmp")
    lock = os.open(
        os.path.join(folder, f"{name}.lock"), os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW, 0o600
    )
    try:
        fcntl.flock(lock, fcntl.LOCK_EX)
        os.ftruncate(lock, 0)
        os.pwrite(lock, f"{os.getpid()} {time.time():.3f}\n".encode(), 0)
        if _built_meanwhile(target, record, key, stale):
            return False
        flags = _compile(c_file, tmp, request)
        os.chmod(tmp, 0o755)  # (whatever the umask: writable by this user only)
        saved = {
            "key": key,
            "sha256": _digest(tmp),
            "compiler": request["compiler"],
            "flags": flags,
        }
        fd = os.open(record_tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644)
        with os.fdopen(fd, "w") as fh:
            os.fchmod(fd, 0o644)
            fh.write(json.dumps(saved, indent=1) + "\n")
        os.replace(record_tmp, record)
        os.replace(tmp, target)
        os.replace(c_file, os.path.join(folder, f"{name}.c"))
        return True
    finally:
        for leftover in (c_file, tmp, record_tmp):
            try:
                os.unlink(leftover)
            except OSError:
                pass
        os.ftruncate(lock, 0)
        os.close(lock)  # (releases the lock)


def main(argv: list[str]) -> int:
    folder, name, c_file, stale, request = argv[1:6]
    try:
        built = build(folder, name, c_file, stale, json.loads(request))
        result, code = "ok built" if built else "ok cached", 0
    except RuntimeError as err:
        result, code = f"error: {err}", 3
    except OSError as err:
        result, code = f"oserror: {err.strerror or err}", 4
    try:
        print(result, flush=True)
    except OSError:
        pass  # (the asker stopped listening: the library is installed all the same)
    return code


if __name__ == "__main__":
    sys.exit(main(sys.argv))
