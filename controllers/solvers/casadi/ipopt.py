"""CasADi + IPOPT solvers of the scenario MPC problem (paper eq. MPCScen), for any system.

:class:`IpoptScenarioSolver` solves either NLP of :mod:`controllers.solvers.casadi.nlp`: the
condensed one (single shooting, the default: the shared inputs and slacks are the only
variables) or the textbook multiple-shooting one (every scenario's states are variables; the
reference of the benchmark). It builds its NLP once, with the initial states, the latent
forces and the back-off as parameters, and re-solves it at every step with a warm start.
:func:`solve_scenario_problem` solves one problem from a cold start (solvers cached).
"""

from __future__ import annotations

import math
import time
from typing import Any

import casadi as ca
import numpy as np

from controllers.problem import MPCSolution, ScenarioProblem, is_usable
from controllers.solvers.casadi.nlp import build_condensed, build_multiple_shooting, shift_blocks

FORMULATIONS = ("condensed", "multiple_shooting")

DEFAULT_IPOPT_OPTIONS: dict[str, Any] = {
    "print_level": 0,
    "sb": "yes",
    "max_iter": 200,
    "tol": 1e-8,
}

# Previous multipliers are reused only after a solve whose total slack was below this.
WARM_DUALS_MAX_SLACK = 1e-6  # [constraint units]

# Used with the previous multipliers: start close to the central path instead of at
# mu = 0.1, and do not push a good iterate far into the interior.
WARM_START_IPOPT_OPTIONS: dict[str, Any] = {
    "warm_start_init_point": "yes",
    "warm_start_bound_push": 1e-6,
    "warm_start_mult_bound_push": 1e-6,
    "mu_init": 1e-4,
}


