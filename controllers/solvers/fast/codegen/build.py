"""The fast solver's per-iteration work compiled to C: generated, compiled once, cached.

:class:`~controllers.solvers.fast.condensed.CondensedModel` needs, at every SQP iteration, the
rollout of all scenarios, the step Jacobians, the causal forward sensitivities, the
constraint Jacobians, the cost gradient and the exact Hessian of the Lagrangian (second-order
adjoint). This module generates that work as one C library:

* the pointwise functions (Euler step, its Jacobian, one step of the Hessian's backward
  recursion with the Hessian of ``lambda' F`` inside, the constraints, their Jacobian and the
  Hessian of ``mu' g``) are CasADi functions of the system's own expressions
  (:meth:`ControlSystem.casadi_step`, :meth:`ControlSystem.casadi_constraints`), written as C
  by CasADi's ``CodeGenerator``;
* a fixed driver (the C files of ``codegen/c/``: ``driver.c`` with the row selection
  ``selection.c`` and the Hessian ``hessian.c``, read with :func:`c_source`) loops over the
  steps and scenarios, with the horizon ``N`` and the scenario count ``Ns`` given at run time,
  and skips the structural zeros of the sensitivities (``S_k`` has nonzero columns only for
  inputs before step ``k``).

So one library serves a system and time step at every ``N`` and ``Ns``. It is compiled with
the system C compiler (``$CC``, else ``cc``, else ``gcc``; ``-O3 -fPIC -shared``) and called
through ``ctypes`` on the NumPy arrays directly (no copies). :func:`build_library` raises
:class:`CodegenUnavailable` when no compiler is found or compilation fails; the caller then
falls back to NumPy. A build that failed is not tried again in the same process.

The cache (:func:`load_library`): libraries are kept under ``$LFM_CACHE_DIR`` (default
``~/.cache/lfm-scenario-mpc``) as ``<stem>_<key>.so``, the key a hash of the C source, the
compiler (its command, the resolved executable with its size and modification time) and
the flags of :data:`BUILDS`. Nothing is loaded from there unchecked:

* the folder must be owned by the user and writable by no one else (it is created with mode
  0700; a folder of the user's that others cannot write is tightened to 0700), and none of
  its parents may be writable by others without the sticky bit. Otherwise a one-line
  warning names it and this process builds in a private temporary folder (mode 0700,
  removed at exit) instead; the same when the folder cannot be written;
* a cached library must be a regular file of the user's that no one else can write, with
  its record ``<stem>_<key>.json`` (written at build time) naming its key and the SHA-256
  of its content, and the content must match;
* then a short-lived child process loads it and checks its symbols, the key it was built
  for and, for the system's library, the system's sizes (a damaged file can crash the child,
  never the caller); only then this process loads it.

A library failing a check is rebuilt, with a one-line notice naming it. Builds and loads
of one key take a lock on ``<stem>_<key>.lock`` (exclusive to build, shared to load), so a
library and its record are replaced together and two processes compiling the same library
at once compile it once.

A build runs in a process of its own (:mod:`.builder_process`, in its own session), so it
goes on to its end and its library is installed in the cache, atomically, even when the
process that asked for it stops waiting: its episode ran past its time limit, the run was
interrupted, or the compiler is slower than :func:`compile_wait` (120 s,
``$LFM_COMPILE_TIMEOUT``), after which the asking process (and any other that needs the
library while that build runs) gets :class:`CodegenUnavailable`, and the fast solver its
NumPy backend, with one notice. The evaluation compiles the libraries its agents need before
the first episode's clock starts (:func:`controllers.solvers.fast.prepare.compile_ahead`).
"""

from __future__ import annotations

import atexit
import contextlib
import ctypes
import fcntl
import hashlib
import json
import math
import os
import shlex
import shutil
import stat
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from controllers.solvers.fast.codegen.builder_process import identity
from controllers.solvers.fast.codegen.source import (
    library_source,
)
from controllers.solvers.fast.codegen.trust import folder_problem, library_problem

