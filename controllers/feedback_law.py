"""The feedback law of the feedback scenario prediction, and its gains from the model.

With ``ScenarioProblem(..., prediction="feedback")`` scenario ``s`` applies, at step ``k``
of the horizon::

    u_{s,0} = v_0                                   (every scenario, also from particles)
    u_{s,k} = v_k + K_k (x_{s,k} - r_k),   k = 1..N-1

``v`` ``(N, nu)`` is the shared decision (``v_0`` is the input applied now, before any
scenario's deviation is known: no feedback at ``k = 0``); the gains ``K`` ``(N, nu, nx)``
(``K_0 = 0``) and the reference states ``r`` ``(N, nx)`` form a :class:`FeedbackLaw`,
frozen during one solve.

:func:`feedback_law` computes them from the model alone (no system-specific code): ``r``
is the nominal rollout (:func:`nominal_rollout`: the mean initial state under the mean
force of the scenarios) of a reference plan ``u_ref`` (in closed loop: the previous plan's
nominal inputs, shifted by one step), and ``K`` the finite-horizon time-varying LQR
(:func:`tvlqr_gains`) of the cost's ``Q``, ``R``, ``Qf`` on the Jacobians of the model's
Euler step (:meth:`~lfm_env.system.ControlSystem.casadi_step`) along that rollout.

Why these choices (measured; docs/history.md): ``r`` does not change the optimum for a
given ``K`` (``u_{s,k} = (v_k - K_k r_k) + K_k x_{s,k}``: ``r`` only re-parametrises ``v``),
but it sets where ``K`` is linearised, and there it matters: gains along a poor plan (zero
inputs) gave *more* slack than open loop on 12 of 30 paper problems at N = 15, gains along
the previous (or the open-loop) plan on 2. The cost's own weights keep the controller's
trade-offs (more state weight saturates the inputs: more problems infeasible, measured).
"""

from __future__ import annotations

import weakref
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import casadi as ca
import numpy as np

if TYPE_CHECKING:
    from controllers.problem import ScenarioProblem


def _frozen(a: Any, name: str) -> np.ndarray:
    arr = np.asarray(a)
    if arr.dtype.kind not in "biuf":
        raise ValueError(f"FeedbackLaw.{name} must be an array of real numbers, got {arr.dtype}")
    arr = np.array(arr, dtype=float)
    arr.setflags(write=False)
    return arr


@dataclass(frozen=True, eq=False)
class FeedbackLaw:
    """``u_{s,k} = v_k + K[k] (x_{s,k} - r[k])`` for ``k >= 1``; ``u_{s,0} = v_0``.

    Args:
        K: gains ``(N, nu, nx)``, in input units per state unit; ``K[0]`` must be zero (the
            first input is shared by every scenario).
        r: reference states ``(N, nx)`` of steps ``0..N-1``, in the states' units
            (``r[0]`` is not used).

    Raises:
        ValueError: on non-finite entries, inconsistent shapes or ``K[0] != 0``.
    """

    K: np.ndarray
    r: np.ndarray

    def __post_init__(self) -> None:
        K, r = _frozen(self.K, "K"), _frozen(self.r, "r")
        if K.ndim != 3 or r.ndim != 2 or K.shape[0] != r.shape[0] or K.shape[2] != r.shape[1]:
            raise ValueError(
                f"FeedbackLaw: K has shape {K.shape} and r {r.shape}; expected K (N, nu, nx) "
                "and r (N, nx)"
            )
        if K.shape[0] < 1:
            raise ValueError("FeedbackLaw: K and r must have at least one step (N >= 1)")
        if not (np.all(np.isfinite(K)) and np.all(np.isfinite(r))):
            raise ValueError("FeedbackLaw: K and r must be finite (no NaN or inf)")
        if np.any(K[0] != 0.0):
            raise ValueError(
                "FeedbackLaw.K[0] must be zero: the first input is applied now and shared by "
                "every scenario (no feedback at k = 0)"
            )
        object.__setattr__(self, "K", K)
        object.__setattr__(self, "r", r)

    @property
    def horizon(self) -> int:
        """``N``, the steps of the law."""
        return int(self.K.shape[0])

    @classmethod
    def zero(cls, problem: ScenarioProblem) -> FeedbackLaw:
        """No feedback (``K = 0``, ``r = 0``): the open-loop prediction."""
        n, nu, nx = problem.horizon, problem.nu, problem.nx
        return cls(np.zeros((n, nu, nx)), np.zeros((n, nx)))

    def check(self, problem: ScenarioProblem) -> FeedbackLaw:
        """This law, or a ValueError when its shapes do not fit ``problem``."""
        shape = (problem.horizon, problem.nu, problem.nx)
        if self.K.shape != shape:
            raise ValueError(
                f"law.K has shape {self.K.shape}; expected (horizon, nu, nx) = {shape}"
            )
        return self