class IpoptScenarioSolver:
    """IPOPT solver of a :class:`ScenarioProblem`, built once and re-solved every step.

    Every solve starts from a primal guess (``u_guess``, else the previous plan shifted by
    one step) with the slacks at their minimal values for it. A primal guess alone saves
    IPOPT little (measured at N=7, Ns=150: about 31 instead of 30 iterations), because it
    pushes the iterate into the interior and restarts the barrier at ``mu_init = 0.1``. So
    two IPOPT instances share the NLP: a cold one (IPOPT defaults) and a warm one
    (``warm_start_init_point`` and a small ``mu_init``) that also receives the previous
    multipliers, shifted like the plan: about 16 iterations instead of 30 there. The warm
    one is used only after a successful solve that needed no slack; after solves with
    active slacks the warm start cost iterations instead (measured: 54-63 instead of 34),
    since the penalised constraints change their active set with every draw of ``W``.

    Args:
        problem: the scenario problem (model, cost, horizon, scenario count, penalty).
        formulation: ``"condensed"`` (single shooting, default) or ``"multiple_shooting"``
            (the textbook reference).
        ipopt_options: IPOPT options (names without the ``ipopt.`` prefix) merged over
            :data:`DEFAULT_IPOPT_OPTIONS` (and over :data:`WARM_START_IPOPT_OPTIONS` for
            the warm instance).
        warm_start_duals: pass the previous multipliers to the warm instance; with False
            only the primal guess is warm started.
        max_time: wall-clock limit of one solve [s] (IPOPT's ``max_wall_time``), ``None``
            for none; a solve that reaches it returns its last iterate with
            ``success=False`` and status ``Maximum_WallTime_Exceeded``, and is not retried.
    """

    def __init__(
        self,
        problem: ScenarioProblem,
        formulation: str = "condensed",
        ipopt_options: dict[str, Any] | None = None,
        warm_start_duals: bool = True,
        max_time: float | None = None,
    ) -> None:
        if formulation not in FORMULATIONS:
            raise ValueError(f"formulation={formulation!r}: must be one of {FORMULATIONS}")
        self.problem = problem
        self.formulation = formulation
        self.warm_start_duals = warm_start_duals
        user = dict(ipopt_options or {})
        if max_time is not None:
            user.setdefault("max_wall_time", check_max_time(max_time))
        self.ipopt_options = {**DEFAULT_IPOPT_OPTIONS, **user}
        t0 = time.perf_counter()
        build = build_condensed if formulation == "condensed" else build_multiple_shooting
        self._nlp = build(problem)
        self._cold = self._make_solver("cold", self.ipopt_options)
        self._warm = None
        if warm_start_duals:
            warm_options = {**DEFAULT_IPOPT_OPTIONS, **WARM_START_IPOPT_OPTIONS, **user}
            self._warm = self._make_solver("warm", warm_options)
        self.build_time = time.perf_counter() - t0  # [s]
        self._prev: dict[str, np.ndarray | None] | None = None

    def _make_solver(self, name: str, ipopt_options: dict[str, Any]) -> ca.Function:
        opts = {"ipopt": ipopt_options, "print_time": False, "error_on_fail": False}
        return ca.nlpsol(f"scenario_mpc_{self.formulation}_{name}", "ipopt", self._nlp.nlp, opts)

    @staticmethod
    def _run(
        solver: ca.Function, args: dict[str, np.ndarray], duals: dict[str, np.ndarray]
    ) -> tuple[dict[str, ca.DM] | None, Exception | None, dict[str, Any], float]:
        """One IPOPT call: result (None on an exception), the exception, stats, wall time [s]."""
        error = None
        t0 = time.perf_counter()
        try:
            result = solver(**args, **duals)
        except RuntimeError as exc:  # e.g. a NaN in an evaluation CasADi refuses to pass on
            result, error = None, exc
        solve_time = time.perf_counter() - t0
        return result, error, solver.stats(), solve_time

    @staticmethod
    def _iterate(result: dict[str, ca.DM] | None, z0: np.ndarray) -> np.ndarray:
        """IPOPT's final decision vector, or the initial guess if there is no finite one."""
        z = z0 if result is None else result["x"].full().ravel()
        return z if np.all(np.isfinite(z)) else z0

    def _objective_of(
        self,
        result: dict[str, ca.DM],
        z0: np.ndarray,
        x0: np.ndarray,
        W: np.ndarray,
        backoff: np.ndarray | None,
    ) -> float:
        problem = self.problem
        u = self._iterate(result, z0)[: problem.nu * problem.horizon].reshape(-1, problem.nu)
        return problem.objective(x0, W, problem.system.clip_input(u), backoff)

    def reset(self) -> None:
        """Forget the warm start: the next solve starts cold from zero inputs (clipped)."""
        self._prev = None

    def _initial_guess(
        self,
        x0: np.ndarray,
        W: np.ndarray,
        u_guess: np.ndarray | None,
        backoff: np.ndarray | None = None,
    ) -> tuple[np.ndarray, dict[str, np.ndarray]]:
        """Primal start ``[u, s, states]`` and the multipliers to pass (empty when cold).

        The previous multipliers belong to the previous solution, so they are passed only
        when the primal guess is that solution, shifted (the default) or not (``u_guess``
        equal to the previous ``u``: re-solving the same or a nearby problem).
        """
        problem, n, nlp, prev = self.problem, self.problem.horizon, self._nlp, self._prev
        mode = "cold"
        shifted = None if prev is None else np.concatenate([prev["u"][1:], prev["u"][-1:]])
        if u_guess is not None:
            u0 = u_guess = problem.check_inputs(u_guess, "u_guess")
            if prev is not None and np.array_equal(u_guess, prev["u"]):
                mode = "same"
            elif shifted is not None and np.array_equal(u_guess, shifted):
                mode = "shift"
        elif shifted is not None:
            u0, mode = shifted, "shift"
        else:
            u0 = np.zeros((n, problem.nu))
        u0 = problem.system.clip_input(u0)

        duals: dict[str, np.ndarray] = {}
        if self._warm is not None and mode != "cold" and prev["lam_x"] is not None:
            for key, blocks in (("lam_x", nlp.x_blocks), ("lam_g", nlp.g_blocks)):
                lam = prev[key]
                duals[key + "0"] = shift_blocks(lam, blocks, n) if mode == "shift" else lam

        X = problem.rollout(x0, W, u0)
        parts = [u0.ravel(), problem.minimal_slack(X, backoff).ravel()]
        if self.formulation == "multiple_shooting":
            parts.append(X[:, 1:].transpose(1, 0, 2).ravel())
        return np.concatenate(parts), duals

    def solve(
        self,
        x0: np.ndarray,
        W: np.ndarray,
        u_guess: np.ndarray | None = None,
        backoff: np.ndarray | None = None,
    ) -> MPCSolution:
        """Solve the scenario problem for initial state(s) ``x0`` and latent forces ``W``.

        Args:
            x0: initial state, in the states' units (``system.state_names``), shape
                ``(nx,)`` or ``(Ns, nx)`` (one per scenario).
            W: latent force of each scenario and step, in the force's units, shape
                ``(Ns, N, nw)`` (or ``(Ns, N)`` when ``nw == 1``).
            u_guess: initial input sequence ``(N, nu)`` in the inputs' units; by default
                the previous solution shifted by one step (zero inputs, clipped into the
                bounds, on the first solve).
            backoff: constraint tightening ``(N, ng)`` or ``(ng,)``, ``>= 0``
                (:meth:`ScenarioProblem.check_backoff`); ``None`` for none.

        Returns:
            The solution; ``u`` is clipped into the input bounds, and ``objective`` and
            ``slack`` are :meth:`ScenarioProblem.objective` and the sum of
            :meth:`ScenarioProblem.minimal_slack` evaluated on it, so every solver is compared
            on the same function. A failed solve does not raise: it returns IPOPT's last
            iterate with ``success=False`` and IPOPT's status (``usable`` when its objective
            is below the initial guess's, ``extra["start_objective"]``; IPOPT's iterates
            need not decrease it). A failed warm-started solve
            is retried once cold (``extra["cold_retry"]``); ``solve_time`` and
            ``iterations`` then cover both calls.

        Raises:
            ValueError: on wrongly shaped or non-finite ``x0``, ``W`` or ``u_guess``.
        """
        problem, n, nlp = self.problem, self.problem.horizon, self._nlp
        x0, W = problem.check_data(x0, W)
        b = problem.check_backoff(backoff)
        b_param = np.zeros(problem.ng * n) if b is None else b.ravel()  # (k, j): vec of (ng, N)
        z0, duals = self._initial_guess(x0, W, u_guess, b)
        args = {
            "x0": z0,
            "p": np.concatenate([x0.ravel(), W.ravel(), b_param]),
            "lbx": nlp.lbx,
            "ubx": nlp.ubx,
            "lbg": nlp.lbg,
            "ubg": nlp.ubg,
        }
        result, error, stats_, solve_time = self._run(
            self._warm if duals else self._cold, args, duals
        )
        iterations = _iterations(stats_, error, self.ipopt_options)
        retried = False
        timed_out = stats_.get("return_status") == "Maximum_WallTime_Exceeded"
        if duals and not timed_out and (error is not None or not stats_.get("success", False)):
            # A warm start that fails must not cost the step: retry cold from the same guess,
            # and if that fails too keep whichever iterate has the lower objective.
            warm_run = (result, error, stats_)
            result, error, stats_, more_time = self._run(self._cold, args, {})
            solve_time += more_time
            iterations += _iterations(stats_, error, self.ipopt_options)
            retried = True
            if not (error is None and stats_.get("success", False)) and warm_run[0] is not None:
                warm_obj = self._objective_of(warm_run[0], z0, x0, W, b)
                if result is None or warm_obj < self._objective_of(result, z0, x0, W, b):
                    result, error, stats_ = warm_run

        z = self._iterate(result, z0)
        nu, ng = problem.nu, problem.ng
        u = problem.system.clip_input(z[: nu * n].reshape(n, nu))
        predicted = problem.rollout(x0, W, u)
        slack = float(np.sum(problem.minimal_slack(predicted, b)))
        success = error is None and bool(stats_.get("success", False))
        status = repr(error) if error is not None else str(stats_.get("return_status", "?"))

        # Multipliers of a failed solve are no good start, and neither (measured) are those
        # of a solve with active slacks: the penalised constraints then change their active
        # set with each new draw of W. Keep only the inputs in both cases.
        lam_x = lam_g = None
        if success and slack <= WARM_DUALS_MAX_SLACK:
            lam_x, lam_g = result["lam_x"].full().ravel(), result["lam_g"].full().ravel()
        self._prev = {"u": u, "lam_x": lam_x, "lam_g": lam_g}
        objective = problem.objective(x0, W, u, b)
        # Not converged: usable if below the warm start (IPOPT's iterates need not be).
        start = math.nan if success else problem.objective(x0, W, z0[: nu * n], b)
        return MPCSolution(
            u=u,
            objective=objective,
            slack=slack,
            status=status,
            success=success,
            solve_time=solve_time,
            iterations=iterations,
            predicted=predicted,
            extra={
                "formulation": self.formulation,
                "warm_started_duals": bool(duals),
                "cold_retry": retried,
                "ipopt_objective": math.nan if result is None else float(result["f"]),
                "slacks": z[nu * n : (nu + ng) * n].reshape(n, ng).copy(),
                "start_objective": start,
            },
            usable=is_usable(success, objective, start),
        )