CACHE_ENV = "LFM_CACHE_DIR"
FLAGS = ("-O3", "-fPIC", "-shared")
# Added when the compiler takes it (the C library's scenario chunks then run in threads,
# CondensedModel.threads); without it the chunks run one after another.
OPENMP_FLAG = "-fopenmp"
# Without OpenMP, its simd pragmas alone (the rollout's vectorised scenario loop).
SIMD_FLAG = "-fopenmp-simd"
# glibc's vector math library for the rollout's vectorised loop (codegen.inline); the link
# must resolve every symbol, so a system without libmvec fails here and builds without it.
VECTOR_MATH_FLAGS = ("-DLFM_VECTOR_MATH",)
VECTOR_MATH_LIBS = ("-lmvec", "-Wl,-z,defs")
# The builds tried in turn, (flags, libraries): the first that compiles is kept.
BUILDS = (
    ((*FLAGS, OPENMP_FLAG, *VECTOR_MATH_FLAGS), VECTOR_MATH_LIBS),
    ((*FLAGS, SIMD_FLAG, *VECTOR_MATH_FLAGS), VECTOR_MATH_LIBS),
    ((*FLAGS, OPENMP_FLAG), ()),
    ((*FLAGS, SIMD_FLAG), ()),
    (FLAGS, ()),
)
COMPILE_TIMEOUT = 120.0  # [s] one compiler run taking longer is abandoned (fallback)
#: [s] a process waits this long for a library's build (``$LFM_COMPILE_TIMEOUT`` changes it),
#: then runs its NumPy backend with one notice; the build goes on and is cached.
COMPILE_WAIT = 120.0
COMPILE_WAIT_ENV = "LFM_COMPILE_TIMEOUT"

# Loaded libraries of this process, by key (a second build is free).
_LOADED: dict[str, ctypes.CDLL] = {}
# Why the build of a key failed in this process: it is not tried again (a full disk or a
# broken compiler would otherwise cost a compile attempt at every agent built).
_FAILED: dict[str, str] = {}
# The one-line notices this process printed (each is printed once).
_NOTICED: set[str] = set()
# This process's private build folder, when the cache folder cannot be used (removed at exit).
_PRIVATE: list[Path] = []
# The cache directories that replace the configured one inside fresh_cache() (innermost last).
_CACHE_OVERRIDE: list[Path] = []


class CodegenUnavailable(RuntimeError):
    """No C library: no compiler found, compilation failed or the library did not load."""


#: The notices shown by this process or the one that started it (hashes; inherited by the
#: processes it starts after a notice): a run's workers do not repeat the run's notice.
NOTICES_ENV = "LFM_NOTICES_SHOWN"


def notice(message: str) -> None:
    """Print ``warning: <message>`` on stderr, once per process for each message, and not
    in a process started after its parent printed it (:data:`NOTICES_ENV`)."""
    tag = hashlib.sha256(message.encode()).hexdigest()[:12]
    shown = [t for t in os.environ.get(NOTICES_ENV, "").split(",") if t]
    if message in _NOTICED or tag in shown:
        return
    _NOTICED.add(message)
    os.environ[NOTICES_ENV] = ",".join([*shown, tag])
    print(f"warning: {message}", file=sys.stderr, flush=True)


def cache_dir() -> Path:
    """The C library cache directory: ``$LFM_CACHE_DIR`` or ``~/.cache/lfm-scenario-mpc``
    (inside :func:`fresh_cache`, its temporary directory)."""
    if _CACHE_OVERRIDE:
        return _CACHE_OVERRIDE[-1]
    env = os.environ.get(CACHE_ENV)
    return Path(env) if env else Path.home() / ".cache" / "lfm-scenario-mpc"


@contextlib.contextmanager
def fresh_cache() -> Iterator[Path]:
    """An empty, temporary C library cache for the duration, yielded as a path.

    A library built inside is compiled anew (the libraries this process has loaded are set
    aside meanwhile, and restored after), so its ``compile_time`` is a cold build's: the
    benchmark measures compilation this way without touching the real cache. Solvers
    built inside keep their loaded library after the directory is removed.
    """
    saved, failed = dict(_LOADED), dict(_FAILED)
    _LOADED.clear()
    _FAILED.clear()
    with tempfile.TemporaryDirectory(prefix="lfm-codegen-cache-") as tmp:
        _CACHE_OVERRIDE.append(Path(tmp))
        try:
            yield Path(tmp)
        finally:
            _CACHE_OVERRIDE.pop()
            _LOADED.clear()
            _LOADED.update(saved)
            _FAILED.clear()
            _FAILED.update(failed)


