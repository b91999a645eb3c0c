"""The C source of a system's library, generated from the system's own expressions.

The pointwise functions (Euler step, its Jacobian, one step of the Hessian's backward
recursion, the constraints, their Jacobian and the Hessian of ``mu' g``) are CasADi functions
of :meth:`ControlSystem.casadi_step` and :meth:`ControlSystem.casadi_constraints`, written as
C by CasADi's ``CodeGenerator`` and, where they allow it, rewritten for vectorised loops
(:mod:`.inline`); the fixed driver around them is the C files of ``c/``
(:func:`c_source`). :mod:`.build` compiles and caches the result.
"""

from __future__ import annotations

import contextlib
import re
from importlib import resources

import casadi as ca
import numpy as np

from controllers.solvers.fast.codegen import interface
from controllers.solvers.fast.codegen.inline import (
    VECTOR_MATH_DECLARATIONS,
    NotInlinable,
    inline_con_jac,
    inline_step,
    inline_step_curv,
    inline_step_jac,
)

# A line of a C file of c/ that stands for another file of that folder (c_source).
_INCLUDE = re.compile(r'^#include "([\w.]+)"[^\n]*\n', re.MULTILINE)
# The C files written from Python tables rather than kept in c/ (c_source inserts them).
GENERATED = {"sqp_interface.h": interface.header}


def c_source(name: str) -> str:
    """The text of the C file ``c/<name>`` beside this module (or of a generated one,
    :data:`GENERATED`), each of its ``#include "..."`` lines replaced by the text of that file
    (a whole translation unit)."""
    if name in GENERATED:
        text = GENERATED[name]()
    else:
        text = (resources.files(__package__) / "c" / name).read_text(encoding="utf-8")
    return _INCLUDE.sub(lambda m: c_source(m.group(1)), text)


def feedback_data_size(system) -> int:
    """The values of a feedback library's data row per step that its generated functions
    read: ``v`` (``nu``), ``K`` (``nu nx``, row-major) and ``r`` (``nx``)."""
    return system.nu + system.nu * system.nx + system.nx