def check_max_time(max_time: Any) -> float:
    """A solve's wall-clock limit [s] as a float, or ``ValueError`` naming ``max_time``."""
    ok = isinstance(max_time, (int, float)) and not isinstance(max_time, bool)
    if not (ok and math.isfinite(max_time) and max_time > 0):
        raise ValueError(f"max_time={max_time!r}: must be a finite number of seconds > 0")
    return float(max_time)


def _iterations(stats_: dict[str, Any], error: Exception | None, options: dict[str, Any]) -> int:
    """IPOPT's iteration count, 0 when it stopped before iterating (``iter_count`` is garbage)."""
    iterations = int(stats_.get("iter_count", 0))
    if error is not None or not 0 <= iterations <= int(options["max_iter"]):
        return 0
    return iterations


_SOLVER_CACHE: dict[tuple[ScenarioProblem, str], IpoptScenarioSolver] = {}
_SOLVER_CACHE_SIZE = 8  # built solvers kept; each holds two IPOPT instances


def solve_scenario_problem(
    problem: ScenarioProblem,
    x0: np.ndarray,
    W: np.ndarray,
    solver: str = "condensed",
    u_guess: np.ndarray | None = None,
) -> MPCSolution:
    """Solve one scenario problem from a cold start (or from ``u_guess``).

    Solvers are cached per ``(problem, formulation)`` so repeated calls do not rebuild the
    NLP; the cached solver's warm start is reset, so each call is independent.

    Args:
        problem: the problem data.
        x0: initial state(s), ``(nx,)`` or ``(Ns, nx)``, in the states' units.
        W: latent forces ``(Ns, N, nw)`` (or ``(Ns, N)`` when ``nw == 1``).
        solver: ``"condensed"`` or ``"multiple_shooting"``.
        u_guess: optional initial inputs ``(N, nu)``.
    """
    key = (problem, solver)
    if key not in _SOLVER_CACHE:
        if len(_SOLVER_CACHE) >= _SOLVER_CACHE_SIZE:
            _SOLVER_CACHE.clear()
        # Each call starts cold, so the warm-start IPOPT instance would never be used.
        _SOLVER_CACHE[key] = IpoptScenarioSolver(
            problem, formulation=solver, warm_start_duals=False
        )
    ipopt = _SOLVER_CACHE[key]
    ipopt.reset()
    return ipopt.solve(x0, W, u_guess=u_guess)


__all__ = [
    "DEFAULT_IPOPT_OPTIONS",
    "FORMULATIONS",
    "WARM_DUALS_MAX_SLACK",
    "WARM_START_IPOPT_OPTIONS",
    "IpoptScenarioSolver",
    "check_max_time",
    "solve_scenario_problem",
]