def find_compiler() -> list[str]:
    """The C compiler command: ``$CC`` if set (only it), else ``cc`` or ``gcc`` on ``PATH``.

    Raises:
        CodegenUnavailable: when that compiler is not found.
    """
    cc = os.environ.get("CC")
    candidates = [shlex.split(cc)] if cc else [["cc"], ["gcc"]]
    for cmd in candidates:
        if cmd and shutil.which(cmd[0]):
            return [shutil.which(cmd[0]) or cmd[0], *cmd[1:]]
    raise CodegenUnavailable(
        f"no C compiler found (CC={cc!r})" if cc else "no C compiler found (cc, gcc on PATH)"
    )


@dataclass
class CompiledLibrary:
    """A loaded C library and how it was obtained."""

    lib: ctypes.CDLL
    path: Path
    key: str  # hash of the C source, the compiler and its flags
    cache_hit: bool  # found on disk or already loaded (no compiler was run by this call)
    build_time: float  # [s] generation + compilation (or cache lookup) + loading


# The entry points of the system's C library (checked before it is loaded).
LIBRARY_SYMBOLS = (
    "lfm_rollout",
    "lfm_linearise",
    "lfm_hessian",
    "lfm_hessian_scratch",
    "lfm_openmp",
    "lfm_vector_math",
    "lfm_linear_change",
    "lfm_rows",
    "lfm_screen",
    "lfm_violated",
)

# Appended to every cached library's source: the key it is built for (and, for a system's
# library, its sizes), read back by the check before it is loaded.
_KEY_FUNCTION = 'const char *lfm_cache_key(void) {{ return "{key}"; }}\n'
_DIMS_FUNCTION = "void lfm_dims(long *d) { d[0] = NX; d[1] = NU; d[2] = NW; d[3] = NG; }\n"


def _compiler_identity(compiler: list[str]) -> list[str]:
    """The compiler as part of the cache key: its command, and its resolved executable with
    that file's size and modification time (an upgraded compiler gets new libraries)."""
    exe = os.path.realpath(compiler[0])
    try:
        st = os.stat(exe)
        signature = f"{exe} {st.st_size} {st.st_mtime_ns}"
    except OSError:
        signature = exe
    return [*compiler, signature]


def cache_key(source: str, compiler: list[str]) -> str:
    """The cache key of a library: a hash of its C source, the compiler (command, executable,
    its size and modification time) and the flags of every build of :data:`BUILDS`."""
    text = "\0".join([source, repr(BUILDS), *_compiler_identity(compiler)])
    return hashlib.sha256(text.encode()).hexdigest()[:24]


def _private_folder() -> Path:
    """This process's private build folder (mode 0700, removed at exit), made once."""
    if not _PRIVATE:
        folder = Path(tempfile.mkdtemp(prefix="lfm-codegen-"))
        _PRIVATE.append(folder)
        atexit.register(shutil.rmtree, folder, True)
    return _PRIVATE[0]


def _cache_folder() -> Path:
    """The cache folder to use: :func:`cache_dir`, created with mode 0700, if it can be
    trusted (:func:`.trust.folder_problem`); otherwise, with a one-line warning naming it, this
    process's private folder."""
    folder = cache_dir()
    try:
        folder.mkdir(parents=True, exist_ok=True, mode=0o700)
        problem = folder_problem(folder)
        st = os.stat(folder)
        if problem is None and stat.S_IMODE(st.st_mode) != 0o700:
            os.chmod(folder, 0o700)  # the user's own, readable by others: made private
    except OSError as err:
        problem = f"cache folder {str(folder)!r} cannot be used ({err.strerror or err})"
    if problem is None:
        return folder
    notice(f"{problem}; not using it: C libraries are built in a private temporary folder")
    return _private_folder()


