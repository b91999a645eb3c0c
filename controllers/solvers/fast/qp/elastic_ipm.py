"""A structured interior-point solver for the fast SQP's elastic QP, compiled to C.

The QP with slacks of :class:`~controllers.solvers.fast.qp.slot_qp.SlotQP` is::

    min  1/2 d'H d + g'd + sum_c (rho_c s_c + 1/2 r_c s_c^2)
    s.t. a_i'd - s_c(i) <= b_i   (every row i has exactly one slack column c(i))
         s >= 0,  lo <= d <= hi

with ``n`` inputs (14 at N = 7, 60 at N = 30), ``m`` scenario and shared rows and ``G``
slack columns (one per (constraint, step) group and shared row). A general dense solver
(PIQP, qpOASES) factorises a system in all ``n + G`` variables at every iteration; here
the slacks are eliminated, which leaves an ``n x n`` system. With ``D_i`` the scaling of
row ``i`` (its multiplier over its slack, below), ``T_c = sum_{i in c} D_i`` and the weighted
mean row ``abar_c = sum_{i in c} D_i a_i / T_c`` of each group, the reduced matrix is::

    M = H + diag(box terms) + sum_c [ sum_{i in c} D_i (a_i - abar_c)(a_i - abar_c)'
                                      + T_c e_c / (T_c + e_c) abar_c abar_c' ]

where ``e_c = r_c + D_{s_c}`` (the slack's own curvature and its bound's scaling). Written
as this weighted covariance, every term is positive semidefinite: the direct form
``sum D_i a_i a_i' - (sum D_i a_i)(sum D_i a_i)' / k_c`` cancels catastrophically when one
row of a group is strongly active (``D_i`` near ``1e13``). Cost per iteration
``O((m + G) n^2)`` instead of ``O(m (n + G)^2)``.

The method is Mehrotra's predictor-corrector on the primal-dual conditions, started as
CVXOPT's ``coneqp`` does (the Newton system with unit scalings, then slacks and
multipliers shifted to at least one), with a small dual regularisation ``delta``: the row
scalings are ``D = z / (v + delta z)`` (``v`` the row's slack, ``z`` its multiplier), which
bounds them by ``1 / delta``. Without it, the multiplier steps of the strongly active rows
are differences of nearly equal numbers multiplied by ``D`` (up to ~1e17), and the dual
residual grew from 1e-8 to 1e-4 in the last iterations of 38 of 138 recorded QPs at
N = 15. The residuals themselves are computed exactly, so the regularisation changes the
path, not the solution. It stops when the primal and dual
residuals are below ``eps_abs + eps_rel`` times the sums of the absolute values of their
terms (their rounding scale) and the duality gap ``sum v z`` below ``1e-8 + 1e-9`` times
the objective's terms (PIQP's default gap test).

The C source (``controllers/solvers/fast/codegen/c/elastic_ipm.c``) is compiled once with the
C library's compiler and cached like it
(:func:`controllers.solvers.fast.codegen.build.load_library`); without a compiler the SQP uses
PIQP and qpOASES as before (:func:`available`).
"""

from __future__ import annotations

import ctypes
import functools
from dataclasses import dataclass

import numpy as np

from controllers.solvers.fast.codegen.build import (
    CodegenUnavailable,
    address,
    load_library,
)
from controllers.solvers.fast.codegen.source import c_source
from lfm_env.validation import real_vector

# Dual regularisation delta: row scalings z / (v + delta z) stay below 1 / delta. On the
# recorded elastic QPs of N = 15 (138): 0 left 38 unsolved (the dual residual grew in the
# last iterations), 1e-12 none, 1e-10 2 and 1e-8 8 (at the iteration limit: a larger delta
# slows the final convergence).
DUAL_REGULARISATION = 1e-12
MAX_ITERATIONS = 100
# Fraction of the distance to the boundary a step may go.
STEP_FRACTION = 0.995


_STATUS = {
    0: "solved",
    -1: "iteration limit",
    -2: "reduced matrix not positive definite",
    -3: "out of memory",
    -4: "non-finite residual",
}