def pointwise_functions(system, dt: float, feedback: bool = False) -> list[ca.Function]:
    """The pointwise CasADi functions of ``system`` the driver calls (dense outputs).

    With ``feedback`` the functions of the closed-loop step of a feedback prediction: their
    ``u`` is the step's data row ``[v, K (nu, nx) row-major, r]``, the scenario applies
    ``v + K (x - r)``, and the Jacobians and Hessians are taken with respect to ``(x, v)``
    (so ``A`` is the closed loop's ``A + B K``); the driver is compiled with
    ``LFM_FEEDBACK``.

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
    if feedback:  # u: the nominal input v; the data row [v, K, r]
        gains, ref = ca.SX.sym("K", nu * nx), ca.SX.sym("r", nx)
        data = ca.vertcat(u, gains, ref)
        applied = u + ca.mtimes(ca.reshape(gains, nx, nu).T, x - ref)
    else:
        data, applied = u, u
    F = system.casadi_step(dt)(x, applied, w)
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
        expr, symbols, values = ca.extract_parametric(ca.cse(d(expr)), data)
        p = ca.vertcat(*symbols) if symbols else ca.SX(0, 1)
        pre = ca.vertcat(*values) if values else ca.SX(0, 1)
        fns.append(ca.Function(f"{name}_pre", [data], [pre]))
        fns.append(ca.Function(name, [x, data, w, p, *extra], [d(expr)]))
    if ng:
        mu = ca.SX.sym("mu", ng)
        g = constraints(x)
        fns += [
            ca.Function("lfm_con_jac", [x], [ca.cse(rows(ca.jacobian(g, x)))]),
            ca.Function("lfm_con_hess", [x, mu], [ca.cse(d(ca.hessian(ca.dot(mu, g), x)[0]))]),
        ]
    return fns


def step_jacobian_pattern(system, dt: float, feedback: bool = False) -> str:
    """C table ``A_NZ`` (``nx * nx``, row-major): 1 where the step's Jacobian ``dF/dx`` can be
    nonzero (CasADi's structural sparsity), 0 where it is zero for every point.

    The linearisation skips the zeros in ``A_k S_k`` (the bicycle's ``A`` has 9 of 16
    nonzeros); the table is a compile-time constant the compiler can fold where it unrolls.
    With ``feedback``, of the closed loop's ``A + B K`` (any ``K``: the pattern of
    :func:`pointwise_functions`'s step).
    """
    nx = system.nx
    step = pointwise_functions(system, dt, feedback)[1]  # lfm_step(x, u or data, w, p)
    x = ca.SX.sym("x", nx)
    args = [ca.SX.sym(f"a{i}", step.size1_in(i)) for i in range(1, step.n_in())]
    sp = ca.jacobian(step(x, *args)[:nx], x).sparsity()
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


def feedback_defines(system) -> str:
    """The sizes and tables of a feedback library (``LFM_FEEDBACK``): the data row's size
    ``ND`` (:func:`feedback_data_size` plus the input weight ``R`` and the rows' flag, see
    ``codegen/c/driver.c``), the row types ``NGR`` (the state constraints, then each input's
    upper and lower row), the rows of the sensitivities ``NXS`` (the state's, then the
    input's), the rows' Jacobian tables ``GR_*`` (an input row has one entry, on its input)
    and the input bounds."""
    nx, nu = system.nx, system.nu
    nnz = int(constraint_jacobian_pattern(system).sum())
    ptr = [0, *np.cumsum(constraint_jacobian_pattern(system).sum(axis=1))]
    ptr += [nnz + q + 1 for q in range(2 * nu)]
    cols = [*(np.flatnonzero(constraint_jacobian_pattern(system)) % nx)]
    cols += [nx + q for q in range(nu)] * 2

    def table(name: str, kind: str, values) -> str:
        return f"static const {kind} {name}[{len(values)}] = {{{', '.join(values)}}};"

    lines = [
        "#define LFM_FEEDBACK 1",
        f"#define NDF {feedback_data_size(system)}",
        f"#define ND (NDF + {nu * nu} + 1)",
        f"#define NGR (NG + {2 * nu})",
        f"#define NXS (NX + {nu})",
        f"#define GR_NNZ (G_NNZ + {2 * nu})",
        table("GR_PTR", "int", [str(int(v)) for v in ptr]),
        table("GR_COL", "int", [str(int(v)) for v in cols]),
        table("U_LO", "double", [_c_double(v) for v in system.input_lower]),
        table("U_HI", "double", [_c_double(v) for v in system.input_upper]),
    ]
    return "\n".join(lines)


OPEN_LOOP_DEFINES = "\n".join(
    [
        "#define ND NU",
        "#define NGR NG",
        "#define NXS NX",
        "#define GR_NNZ G_NNZ",
        "#define GR_PTR G_PTR",
        "#define GR_COL G_COL",
    ]
)


def _c_double(value: float) -> str:
    value = float(value)
    if np.isinf(value):
        return "INFINITY" if value > 0 else "-INFINITY"
    return repr(value)


def library_source(system, dt: float, feedback: bool = False) -> str:
    """The complete C source of ``system``'s C library at time step ``dt`` [s] (with
    ``feedback``, of its feedback prediction: :func:`pointwise_functions`)."""
    # (The generator's name prefixes the generated symbols: part of the source, so of the
    # cache key; kept as it was.)
    cg = ca.CodeGenerator("lfm_kernel.c", {"with_header": False, "casadi_real": "double"})
    fns = pointwise_functions(system, dt, feedback)
    for f in fns:
        cg.add(f)
    sizes = {"NX": system.nx, "NU": system.nu, "NW": system.nw, "NG": system.ng}
    for f in fns:
        if f.name().endswith("_pre"):
            sizes["NP_" + f.name()[4:-4].upper()] = f.nnz_out(0)
    defines = "\n".join(f"#define {k} {v}" for k, v in sizes.items())
    defines += "\n" + step_jacobian_pattern(system, dt, feedback)
    defines += "\n" + constraint_jacobian_table(system)
    defines += "\n" + (feedback_defines(system) if feedback else OPEN_LOOP_DEFINES)
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
