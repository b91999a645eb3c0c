"""Definition of the scenario MPC problem (paper eq. MPCScen), independent of any solver.

Every solver in this package (the textbook IPOPT formulation and the fast default)
solves the same :class:`ScenarioProblem` and returns an :class:`MPCSolution`; the
NumPy functions here (:func:`rollout`, :func:`objective`, :func:`constraint_violation`)
are the reference both are checked against.

Conventions (shared by every solver):

* ``x0``: initial physical state ``[p_x, p_y, v, psi]`` [m, m, m/s, rad], shape ``(4,)``
  (same for all scenarios) or ``(Ns, 4)`` (one per scenario).
* ``W``: latent force [m/s^2] of each scenario along the horizon, shape ``(Ns, N)``;
  ``W[i, k]`` acts during step ``k``: ``v_{k+1} = v_k + (a_k + W[i, k]) dt``.
* ``u``: the shared input sequence, shape ``(N, 2)``, rows ``[a_k, delta_k]``.
* Objective: the *average* over scenarios of
  ``sum_{k<N} (x_k - x_g)^T Q (x_k - x_g) + u_k^T R u_k + (x_N - x_g)^T Qf (x_N - x_g)``
  plus ``slack_penalty * sum(s)`` (an exact L1 penalty).
* State constraints (track band, speed bounds, x bounds) apply to ``x_1 ... x_N`` of
  every scenario; input bounds are hard. They are softened by one slack
  ``s[k, j] >= 0`` per step ``k = 1..N`` and constraint kind ``j`` (the six kinds of
  :func:`constraint_values`), shared by all scenarios: ``g_j(x_k^(i)) <= s[k, j]``
  for every ``i``. So there are ``6 N`` slacks whatever ``Ns`` is, and at the optimum
  ``s[k, j] = max(0, max_i g_j(x_k^(i)))``: :func:`objective` evaluates exactly this
  exact-penalty function of ``u``, which every solver must minimise.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from lfm_env.track import SineTrack
from lfm_env.vehicle import euler_step


@dataclass(frozen=True)
class ScenarioProblem:
    """Data of a scenario MPC problem; everything that does not change between steps."""

    horizon: int = 7  # N, prediction steps
    n_scenarios: int = 150  # Ns
    dt: float = 0.2  # [s] sampling time
    vehicle_length: float = 0.5  # [m]
    Q: tuple[float, ...] = (2.0, 2.0, 1.0, 0.0)  # stage weight diagonal on [p_x, p_y, v, psi]
    R: tuple[float, ...] = (0.5, 10.0)  # input weight diagonal on [a, delta]
    Qf: tuple[float, ...] = (2.0, 2.0, 1.0, 0.0)  # terminal weight diagonal
    x_goal: tuple[float, ...] = (62.83, 0.0, 4.0, 0.0)  # [m, m, m/s, rad]
    track: SineTrack = field(default_factory=SineTrack)
    speed_min: float = 0.0  # [m/s]
    speed_max: float = 8.0  # [m/s]
    accel_max: float = 5.0  # [m/s^2], |a| <= accel_max
    steer_max: float = float(np.deg2rad(25.0))  # [rad], |delta| <= steer_max
    slack_penalty: float = 1.0e4  # per metre (or m/s) of total constraint slack

    def __post_init__(self) -> None:
        def check(name: str, ok: bool, allowed: str) -> None:
            if not ok:
                raise ValueError(
                    f"ScenarioProblem.{name}={getattr(self, name)!r}: must be {allowed}"
                )

        def is_int(v: object) -> bool:
            return isinstance(v, (int, np.integer)) and not isinstance(v, bool)

        def is_number(v: object) -> bool:
            return isinstance(v, (int, float, np.integer, np.floating)) and not isinstance(v, bool)

        for name in (
            "dt", "vehicle_length", "speed_min", "speed_max", "accel_max", "steer_max",
            "slack_penalty",
        ):  # fmt: skip
            check(name, is_number(getattr(self, name)), "a real number")
        check("horizon", is_int(self.horizon) and self.horizon >= 1, "an int >= 1")
        check("n_scenarios", is_int(self.n_scenarios) and self.n_scenarios >= 1, "an int >= 1")
        check("dt", np.isfinite(self.dt) and self.dt > 0, "finite and > 0")
        check("vehicle_length", np.isfinite(self.vehicle_length) and self.vehicle_length > 0, "> 0")
        for name, n in (("Q", 4), ("R", 2), ("Qf", 4), ("x_goal", 4)):
            v = np.asarray(getattr(self, name), dtype=float)
            check(name, v.shape == (n,) and bool(np.all(np.isfinite(v))), f"{n} finite numbers")
        for name in ("Q", "R", "Qf"):
            check(name, bool(np.all(np.asarray(getattr(self, name)) >= 0)), "non-negative")
        check("speed_max", self.speed_max > self.speed_min, f"> speed_min={self.speed_min}")
        check("accel_max", np.isfinite(self.accel_max) and self.accel_max > 0, "finite and > 0")
        check("steer_max", 0 < self.steer_max < np.pi / 2, "in (0, pi/2) rad")
        check("slack_penalty", np.isfinite(self.slack_penalty) and self.slack_penalty > 0, "> 0")

    @property
    def input_lower(self) -> np.ndarray:
        """Lower input bounds ``[-a_max, -delta_max]``."""
        return np.array([-self.accel_max, -self.steer_max])

    @property
    def input_upper(self) -> np.ndarray:
        """Upper input bounds ``[a_max, delta_max]``."""
        return np.array([self.accel_max, self.steer_max])

    def check_data(self, x0: np.ndarray, W: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Validate and broadcast ``x0`` to ``(Ns, 4)`` and ``W`` to ``(Ns, N)``."""
        x0 = _as_float_array(x0, "x0")
        W = _as_float_array(W, "W")
        ns, n = self.n_scenarios, self.horizon
        if W.shape != (ns, n):
            raise ValueError(f"W has shape {W.shape}; expected (n_scenarios, horizon) = {(ns, n)}")
        if x0.shape == (4,):
            x0 = np.broadcast_to(x0, (ns, 4))
        if x0.shape != (ns, 4):
            raise ValueError(f"x0 has shape {x0.shape}; expected (4,) or {(ns, 4)}")
        if not (np.all(np.isfinite(x0)) and np.all(np.isfinite(W))):
            raise ValueError("x0 and W must be finite (no NaN or inf)")
        return x0, W