@dataclass
class ElasticQPResult:
    """The solution of :func:`solve_elastic_qp`."""

    d: np.ndarray  # (n,) the step
    s: np.ndarray  # (G,) the slacks
    z: np.ndarray  # (m,) the rows' multipliers (>= 0)
    iterations: int
    status: str  # "solved" or why not

    @property
    def solved(self) -> bool:
        return self.status == "solved"


@functools.cache
def _library() -> ctypes.CDLL | None:
    """The compiled solver, built at the first call (None when no compiler works)."""
    try:
        # (after a newline, as the library's cache key, a hash of the text, always had it)
        source = "\n" + c_source("elastic_ipm.c")
        lib = load_library(source, "lfm_elastic_qp", symbols=("lfm_elastic_qp",)).lib
    except CodegenUnavailable:
        return None
    L, P, D = ctypes.c_long, ctypes.c_void_p, ctypes.c_double
    lib.lfm_elastic_qp.argtypes = [L, L, L, P, P, P, P, P, P, P, P, P, D, D, D, D, L, P, P, P, P]
    lib.lfm_elastic_qp.restype = ctypes.c_int
    return lib


def available() -> bool:
    """Whether the compiled elastic-QP solver can be used here (a C compiler works)."""
    return _library() is not None


def solve_elastic_qp(
    H: np.ndarray,
    g: np.ndarray,
    lo: np.ndarray,
    hi: np.ndarray,
    A: np.ndarray,
    b: np.ndarray,
    col: np.ndarray,
    rho: np.ndarray,
    reg: np.ndarray,
    eps_abs: float = 1e-9,
    eps_rel: float = 1e-12,
    max_iter: int = MAX_ITERATIONS,
) -> ElasticQPResult:
    """Solve the elastic QP of the module docstring.

    Args:
        H: ``(n, n)`` positive definite Hessian of the step.
        g: ``(n,)`` its gradient.
        lo, hi: ``(n,)`` bounds of the step (``-inf`` / ``inf``: none).
        A: ``(m, n)`` rows; ``b``: ``(m,)`` their bounds.
        col: ``(m,)`` the slack column of each row, in ``[0, G)``.
        rho, reg: ``(G,)`` the slacks' linear (penalty) and quadratic costs, ``reg > 0``.
        eps_abs, eps_rel: tolerances of the primal and dual residuals (relative to the
            sums of their terms' magnitudes).
        max_iter: iteration limit.

    Raises:
        ValueError: on arrays of the wrong shape or a column outside ``[0, G)``.
        CodegenUnavailable: when no C compiler is there (see :func:`available`).
    """
    lib = _library()
    if lib is None:
        raise CodegenUnavailable("the elastic QP solver needs a C compiler (see available())")
    H = np.ascontiguousarray(H, dtype=float)
    n = H.shape[0]
    if H.shape != (n, n):
        raise ValueError(f"H: expected a square matrix, got shape {H.shape}")
    A = np.ascontiguousarray(A, dtype=float).reshape(-1, n)
    m = A.shape[0]
    rho = np.ascontiguousarray(rho, dtype=float)
    G = rho.shape[0]
    col = np.ascontiguousarray(col, dtype=np.int64)
    if col.shape != (m,) or (m and (col.min() < 0 or col.max() >= G)):
        raise ValueError(f"col: expected {m} slack columns in [0, {G}), got {col}")
    args = [real_vector(g, n, "g", finite=False), real_vector(lo, n, "lo", finite=False)]
    args.append(real_vector(hi, n, "hi", finite=False))
    b, reg = real_vector(b, m, "b", finite=False), real_vector(reg, G, "reg", finite=False)
    d, s, z = np.zeros(n), np.zeros(G), np.zeros(m)
    iterations = np.zeros(1, dtype=np.int64)
    code = lib.lfm_elastic_qp(
        n,
        m,
        G,
        address(H),
        *(address(a) for a in args),
        address(A),
        address(b),
        address(col),
        address(rho),
        address(reg),
        float(eps_abs),
        float(eps_rel),
        DUAL_REGULARISATION,
        STEP_FRACTION,
        int(max_iter),
        address(d),
        address(s),
        address(z),
        address(iterations),
    )
    return ElasticQPResult(d, s, z, int(iterations[0]), _STATUS.get(code, f"code {code}"))


__all__ = ["ElasticQPResult", "available", "solve_elastic_qp"]