@contextlib.contextmanager
def _key_lock(folder: Path, name: str) -> Iterator[None]:
    """Hold the lock ``folder/name`` shared for the duration (no build replaces the library
    meanwhile); without one when it cannot be created or taken (a folder this process cannot
    write, which no other process of the user's can write either; a file system without
    locks).

    Raises:
        CodegenUnavailable: a build holds the lock for longer than :func:`compile_wait`
            since it started (it names its start in the lock file).
    """
    try:
        fd = os.open(folder / name, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW, 0o600)
    except OSError:
        yield
        return
    try:
        _wait_for_builds(fd)
        yield
    finally:
        os.close(fd)  # (releases the lock)


def _wait_for_builds(fd: int) -> None:
    """Take the shared lock on ``fd``, waiting for the build that holds it at most until
    :func:`compile_wait` after its start."""
    wait, first = compile_wait(), time.time()
    while True:
        try:
            fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
            return
        except BlockingIOError:
            pass
        except OSError:
            return  # (a file system without locks: none)
        try:
            started = float(os.pread(fd, 100, 0).split()[1])
        except (OSError, ValueError, IndexError):
            started = first  # (the build has not written its start yet)
        if time.time() - started > wait:
            raise CodegenUnavailable(_too_slow(wait))
        time.sleep(0.05)


def compile_wait() -> float:
    """[s] a process waits for the build of a library it needs (:data:`COMPILE_WAIT`, or
    ``$LFM_COMPILE_TIMEOUT``) before it gives it up for its NumPy backend."""
    text = os.environ.get(COMPILE_WAIT_ENV, "")
    try:
        value = float(text)
    except ValueError:
        return COMPILE_WAIT
    return value if math.isfinite(value) and value > 0 else COMPILE_WAIT


def _too_slow(wait: float) -> str:
    """Why a library is not available when its build takes longer than ``wait`` [s] (the
    same text in every process of a run, so the fallback's notice is shown once)."""
    return (
        f"the C compiler did not finish within {wait:g} s (${COMPILE_WAIT_ENV}); the build "
        "goes on in the background and its library is cached for the next run"
    )


# Builds this process stopped waiting for: they go on (kept here, reaped when they end).
_ABANDONED: list[subprocess.Popen] = []


def _build_in_background(
    folder: Path, name: str, source: str, compiler: list[str], stale: str
) -> bool:
    """Build ``folder/name.so`` in a process of its own (:mod:`.builder_process`), which
    goes on to its end whatever happens to this one; wait for it at most
    :func:`compile_wait`. ``True`` if it compiled, ``False`` if another process had built
    the library meanwhile.

    Raises:
        CodegenUnavailable: the compilation failed, or took longer than the wait.
        OSError: ``folder`` cannot be written.
    """
    _ABANDONED[:] = [p for p in _ABANDONED if p.poll() is None]
    c_file = folder / f"{name}.{os.getpid()}-{os.urandom(4).hex()}.c"
    try:
        c_file.write_text(source)
    except OSError:
        c_file.unlink(missing_ok=True)  # (a part written to a full disk)
        raise
    request = {"compiler": compiler, "builds": BUILDS, "timeout": COMPILE_TIMEOUT}
    script = Path(__file__).with_name("builder_process.py")
    cmd = [sys.executable, "-I", "-S", str(script), str(folder), name, str(c_file), stale]
    try:
        proc = subprocess.Popen(
            [*cmd, json.dumps(request)],
            stdin=subprocess.DEVNULL,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            start_new_session=True,  # Ctrl-C of the run does not reach it
        )
    except OSError:
        c_file.unlink(missing_ok=True)
        raise
    _ABANDONED.append(proc)  # (until it has answered below)
    wait = compile_wait()
    try:
        out, err = proc.communicate(timeout=wait)
    except subprocess.TimeoutExpired:
        raise CodegenUnavailable(_too_slow(wait)) from None
    _ABANDONED.remove(proc)
    line = (out.strip().splitlines() or [err.strip()[-300:] or "no answer"])[-1]
    if line.startswith("ok"):
        return line == "ok built"
    if line.startswith("oserror: "):
        raise OSError(line.partition(": ")[2])
    raise CodegenUnavailable(line.partition("error: ")[2] or line)