def _as_float_array(value: object, name: str) -> np.ndarray:
    """``value`` as a float array, or a ValueError naming ``name`` (text, objects, complex)."""
    arr = np.asarray(value)
    if arr.dtype.kind not in "biuf":
        raise ValueError(f"{name} must be an array of finite real numbers, got dtype {arr.dtype}")
    return arr.astype(float, copy=False)


@dataclass
class MPCSolution:
    """What a solve returns."""

    u: np.ndarray  # (N, 2) optimal shared input sequence [m/s^2, rad]
    objective: float  # scenario-averaged cost plus slack penalty
    slack: float  # sum of the slacks s[k, j] [m or m/s]; 0 when the hard problem is feasible
    status: str  # solver's return status, e.g. "Solve_Succeeded"
    success: bool  # True when the solver reports convergence
    solve_time: float  # [s] wall time of the solve
    iterations: int  # solver iterations
    predicted: np.ndarray | None = None  # (Ns, N+1, 4) predicted states under u
    extra: dict = field(default_factory=dict)  # solver-specific statistics


def rollout(problem: ScenarioProblem, x0: np.ndarray, W: np.ndarray, u: np.ndarray) -> np.ndarray:
    """Predicted states ``(Ns, N+1, 4)`` of every scenario under inputs ``u`` ``(N, 2)``."""
    x0, W = problem.check_data(x0, W)
    u = np.asarray(u, dtype=float).reshape(problem.horizon, 2)
    X = np.empty((problem.n_scenarios, problem.horizon + 1, 4))
    X[:, 0] = x0
    for k in range(problem.horizon):
        X[:, k + 1] = euler_step(X[:, k], u[k], problem.dt, W[:, k], problem.vehicle_length)
    return X


