"""An iterate of the fast SQP as the condensed model evaluates it: the :class:`Rollout` of all
scenarios under one input sequence (states, constraint values, merit) and its
:class:`Linearisation` (sensitivities, constraint Jacobians, cost gradient), dense from NumPy
or causally packed from the C library (:func:`packed_block`)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class Rollout:
    """States, constraint values and merit of all scenarios under one input sequence."""

    u: np.ndarray  # (N nu,) flattened inputs [u_0, u_1, ...]
    X: np.ndarray  # (N+1, nx, Ns) states, component-major per step
    G: np.ndarray  # (ng, N, Ns) constraint values of steps 1..N
    slack: float  # sum of the minimal slacks
    merit: float  # exact-penalty objective (inf if not finite)


@dataclass
class Linearisation:
    """First-order information at a rollout, w.r.t. the flattened inputs ``u``."""

    ro: Rollout
    # (N, Ns, nx, nx) step Jacobians d x_{k+1} / d x_k; None from the C library, which
    # uses each where it computes it (in S and the Hessian's recursion) and stores none
    A: np.ndarray | None
    S: np.ndarray  # (N, Ns, nx, N nu) sensitivities d x_k / d u of steps 1..N, or packed
    Jg: np.ndarray  # (N, Ns, ng, nx) constraint Jacobians at steps 1..N, or packed
    grad: np.ndarray  # (N nu,) gradient of the cost
    # Packed (the C library): S causally, the state of step k + 1 (k from 0) depends on
    # u_0..u_k only, so its block is stored as (Ns, nx, (k + 1) nu), the steps one after
    # another in one flat array; Jg as (N, Ns, nnz), the entries at jg_index of each
    # (ng, nx) Jacobian read row-major (those that can be nonzero).
    packed: bool = False
    jg_index: np.ndarray | None = None
    # Rows of S per scenario and step: nx, or with a feedback prediction nx + nu (below the
    # state's sensitivities those of the input u_{s,k} the scenario applies at that step);
    # 0: nx. The row types of G and Jg are then the state constraints and the input rows.
    rows: int = 0

    def constraint_jacobians(self) -> np.ndarray:
        """``Jg`` as ``(N, Ns, ng, nx)`` (a new array if it is packed; with feedback
        ``(N, Ns, ng + 2 nu, nx + nu)``)."""
        if not self.packed:
            return self.Jg
        n, nx, ns = self.ro.X.shape
        nxs = self.rows or nx
        ng = self.ro.G.shape[0]
        full = np.zeros((n - 1, ns, ng * nxs))
        full[:, :, self.jg_index] = self.Jg
        return full.reshape(n - 1, ns, ng, nxs)

    def sensitivities(self) -> np.ndarray:
        """``S`` as ``(N, Ns, nx, N nu)`` (a new array if it is packed; with feedback
        ``(N, Ns, nx + nu, N nu)``)."""
        if not self.packed:
            return self.S
        n, nx, ns = self.ro.X.shape
        nxs = self.rows or nx
        n -= 1
        nu = self.grad.size // n
        full = np.zeros((n, ns, nxs, n * nu))
        for k in range(n):
            width = (k + 1) * nu
            full[k, :, :, :width] = packed_block(self.S, k, ns, nxs, nu)
        return full


def packed_block(S: np.ndarray, k: int, ns: int, nx: int, nu: int) -> np.ndarray:
    """Step ``k`` (from 0) of a causally packed ``S``: a view ``(Ns, nx, (k + 1) nu)``."""
    start = ns * nx * nu * k * (k + 1) // 2
    width = (k + 1) * nu
    return S[start : start + ns * nx * width].reshape(ns, nx, width)


__all__ = ["Linearisation", "Rollout", "packed_block"]