# The step Jacobians of each problem's model, built once (CasADi expressions).
_JACOBIANS: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def _step_jacobians(problem: ScenarioProblem) -> ca.Function:
    """``(A, B)`` of the Euler step at ``N`` points at once: inputs ``(nx, N)``, ``(nu, N)``,
    ``(nw, N)``; outputs ``(nx, N nx)`` and ``(nx, N nu)`` (blocks per step)."""
    fn = _JACOBIANS.get(problem)
    if fn is None:
        x, u, w = (
            ca.SX.sym(name, size)
            for name, size in (("x", problem.nx), ("u", problem.nu), ("w", problem.nw))
        )
        F = problem.system.casadi_step(problem.dt)(x, u, w)
        one = ca.Function("AB", [x, u, w], [ca.jacobian(F, x), ca.jacobian(F, u)])
        fn = _JACOBIANS[problem] = one.map(problem.horizon)
    return fn


def nominal_rollout(
    problem: ScenarioProblem, x0: np.ndarray, W: np.ndarray, u: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The nominal trajectory of a plan: from the mean initial state under the mean force.

    Args:
        problem: the scenario problem (its model's Euler step).
        x0: initial state(s) ``(nx,)`` or ``(Ns, nx)``, in the states' units.
        W: latent forces ``(Ns, N, nw)`` (or ``(Ns, N)``).
        u: inputs ``(N, nu)``, in the inputs' units.

    Returns:
        ``(X (N+1, nx), w_mean (N, nw))``: the states and the mean force of each step.
    """
    x0, W = problem.check_data(x0, W)
    u = np.asarray(u, dtype=float).reshape(problem.horizon, problem.nu)
    xbar, wbar = x0.mean(axis=0), W.mean(axis=0)
    X = np.empty((problem.horizon + 1, problem.nx))
    X[0] = xbar
    for k in range(problem.horizon):
        X[k + 1] = problem.model.physical_step(X[k], u[k], wbar[k])
    return X, wbar


def tvlqr_gains(
    problem: ScenarioProblem, xr: np.ndarray, ur: np.ndarray, wr: np.ndarray
) -> np.ndarray:
    """Finite-horizon time-varying LQR gains ``K`` ``(N, nu, nx)`` along a trajectory.

    ``A_k, B_k`` are the Jacobians of the model's Euler step at ``(xr[k], ur[k], wr[k])``;
    the weights are the cost's ``Q`` (steps ``0..N-1``), ``Qf`` (step ``N``) and ``R``.
    Backward Riccati recursion, ``P_N = Qf``::

        K_k = -(R + B' P B)^{-1} B' P A
        P_k = Q + K' R K + (A + B K)' P (A + B K)     (Joseph form, symmetrised)

    ``K_0`` is set to zero afterwards (no feedback at the first step). ``R + B' P B`` is
    solved by least squares, so an input with zero weight and no effect gets zero gain.

    Args:
        problem: the scenario problem (model and cost).
        xr: states ``(N+1, nx)`` (only ``0..N-1`` are used).
        ur: inputs ``(N, nu)``.
        wr: forces ``(N, nw)``.
    """
    n, nx, nu = problem.horizon, problem.nx, problem.nu
    A_all, B_all = _step_jacobians(problem)(
        np.asarray(xr, dtype=float)[:n].T, np.asarray(ur, dtype=float).T, np.asarray(wr).T
    )
    A_all = np.asarray(A_all).reshape(nx, n, nx).transpose(1, 0, 2)  # (N, nx, nx)
    B_all = np.asarray(B_all).reshape(nx, n, nu).transpose(1, 0, 2)  # (N, nx, nu)
    cost = problem.cost
    Q, R = cost.Q, cost.R
    K = np.zeros((n, nu, nx))
    P = np.array(cost.Qf, dtype=float)
    for k in range(n - 1, 0, -1):
        A, B = A_all[k], B_all[k]
        K[k] = -np.linalg.lstsq(R + B.T @ P @ B, B.T @ P @ A, rcond=None)[0]
        Acl = A + B @ K[k]
        P = Q + K[k].T @ R @ K[k] + Acl.T @ P @ Acl
        P = 0.5 * (P + P.T)
    return K


def feedback_law(
    problem: ScenarioProblem, x0: np.ndarray, W: np.ndarray, u_ref: np.ndarray
) -> FeedbackLaw:
    """The law of one solve: TV-LQR (:func:`tvlqr_gains`) along the nominal rollout
    (:func:`nominal_rollout`) of the reference plan ``u_ref`` ``(N, nu)`` (clipped into
    the input bounds first); ``r`` is that rollout's states ``0..N-1``.

    Args:
        problem: the scenario problem.
        x0: initial state(s) ``(nx,)`` or ``(Ns, nx)``.
        W: latent forces ``(Ns, N, nw)`` (or ``(Ns, N)``).
        u_ref: the reference plan ``(N, nu)`` in the inputs' units (in closed loop the
            previous plan's nominal inputs shifted by one step).
    """
    u = problem.system.clip_input(problem.check_inputs(u_ref, "u_ref"))
    X, wbar = nominal_rollout(problem, x0, W, u)
    K = tvlqr_gains(problem, X, u, wbar)
    return FeedbackLaw(K=K, r=X[:-1].copy())


def nominal_inputs(
    problem: ScenarioProblem, x0: np.ndarray, W: np.ndarray, v: np.ndarray, law: FeedbackLaw
) -> np.ndarray:
    """The inputs ``(N, nu)`` a feedback plan ``v`` applies along its nominal rollout (mean
    initial state, mean force): the plan an agent keeps, and the next solve's reference
    once shifted. ``nominal_inputs(...)[0] == v[0]``."""
    x0, W = problem.check_data(x0, W)
    law = law.check(problem)
    v = np.asarray(v, dtype=float).reshape(problem.horizon, problem.nu)
    x, wbar = x0.mean(axis=0), W.mean(axis=0)
    U = np.empty_like(v)
    for k in range(problem.horizon):
        U[k] = v[k] + law.K[k] @ (x - law.r[k]) if k else v[0]
        x = problem.model.physical_step(x, U[k], wbar[k])
    return U


def shifted(u: np.ndarray) -> np.ndarray:
    """The plan ``(N, nu)`` one step on: ``u_1 .. u_{N-1}, u_{N-1}``."""
    return np.concatenate([u[1:], u[-1:]])


def reference_plan(
    problem: ScenarioProblem, u_guess: Any, previous: np.ndarray | None
) -> tuple[np.ndarray | None, str]:
    """The reference plan a feedback solve linearises its law along, and where it came from:
    ``u_guess`` when given (``"u_guess"``), else the ``previous`` plan's nominal inputs
    shifted by one step (``"previous_plan"``), else ``None`` (``"law"``: the law was given,
    or the solver solves the open-loop problem first)."""
    if u_guess is not None:
        return problem.check_inputs(u_guess, "u_guess"), "u_guess"
    if previous is not None:
        return shifted(previous), "previous_plan"
    return None, "law"


__all__ = [
    "FeedbackLaw",
    "feedback_law",
    "nominal_inputs",
    "nominal_rollout",
    "reference_plan",
    "shifted",
    "tvlqr_gains",
]