def build_library(system, dt: float, feedback: bool = False) -> CompiledLibrary:
    """The C library of ``system`` at time step ``dt`` [s], from the cache if there (with
    ``feedback``, the library of its feedback prediction: ``library_source``).

    Raises:
        CodegenUnavailable: no compiler found, compilation failed or the library did not load.
    """
    start = time.perf_counter()
    dims = (system.nx, system.nu, system.nw, system.ng)
    stem = "lfm_feedback" if feedback else "lfm_codegen"
    library = load_library(
        library_source(system, dt, feedback), stem, symbols=LIBRARY_SYMBOLS, dims=dims
    )
    _declare(library.lib)
    library.build_time = time.perf_counter() - start
    return library


def load_library(
    source: str,
    stem: str,
    symbols: tuple[str, ...] = (),
    dims: tuple[int, int, int, int] | None = None,
) -> CompiledLibrary:
    """The shared library of the C ``source``, compiled with the C library's compiler and
    flags (:data:`BUILDS`) and cached under :func:`cache_dir` as ``<stem>_<key>.so``
    (:func:`cache_key`; loaded once per process; checked before it is loaded: see the module
    docstring).

    Args:
        source: the C source.
        stem: the start of the cached files' names.
        symbols: the symbols the library must have (checked before it is loaded).
        dims: ``(nx, nu, nw, ng)`` of a system's library, whose source defines ``NX``,
            ``NU``, ``NW`` and ``NG`` (checked before it is loaded).

    Raises:
        CodegenUnavailable: no compiler found, compilation failed or the library did not
            load (a failed build is not tried again in this process: the same error).
    """
    start = time.perf_counter()
    compiler = find_compiler()
    key = cache_key(source, compiler)
    lib = _LOADED.get(key)
    if lib is not None:
        return CompiledLibrary(lib, Path(lib._name), key, True, time.perf_counter() - start)
    if key in _FAILED:
        raise CodegenUnavailable(_FAILED[key])
    source += "\n" + _KEY_FUNCTION.format(key=key) + (_DIMS_FUNCTION if dims else "")
    check = (symbols, "" if dims is None else ",".join(map(str, dims)))
    try:
        lib, path, hit = _load_or_build(_cache_folder(), f"{stem}_{key}", source, compiler, check)
    except CodegenUnavailable as err:
        _FAILED[key] = str(err)
        raise
    _LOADED[key] = lib
    return CompiledLibrary(lib, path, key, hit, time.perf_counter() - start)


def _load_or_build(
    folder: Path, name: str, source: str, compiler: list[str], check: tuple
) -> tuple[ctypes.CDLL, Path, bool]:
    """The checked library ``folder/name.so``: loaded if a valid one is there, else built
    (in a process of its own: :func:`_build_in_background`; in this process's private
    folder if ``folder`` cannot be written); with the cache hit flag."""
    path, record = folder / f"{name}.so", folder / f"{name}.json"
    key = name.rpartition("_")[2]
    with _key_lock(folder, f"{name}.lock"):
        if os.path.lexists(path):
            problem = library_problem(path, record, key, *check)
            if problem is None:
                return _dlopen(path), path, True
            notice(f"cached C library {str(path)!r} {problem}; building it again")
        stale = identity(str(path))
    try:
        compiled = _build_in_background(folder, name, source, compiler, stale)
    except OSError as err:  # the folder cannot be written (full, read-only, ...)
        private = _private_folder()
        if folder == private:
            raise CodegenUnavailable(f"cannot build the C library: {err}") from err
        why = getattr(err, "strerror", None) or err
        notice(
            f"cache folder {str(folder)!r} cannot be written ({why}); C libraries are built "
            "in a private temporary folder"
        )
        return _load_or_build(private, name, source, compiler, check)
    with _key_lock(folder, f"{name}.lock"):
        problem = library_problem(path, record, key, *check)
        if problem is not None:
            raise CodegenUnavailable(f"the C library just built {problem}")
        return _dlopen(path), path, not compiled