def constraint_values(problem: ScenarioProblem, X: np.ndarray) -> np.ndarray:
    """State constraint values ``g <= 0`` of predicted states ``X`` ``(Ns, N+1, 4)``.

    Returns ``(Ns, N, 6)``: track upper, track lower, x lower, x upper, speed lower,
    speed upper, for steps ``1..N``.
    """
    Xk = X[:, 1:]
    g_track = problem.track.constraints(Xk)
    v = Xk[..., 2]
    g_speed = np.stack([problem.speed_min - v, v - problem.speed_max], axis=-1)
    return np.concatenate([g_track, g_speed], axis=-1)


def constraint_violation(problem: ScenarioProblem, X: np.ndarray) -> float:
    """Largest state-constraint violation [m or m/s] over all scenarios and steps (0 if none)."""
    return float(max(np.max(constraint_values(problem, X)), 0.0))


def minimal_slack(problem: ScenarioProblem, X: np.ndarray) -> np.ndarray:
    """The smallest feasible slacks ``s[k, j] = max(0, max_i g_j(x_k^(i)))``, shape ``(N, 6)``."""
    return np.maximum(np.max(constraint_values(problem, X), axis=0), 0.0)


def objective(problem: ScenarioProblem, x0: np.ndarray, W: np.ndarray, u: np.ndarray) -> float:
    """Exact-penalty objective of inputs ``u``: the reference every solver minimises.

    Scenario-averaged quadratic cost plus ``slack_penalty * sum(minimal_slack)``.
    """
    X = rollout(problem, x0, W, u)
    slack = float(np.sum(minimal_slack(problem, X)))
    u = np.asarray(u, dtype=float).reshape(problem.horizon, 2)
    e = X - np.asarray(problem.x_goal)
    stage = np.einsum("snj,j,snj->s", e[:, :-1], np.asarray(problem.Q), e[:, :-1])
    terminal = np.einsum("sj,j,sj->s", e[:, -1], np.asarray(problem.Qf), e[:, -1])
    inputs = float(np.einsum("nj,j,nj->", u, np.asarray(problem.R), u))
    return float(np.mean(stage + terminal) + inputs + problem.slack_penalty * slack)


def largest_local_descent(
    problem: ScenarioProblem,
    x0: np.ndarray,
    W: np.ndarray,
    u: np.ndarray,
    radii: tuple[float, ...] = (1e-5, 1e-3),
    n_random: int = 40,
    seed: int = 0,
) -> float:
    """The lowest change of :func:`objective` found next to ``u`` (``>= 0``: none lower).

    A solver-independent check of local optimality: ``u`` is moved along every input
    coordinate in both directions and along ``n_random`` random directions (unit norm),
    by each radius in ``radii`` [m/s^2 and rad alike], clipped to the input bounds, and
    the full objective (every scenario, every constraint, the exact slack penalty) is
    evaluated there. A local minimiser gives a change ``>= 0`` up to rounding (about
    ``1e-12 |objective|``); a point that is not one almost always shows a clear descent.

    Returns:
        ``min(objective(u') - objective(u))`` over the probed points ``u'``.
    """
    u = np.asarray(u, dtype=float)
    base = objective(problem, x0, W, u)
    n_u = u.size
    rng = np.random.default_rng(seed)
    directions = np.concatenate([np.eye(n_u), -np.eye(n_u), rng.standard_normal((n_random, n_u))])
    directions[2 * n_u :] /= np.linalg.norm(directions[2 * n_u :], axis=1, keepdims=True)
    lower = np.broadcast_to(problem.input_lower, u.shape)
    upper = np.broadcast_to(problem.input_upper, u.shape)
    lowest = np.inf
    for radius in radii:
        for d in directions:
            trial = np.clip(u + radius * d.reshape(u.shape), lower, upper)
            lowest = min(lowest, objective(problem, x0, W, trial) - base)
    return float(lowest)
