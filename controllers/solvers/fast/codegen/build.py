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
the system C compiler (``$CC``, else ``cc``, else ``gcc``; ``-O3 -fPIC -shared``), cached on
disk under ``$LFM_CACHE_DIR`` (default ``~/.cache/lfm-scenario-mpc``) by a hash of its C
source and compile command, written atomically (two processes compiling the same library at
once both end with a valid library), and called through ``ctypes`` on the NumPy arrays
directly (no copies). :func:`build_library` raises :class:`CodegenUnavailable` when no
compiler is found or compilation fails; the caller then falls back to NumPy.
"""

from __future__ import annotations

import contextlib
import ctypes
import hashlib
import os
import re
import shlex
import shutil
import subprocess
import tempfile
import time
from collections.abc import Iterator
from dataclasses import dataclass
from importlib import resources
from pathlib import Path

import casadi as ca
import numpy as np

from controllers.solvers.fast.codegen.inline import (
    VECTOR_MATH_DECLARATIONS,
    NotInlinable,
    inline_con_jac,
    inline_step,
    inline_step_curv,
    inline_step_jac,
)

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
COMPILE_TIMEOUT = 120.0  # [s] a compile taking longer is abandoned (fallback)

# A line of a C file of c/ that stands for another file of that folder (c_source).
_INCLUDE = re.compile(r'^#include "([\w.]+)"\n', re.MULTILINE)

# Loaded libraries of this process, by source hash (a second build is free).
_LOADED: dict[str, ctypes.CDLL] = {}
# The cache directories that replace the configured one inside fresh_cache() (innermost last).
_CACHE_OVERRIDE: list[Path] = []


class CodegenUnavailable(RuntimeError):
    """No C library: no compiler found, compilation failed or the library did not load."""


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
    saved = dict(_LOADED)
    _LOADED.clear()
    with tempfile.TemporaryDirectory(prefix="lfm-codegen-cache-") as tmp:
        _CACHE_OVERRIDE.append(Path(tmp))
        try:
            yield Path(tmp)
        finally:
            _CACHE_OVERRIDE.pop()
            _LOADED.clear()
            _LOADED.update(saved)


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


def c_source(name: str) -> str:
    """The text of the C file ``c/<name>`` beside this module, each of its ``#include "..."``
    lines replaced by the text of that file of the folder (a whole translation unit)."""
    text = (resources.files(__package__) / "c" / name).read_text(encoding="utf-8")
    return _INCLUDE.sub(lambda m: c_source(m.group(1)), text)


def pointwise_functions(system, dt: float) -> list[ca.Function]:
    """The pointwise CasADi functions of ``system`` the driver calls (dense outputs).

    ``lfm_step(x, u, w, p)`` (the next state ``F`` and, with constraints, ``g(F)`` after
    it), ``lfm_step_jac(x, u, w, p)`` (``A`` then ``B``, each flattened row-major) and
    ``lfm_step_curv(x, u, w, p, lam, v)``, each with ``*_pre(u) -> p``: the parts of its
    expression that depend on the input alone (CasADi's ``extract_parametric``), computed once
    per step instead of once per scenario. ``lfm_step_curv`` is one step of the Hessian's
    backward recursion: with ``A``, ``B`` the step's Jacobians, ``M`` the Hessian of
    ``lam' F`` in ``(x, u)`` and ``V`` = ``v`` read row-major ``(nx, nx)``, it returns
    ``[A' V A + M_xx, A' V B + M_xu, B' V B + M_uu, A' lam]`` flattened row-major
    (``nx^2 + nx nu + nu^2 + nx`` values). Written symbolically, the generated code skips
    the Jacobians' structural zeros and shares their subexpressions with ``M``. With
    constraints also ``lfm_con_jac(x)`` ``(ng, nx)`` row-major and ``lfm_con_hess(x, mu)``
    ``(nx, nx)``.
    """
    nx, nu, nw, ng = system.nx, system.nu, system.nw, system.ng
    x, u, w = ca.SX.sym("x", nx), ca.SX.sym("u", nu), ca.SX.sym("w", nw)
    lam, v = ca.SX.sym("lam", nx), ca.SX.sym("v", nx * nx)
    F = system.casadi_step(dt)(x, u, w)
    constraints = system.casadi_constraints() if ng else None
    z = ca.vertcat(x, u)
    d = ca.densify
    J = ca.jacobian(F, z)
    A, B = J[:, :nx], J[:, nx:]
    M = ca.hessian(ca.dot(lam, F), z)[0]
    V = ca.reshape(v, nx, nx).T  # row-major
    AV, BV = ca.mtimes(A.T, V), ca.mtimes(B.T, V)

    def rows(m: ca.SX) -> ca.SX:  # row-major flattening
        return ca.vec(d(m).T)

    curv = ca.vertcat(
        rows(ca.mtimes(AV, A) + M[:nx, :nx]),
        rows(ca.mtimes(AV, B) + M[:nx, nx:]),
        rows(ca.mtimes(BV, B) + M[nx:, nx:]),
        d(ca.mtimes(A.T, lam)),
    )
    fns = []
    for name, expr, extra in (
        ("lfm_step", ca.vertcat(F, constraints(F)) if ng else F, []),
        ("lfm_step_jac", ca.vertcat(rows(A), rows(B)), []),
        ("lfm_step_curv", curv, [lam, v]),
    ):
        # (cse: the derivatives repeat subexpressions; it shortens the generated code, with no
        # measured change in speed: gcc already merged the repeated sines and cosines)
        expr, symbols, values = ca.extract_parametric(ca.cse(d(expr)), u)
        p = ca.vertcat(*symbols) if symbols else ca.SX(0, 1)
        pre = ca.vertcat(*values) if values else ca.SX(0, 1)
        fns.append(ca.Function(f"{name}_pre", [u], [pre]))
        fns.append(ca.Function(name, [x, u, w, p, *extra], [d(expr)]))
    if ng:
        mu = ca.SX.sym("mu", ng)
        g = constraints(x)
        fns += [
            ca.Function("lfm_con_jac", [x], [ca.cse(rows(ca.jacobian(g, x)))]),
            ca.Function("lfm_con_hess", [x, mu], [ca.cse(d(ca.hessian(ca.dot(mu, g), x)[0]))]),
        ]
    return fns


def step_jacobian_pattern(system, dt: float) -> str:
    """C table ``A_NZ`` (``nx * nx``, row-major): 1 where the step's Jacobian ``dF/dx`` can be
    nonzero (CasADi's structural sparsity), 0 where it is zero for every point.

    The linearisation skips the zeros in ``A_k S_k`` (the bicycle's ``A`` has 9 of 16
    nonzeros); the table is a compile-time constant the compiler can fold where it unrolls.
    """
    nx = system.nx
    x, u, w = ca.SX.sym("x", nx), ca.SX.sym("u", system.nu), ca.SX.sym("w", system.nw)
    sp = ca.jacobian(system.casadi_step(dt)(x, u, w), x).sparsity()
    flags = [0] * (nx * nx)
    for r, c in zip(*sp.get_triplet(), strict=True):
        flags[r * nx + c] = 1
    return f"static const char A_NZ[{nx * nx}] = {{{', '.join(map(str, flags))}}};"


def constraint_jacobian_pattern(system) -> np.ndarray:
    """``(ng, nx)`` bool: where the constraints' Jacobian ``dg/dx`` can be nonzero (CasADi's
    structural sparsity), i.e. which states each constraint depends on.

    The C library stores only these entries of each point's constraint Jacobian
    (:func:`constraint_jacobian_table`); the bicycle's six constraints have 8 of 24.
    """
    nx, ng = system.nx, system.ng
    pattern = np.zeros((ng, nx), dtype=bool)
    if ng:
        x = ca.SX.sym("x", nx)
        rows, cols = ca.jacobian(system.casadi_constraints()(x), x).sparsity().get_triplet()
        pattern[rows, cols] = True
    return pattern


def constraint_jacobian_table(system) -> str:
    """C tables of the constraint Jacobian entries the C library stores per point, row by row.

    ``G_NNZ`` entries (those of :func:`constraint_jacobian_pattern`, row-major), constraint
    ``j``'s from ``G_PTR[j]`` to ``G_PTR[j + 1]`` (``G_PTR[NG] = G_NNZ``), each at state
    ``G_COL[e]`` and at ``G_IDX[e]`` of the dense row-major ``(NG, NX)`` matrix (these two
    with one unused entry more, so that neither is empty).
    """
    pattern = constraint_jacobian_pattern(system)
    index = np.flatnonzero(pattern)
    ptr = np.concatenate([[0], np.cumsum(pattern.sum(axis=1))])

    def table(name: str, values) -> str:
        items = ", ".join(str(int(v)) for v in values)
        return f"static const int {name}[{len(values)}] = {{{items}}};"

    lines = [f"#define G_NNZ {index.size}", table("G_PTR", ptr)]
    lines += [table("G_COL", [*(index % system.nx), 0]), table("G_IDX", [*index, 0])]
    return "\n".join(lines)


def library_source(system, dt: float) -> str:
    """The complete C source of ``system``'s C library at time step ``dt`` [s]."""
    # (The generator's name prefixes the generated symbols: part of the source, so of the
    # cache key; kept as it was.)
    cg = ca.CodeGenerator("lfm_kernel.c", {"with_header": False, "casadi_real": "double"})
    fns = pointwise_functions(system, dt)
    for f in fns:
        cg.add(f)
    sizes = {"NX": system.nx, "NU": system.nu, "NW": system.nw, "NG": system.ng}
    for f in fns:
        if f.name().endswith("_pre"):
            sizes["NP_" + f.name()[4:-4].upper()] = f.nnz_out(0)
    defines = "\n".join(f"#define {k} {v}" for k, v in sizes.items())
    defines += "\n" + step_jacobian_pattern(system, dt)
    defines += "\n" + constraint_jacobian_table(system)
    work = " ".join(f"W({f.name()});" for f in fns)
    code = cg.dump()
    by_name = {f.name(): f for f in fns}
    # The vectorisable paths of the rollout, the Hessian and the linearisation (else a call
    # per scenario).
    inline = VECTOR_MATH_DECLARATIONS + "\n"
    with contextlib.suppress(NotInlinable):
        inline += inline_step(code, by_name["lfm_step"], system.nx)
    with contextlib.suppress(NotInlinable):
        inline += inline_step_curv(code, by_name["lfm_step_curv"])
    with contextlib.suppress(NotInlinable):
        inline += inline_step_jac(code, by_name["lfm_step_jac"])
    if "lfm_con_jac" in by_name:
        with contextlib.suppress(NotInlinable):
            inline += inline_con_jac(code, by_name["lfm_con_jac"])
    driver = c_source("driver.c").replace("@WORK@", work)  # (the work-size queries)
    return code + "\n" + defines + "\n" + inline + "\n" + driver


@dataclass
class CompiledLibrary:
    """A loaded C library and how it was obtained."""

    lib: ctypes.CDLL
    path: Path
    key: str  # hash of the C source and compile command
    cache_hit: bool  # found on disk or already loaded (no compiler was run)
    build_time: float  # [s] generation + compilation (or cache lookup) + loading


def _compile(source: str, target: Path, compiler: list[str]) -> None:
    """Compile ``source`` to the shared library ``target``, atomically."""
    target.parent.mkdir(parents=True, exist_ok=True)
    tag = f"{os.getpid()}-{os.urandom(4).hex()}"
    c_file = target.with_name(f"{target.stem}.{tag}.c")
    tmp = target.with_name(f"{target.stem}.{tag}.so.tmp")
    try:
        c_file.write_text(source)
        for flags, libs in BUILDS:  # (without what the compiler or system does not have)
            cmd = [*compiler, *flags, str(c_file), "-o", str(tmp), *libs, "-lm"]
            try:
                out = subprocess.run(
                    cmd, capture_output=True, text=True, timeout=COMPILE_TIMEOUT, check=False
                )
            except (OSError, subprocess.TimeoutExpired) as err:
                raise CodegenUnavailable(f"compiler {compiler[0]!r} failed to run: {err}") from err
            if out.returncode == 0:
                break
        if out.returncode != 0:
            msg = (out.stderr or out.stdout).strip().splitlines()[:3]
            raise CodegenUnavailable(f"compilation with {compiler[0]!r} failed: {msg}")
        os.replace(tmp, target)  # atomic: a concurrent build replaces an equal file
        os.replace(c_file, target.with_suffix(".c"))
    finally:
        for leftover in (c_file, tmp):
            leftover.unlink(missing_ok=True)


def build_library(system, dt: float) -> CompiledLibrary:
    """The C library of ``system`` at time step ``dt`` [s], from the cache if there.

    Raises:
        CodegenUnavailable: no compiler found, compilation failed or the library did not load.
    """
    start = time.perf_counter()
    library = load_library(library_source(system, dt), "lfm_codegen")
    _declare(library.lib)
    library.build_time = time.perf_counter() - start
    return library


def load_library(source: str, stem: str) -> CompiledLibrary:
    """The shared library of the C ``source``, compiled with the C library's compiler and
    flags (:data:`BUILDS`) and cached under :func:`cache_dir` as ``<stem>_<hash>.so``
    (loaded once per process).

    Raises:
        CodegenUnavailable: no compiler found, compilation failed or the library did not load.
    """
    start = time.perf_counter()
    compiler_env = os.environ.get("CC", "")
    flags = " ".join((*FLAGS, OPENMP_FLAG))  # (a build without OpenMP keeps the same key)
    key = hashlib.sha256((source + "\0" + flags).encode()).hexdigest()[:24]
    lib = _LOADED.get(key)
    if lib is not None:
        path = Path(lib._name)
        return CompiledLibrary(lib, path, key, True, time.perf_counter() - start)
    path = cache_dir() / f"{stem}_{key}.so"
    hit = path.is_file()
    if not hit:
        try:
            _compile(source, path, find_compiler())
        except OSError:  # the cache is not writable: compile into a private directory
            path = Path(tempfile.mkdtemp(prefix="lfm-codegen-")) / path.name
            _compile(source, path, find_compiler())
    try:
        lib = ctypes.CDLL(str(path))
    except OSError as err:
        raise CodegenUnavailable(f"cannot load {path}: {err} (CC={compiler_env!r})") from err
    _LOADED[key] = lib
    return CompiledLibrary(lib, path, key, hit, time.perf_counter() - start)


def forget_loaded() -> None:
    """Forget the libraries loaded by this process (the next build looks at the disk again)."""
    _LOADED.clear()


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
    "CodegenUnavailable",
    "CompiledLibrary",
    "address",
    "build_library",
    "c_source",
    "cache_dir",
    "find_compiler",
    "forget_loaded",
    "fresh_cache",
    "library_source",
    "load_library",
    "pointwise_functions",
]