def _dlopen(path: Path) -> ctypes.CDLL:
    try:
        return ctypes.CDLL(str(path))
    except OSError as err:
        raise CodegenUnavailable(f"cannot load {path}: {err}") from err


def forget_loaded() -> None:
    """Forget the libraries loaded by this process and the builds that failed in it (the
    next build looks at the disk again and may compile)."""
    _LOADED.clear()
    _FAILED.clear()


# The driver's arrays (C order): x0T (NX, Ns); W any (strides sa, sk, si of force
# component, step, scenario, in elements); u (N NU); goal (NX);
# Wq (N, NX, NX) state weights of steps 1..N; X (N+1, NX, Ns); G (NG, N, Ns);
# Jg (N, Ns, G_NNZ): of each point's constraint Jacobian (NG, NX) only the entries that can
# be nonzero, row by row (constraint j's from G_PTR[j], each at state G_COL[e]; the tables
# of constraint_jacobian_table); mu (NG, N, Ns); H (N NU, N NU).
# S causally packed: x_{k+1} depends on u_0..u_k only, so step k (from 0) is stored as
# (Ns, NX, (k + 1) NU) from S_OFF(k), the steps one after another (N (N + 1) / 2 NU NX Ns
# values instead of N^2 NU NX Ns; the zeros are never written or read).
def _declare(lib: ctypes.CDLL) -> None:
    """Argument types of the driver's entry points."""
    L, P, D = ctypes.c_long, ctypes.c_void_p, ctypes.c_double
    lib.lfm_rollout.argtypes = [L, L, P, P, L, L, L, P, P, P, P, P, P, L]
    lib.lfm_linearise.argtypes = [L, L, P, P, L, L, L, P, P, P, D, P, P, P, L]
    lib.lfm_hessian.argtypes = [L, L, P, P, L, L, L, P, P, P, P, P, P, D, P, P, L]
    lib.lfm_hessian_scratch.argtypes = [L]
    lib.lfm_hessian_scratch.restype = L
    lib.lfm_openmp.argtypes = []
    lib.lfm_openmp.restype = ctypes.c_int
    lib.lfm_vector_math.argtypes = []
    lib.lfm_vector_math.restype = ctypes.c_int
    lib.lfm_linear_change.argtypes = [L, L, P, P, P, P, P]
    lib.lfm_rows.argtypes = [L, L, P, P, L, P, P]
    lib.lfm_screen.argtypes = [L, L, L, P, P, P, P, D, L, P, L]
    lib.lfm_violated.argtypes = [L, L, L, P, P, P, P, P, P, L, P, D, L, P, L]
    lib.lfm_screen.restype = lib.lfm_violated.restype = ctypes.c_long
    entries = (lib.lfm_rollout, lib.lfm_linearise, lib.lfm_hessian, lib.lfm_linear_change)
    for fn in (*entries, lib.lfm_rows):
        fn.restype = ctypes.c_int


def ptr(a: np.ndarray | None) -> int | None:
    """The data address of a C-contiguous float64 array (``None`` for ``None``)."""
    if a is None:
        return None
    if a.dtype != np.float64 or not a.flags.c_contiguous:
        raise ValueError(f"C library array: must be C-contiguous float64, got {a.dtype}")
    return address(a)


def address(a: np.ndarray) -> int:
    """The data address of a C-contiguous array (checked by the caller)."""
    try:
        # Through the buffer protocol: 0.27 us against 0.95 us for ``a.ctypes.data``
        # (a solve takes a few hundred addresses).
        return ctypes.addressof(ctypes.c_char.from_buffer(a))
    except (TypeError, ValueError):  # read-only or empty: NumPy's own way
        return a.ctypes.data


__all__ = [
    "CACHE_ENV",
    "COMPILE_WAIT",
    "compile_wait",
    "CodegenUnavailable",
    "CompiledLibrary",
    "address",
    "LIBRARY_SYMBOLS",
    "build_library",
    "cache_dir",
    "cache_key",
    "find_compiler",
    "forget_loaded",
    "fresh_cache",
    "load_library",
    "notice",
]
