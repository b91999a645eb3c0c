"""Fast default solver of the scenario MPC problem: a condensed exact-Hessian SQP, for any model.

:class:`FastScenarioSolver` minimises exactly :meth:`ScenarioProblem.objective` (the
scenario-averaged quadratic cost plus the exact L1 penalty on the ``ng N`` shared slacks)
over the shared inputs ``u`` ``(N, nu)``, like the IPOPT reference
(:class:`controllers.solvers.ipopt.IpoptScenarioSolver`), but exploits the structure of
the problem. Everything it knows about the system comes from the system definition
(:class:`lfm_env.system.ControlSystem`) through
:class:`~controllers.solvers.condensed.CondensedModel`:

* **Condensing.** The latent forces ``W`` do not depend on ``u``, so every scenario's
  states are explicit functions of the ``N nu`` inputs. Rollouts use the model's NumPy
  step on all scenarios at once; forward sensitivities and the adjoint sweep use step
  Jacobians and Hessians that CasADi generates from the same right-hand side, evaluated
  on all ``Ns N`` points per call.
* **Exact Hessian.** The Hessian of the Lagrangian with respect to ``u`` (second-order
  adjoint), including the curvature of the dynamics and of the constraints weighted by
  the QP multipliers. When it is indefinite, ``sigma J_A' J_A`` of the constraints
  predicted active is added (which leaves the QP step on that active set unchanged), and
  only if that fails are small eigenvalues raised to a floor.
* **Shared linear rows.** Constraints whose condensed Jacobian is one constant row per
  step for every scenario (found symbolically from the model; the bicycle's speed
  bounds) reduce exactly to the extreme scenario per step: one row each.
* **Screened scenario rows with check-and-add.** The other constraints' rows are limited
  to the few scenarios closest to the current maximum of each (constraint, step), plus
  the scenarios extreme in the states that constraint depends on. After each QP solve the
  linearisation of *every* scenario row is checked at the QP step; violated rows are added
  and the QP re-solved, so the accepted step is exactly the step of the full QP.
* **Exact penalty inside the QP.** One slack per (constraint, step), shared by its rows,
  as in the NLP; a dense QP whose rows keep their slots while they stay in it
  (:class:`~controllers.solvers.slot_qp.SlotQP`), solved by qpOASES with hot starts.
* **Globalisation.** A box trust region on the QP step (a fraction of each input's
  range: shrunk to half the accepted step after backtracking or when the merit falls by
  less than a quarter of what the QP model predicted, doubled after a full step that
  reached it and did better; never below ``min_trust_radius``), inside a backtracking
  Armijo line search on the exact-penalty merit, with a second-order correction against
  the Maratos effect. Where the Hessian had to be floored on negative curvature, the QP
  model is flat in those directions and only the trust region keeps the step from
  running to the input bounds. (``trust_radius=0``: Levenberg-Marquardt damping after
  heavy backtracking instead.) A full step whose merit decrease came close to the linear
  prediction is tried 2, 4, ... times as long while the merit keeps falling
  (``max_expand``): where the model is too curved, full steps otherwise shrink by a
  constant factor and the SQP crawls.
* **Extra starts.** The problem is not convex. A system may declare inputs whose sign
  flip mirrors a manoeuvre (``ControlSystem.mirror_inputs``, the bicycle's steering);
  when a plan uses them hard, the SQP also starts from the mirrored plan (and, with
  slack, from the plan with those inputs at zero), drops an extra start once its local
  model cannot beat the best plan or it heads for that same plan, and keeps the best.

The result is a KKT point of the full scenario problem: started from a local optimum that
IPOPT found, it stays there up to solver tolerances.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from controllers.problem import MPCSolution, ScenarioProblem
from controllers.solvers.condensed import CondensedModel, Linearisation, Rollout
from controllers.solvers.slot_qp import QP_SOLVERS, SlotQP

RESTARTS = ("mirror", "straight")
# How an indefinite Hessian is made positive definite when adding sigma J_A' J_A of the
# predicted active constraints does not do it (see FastScenarioSolver._convexify):
# "floor": negative eigenvalues raised to hessian_floor; "abs": replaced by their absolute
# values (at least the floor); "augmented": the floor applied to the augmented Hessian.
HESSIAN_MODIFICATIONS = ("floor", "abs", "augmented")


@dataclass(frozen=True)
class FastSolverOptions:
    """Settings of the fast SQP solvers; the defaults suit the paper's problem.

    Tolerances are in the units of the inputs and constraints (the paper's problem: m/s^2,
    rad, m, m/s).
    """

    max_iter: int = 50  # SQP iterations per start
    # Predicted merit decrease, relative to the merit, that counts as converged (1e3 times
    # it after a failed line search, where rounding stops the search).
    tol: float = 1e-10
    step_tol: float = 1e-8  # [m/s^2, rad] input step that counts as converged
    final_step_tol: float = 1e-6  # [m/s^2, rad] predicted next step that counts as converged
    screen_margin: float = 0.5  # [m] rows within this of activity enter the QP at once
    screen_rows: int = 4  # scenario rows per (constraint, step) screened or added per round
    add_tol: float = 1e-9  # [m] linearised violation of a missing row that adds it
    max_qp_rounds: int = 20  # check-and-add rounds per SQP iteration
    armijo: float = 1e-4  # sufficient-decrease fraction of the predicted decrease
    backtrack: float = 0.5  # step shrink factor of the line search
    min_step: float = 1e-8  # smallest line-search step before giving up
    hessian_floor: float = 1e-3  # smallest Hessian eigenvalue [per (m/s^2)^2 or rad^2]
    slack_regularisation: float = 1e-8  # quadratic weight on the QP slacks (strict convexity)
    second_order_correction: bool = True  # against the Maratos effect
    damping_init: float = 1.0  # first Levenberg-Marquardt damping (trust_radius=0 only)
    damping_threshold: float = 0.1  # line-search step below which the damping grows
    damping_decrease: float = 0.1  # factor on the damping after a full step
    # One of QP_SOLVERS; "auto": qpOASES on small QPs, PIQP on large ones (slot_qp).
    qp_solver: str = "auto"
    hessian_modification: str = "floor"  # one of HESSIAN_MODIFICATIONS
    # Expansion of a full step that decreased the merit by at least expand_ratio times the
    # linear prediction (the model's curvature along it is too high, e.g. after a negative
    # eigenvalue was raised): steps 2, 4, ... times as long while the merit keeps falling,
    # at most max_expand doublings (0: none). Against the linear crawl of full steps that
    # each shrink by a constant factor; not tried while steps shrink fast (a QP step below
    # half the last full step), where it would only cost merit evaluations.
    max_expand: int = 4
    expand_ratio: float = 0.75
    # Extra starts against local optima (see FastScenarioSolver.solve): any of RESTARTS.
    restarts: tuple[str, ...] = ("mirror", "straight")
    restart_threshold: float = 0.35  # fraction of a mirrored input's bound that calls for them
    restart_probe: int = 1  # SQP iterations an extra start runs before it may be given up
    restart_optimism: float = 2.0  # multiple of the model's predicted decrease it may still get
    restart_margin: float = 0.0  # relative margin added to the merit an extra start must beat
    restart_same_tol: float = 0.05  # [m/s^2, rad] an extra start this close to the best: same
    # Initial box trust region on the QP step, |d_i| <= radius * (upper_i - lower_i) (a
    # fraction of each input's range): shrunk to half the accepted step (not below
    # min_trust_radius) after backtracking or when the merit fell by less than 1/4 of the
    # QP model's prediction, doubled (up to 1) after a full step that reached it and fell
    # by more. 0: no trust region; Levenberg-Marquardt damping (damping_*) after heavy
    # backtracking instead.
    trust_radius: float = 0.25
    # Smallest trust radius: below it the line search alone handles a poor model, so the
    # trust region never holds back the fast local convergence near a solution.
    min_trust_radius: float = 1e-3
    # Wall-clock limit of one solve [s], checked between SQP iterations: a solve that
    # reaches it returns its best iterate with success=False, status
    # "Maximum_WallTime_Exceeded" (IPOPT's name), and tries no further start.
    max_time: float = math.inf

    def __post_init__(self) -> None:
        def check(name: str, ok: bool, allowed: str) -> None:
            if not ok:
                raise ValueError(
                    f"FastSolverOptions.{name}={getattr(self, name)!r}: must be {allowed}"
                )

        for name in ("max_iter", "screen_rows", "max_qp_rounds", "restart_probe"):
            value = getattr(self, name)
            check(name, isinstance(value, int) and value >= 1, "an int >= 1")
        for name in (
            "tol",
            "step_tol",
            "final_step_tol",
            "screen_margin",
            "add_tol",
            "min_step",
            "hessian_floor",
            "slack_regularisation",
            "damping_init",
            "restart_optimism",
            "restart_same_tol",
        ):
            value = getattr(self, name)
            ok = isinstance(value, (int, float)) and math.isfinite(value) and value > 0
            check(name, ok, "finite and > 0")
        check("armijo", 0 < self.armijo < 0.5, "in (0, 0.5)")
        check("backtrack", 0 < self.backtrack < 1, "in (0, 1)")
        check("damping_threshold", 0 < self.damping_threshold <= 1, "in (0, 1]")
        check("damping_decrease", 0 <= self.damping_decrease < 1, "in [0, 1)")
        for name in ("trust_radius", "min_trust_radius"):
            value = getattr(self, name)
            ok = isinstance(value, (int, float)) and not isinstance(value, bool) and 0 <= value <= 1
            check(name, ok, "in [0, 1] (a fraction of each input's range; 0: none)")
        ok = self.trust_radius == 0 or self.min_trust_radius <= self.trust_radius
        check("min_trust_radius", ok, f"<= trust_radius ({self.trust_radius})")
        value = self.max_time
        ok = isinstance(value, (int, float)) and not isinstance(value, bool) and value > 0
        check("max_time", ok and not math.isnan(value), "a number of seconds > 0 (inf: none)")
        check("qp_solver", self.qp_solver in QP_SOLVERS, f"one of {QP_SOLVERS}")
        ok = self.hessian_modification in HESSIAN_MODIFICATIONS
        check("hessian_modification", ok, f"one of {HESSIAN_MODIFICATIONS}")
        ok = isinstance(self.max_expand, int) and not isinstance(self.max_expand, bool)
        check("max_expand", ok and self.max_expand >= 0, "an int >= 0")
        check("expand_ratio", 0 < self.expand_ratio <= 1, "in (0, 1]")
        if isinstance(self.restarts, list):
            object.__setattr__(self, "restarts", tuple(self.restarts))
        ok = isinstance(self.restarts, tuple) and all(r in RESTARTS for r in self.restarts)
        check("restarts", ok, f"a tuple of names from {RESTARTS}")
        margin = self.restart_margin
        ok = isinstance(margin, (int, float)) and math.isfinite(margin) and margin >= 0
        check("restart_margin", ok, "finite and >= 0")
        value = self.restart_threshold
        ok = isinstance(value, (int, float)) and 0 < value <= 1
        check("restart_threshold", ok, "in (0, 1]")


@dataclass
class _QPStep:
    """Solution of one SQP subproblem."""

    d: np.ndarray  # (N nu,) input step
    slack_sum: float  # sum of the QP's slacks
    pos: np.ndarray  # (r, 3) scenario rows (constraint, step, scenario) in the QP
    lam: np.ndarray  # (r,) their multipliers
    qp: SlotQP  # the QP object (for a second-order correction)
    row: np.ndarray  # (r,) their row slots in it
    s_pos: np.ndarray  # (ng, N) slack of each (constraint, step) group
    s_shared: np.ndarray  # (n_shared,) slack of each shared row, ordered (step, constraint)
    lam_shared: np.ndarray  # (n_shared,) multipliers of the shared rows
    curvature: float = 0.0  # d' H_qp d of the QP's (convexified) Hessian


class FastScenarioSolver:
    """Condensed exact-Hessian SQP solver of any :class:`ScenarioProblem`.

    The model's derivatives come from :attr:`model_class` (generated from the system
    definition by default; :mod:`controllers.solvers.fast_bicycle` swaps in hand-written ones).

    Same interface and result semantics as :class:`controllers.solvers.ipopt.IpoptScenarioSolver`:
    build once, call :meth:`solve` at every step; the previous solution shifted by one
    step is the default initial guess.

    Args:
        problem: the problem (its model's system gives every expression).
        **options: fields of :class:`FastSolverOptions` (e.g. ``max_iter=30``).

    Raises:
        ValueError: on an unknown or out-of-range option.
    """

    model_class: type[CondensedModel] = CondensedModel

    def __init__(self, problem: ScenarioProblem, **options: Any) -> None:
        unknown = set(options) - set(FastSolverOptions.__dataclass_fields__)
        if unknown:
            raise ValueError(f"unknown {type(self).__name__} options: {sorted(unknown)}")
        self.problem = problem
        self.options = FastSolverOptions(**options)
        self.model = m = self.model_class(problem)
        n = problem.horizon
        self._n_u = m.n_u
        self._lower, self._upper = m.lower, m.upper
        # Shared rows ordered (step, shared constraint).
        n_l = m.shared.size
        self._n_shared = n_l * n
        self._a_shared = m.shared_rows.transpose(1, 0, 2).reshape(n * n_l, m.n_u)
        self._screened = m.screened
        self._n_groups = max(m.screened.size * n, 1)
        self._qps: dict[tuple[int, int], SlotQP] = {}
        self._prev_u: np.ndarray | None = None
        self._deadline = math.inf  # time.perf_counter() value ending the current solve
        # (N nu,) each input's range; inf where it has none (an unbounded input gets no
        # trust region, a fixed one needs none)
        span = self._upper - self._lower
        self._range = np.where(np.isfinite(span) & (span > 0), span, np.inf)
        self._radius = 0.0  # current trust radius (fraction of the range; 0: none)
        # A list to record one dict per SQP iteration into (diagnostics), or None.
        self.trace: list[dict[str, Any]] | None = None

    @property
    def backend(self) -> str:
        """How the derivatives are evaluated: ``"numpy"`` lanes, ``"casadi_map"`` or
        ``"hand_written"`` (the bicycle's cache)."""
        return self.model.backend

    # ------------------------------------------------------------------ public API

    def reset(self) -> None:
        """Forget the warm start: the next solve starts from zero inputs."""
        self._prev_u = None

    def __getstate__(self) -> dict[str, Any]:
        # The QP objects hold raw buffers of a CasADi function, the model generated code:
        # rebuild them after unpickling (e.g. in a worker process).
        state = self.__dict__.copy()
        state["_qps"] = {}
        state["model"] = None
        return state

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__dict__.update(state)
        self.model = self.model_class(self.problem)

    def solve(
        self,
        x0: np.ndarray,
        W: np.ndarray,
        u_guess: np.ndarray | None = None,
        backoff: np.ndarray | None = None,
    ) -> MPCSolution:
        """Solve the scenario problem for initial state(s) ``x0`` and latent forces ``W``.

        Args:
            x0: initial state ``(nx,)`` or ``(Ns, nx)``, in the states' units.
            W: latent forces ``(Ns, N, nw)`` (or ``(Ns, N)`` for one component).
            u_guess: initial input sequence ``(N, nu)``; by default the previous solution
                shifted by one step (zeros clipped into the bounds on the first solve).
            backoff: constraint tightening ``(N, ng)`` or ``(ng,)``, ``>= 0``
                (:meth:`ScenarioProblem.check_backoff`); ``None`` for none.

        Returns:
            The solution: ``u`` inside the input bounds; ``objective``, ``slack`` and
            ``predicted`` those of :class:`ScenarioProblem` (``objective``,
            ``minimal_slack`` summed, ``rollout``) for ``u``, computed by the solver's own
            vectorised rollout (equal up to rounding); ``solve_time`` the wall time of the
            whole call; ``extra`` counts QP solves (``qp_solves``), the most QP rows
            (``qp_rows``), QP calls retried after a failure (``qp_retries``), iterations
            whose check-and-add rounds ran out (``qp_rounds_exhausted``), merit
            evaluations and second-order corrections, names the derivative backend
            (``backend``) and the QP solver option (``qp_solver``) with the QP calls
            per solver it resolved to (``qp_calls``, e.g. ``{"qpoases": 12}``), gives the
            first start's ``{"status", "iterations"}`` (``first_start``), and
            ``extra["restarts"]`` maps each extra start tried to ``"kept"`` or the status it
            ended with; ``iterations`` counts the iterations of every start. A solve
            that does not converge does not raise: it returns the best iterate (the merit
            decreases monotonically) with ``success=False``.

        Extra starts: when the first plan drives an input of ``system.mirror_inputs``
        beyond ``restart_threshold`` of its bound, the SQP also starts from that plan with
        those inputs negated (``"mirror"``) and, if the plan needs slack, with them at zero
        (``"straight"``). After ``restart_probe`` iterations an extra start is abandoned as
        soon as its merit plus ``restart_optimism`` times the decrease its local model
        predicts still lies above the best plan so far; the plan with the lowest objective
        is returned (a failed start never replaces a successful one); an extra start that
        comes within ``restart_same_tol`` of the best plan is stopped too.

        Raises:
            ValueError: on wrongly shaped or non-finite ``x0``, ``W`` or ``u_guess``.
        """
        t_start = time.perf_counter()
        problem, n, nu = self.problem, self.problem.horizon, self.problem.nu
        x0, W = problem.check_data(x0, W)
        b = problem.check_backoff(backoff)
        if u_guess is not None:
            u0 = problem.check_inputs(u_guess, "u_guess").ravel()
        elif self._prev_u is not None:
            u0 = np.concatenate([self._prev_u[1:], self._prev_u[-1:]]).ravel()
        else:
            u0 = np.zeros(n * nu)
        u0 = np.clip(u0, self._lower, self._upper)

        data = _Data(
            x0T=np.ascontiguousarray(x0.T),
            W=np.ascontiguousarray(W.transpose(1, 0, 2)),
            W_lanes=np.ascontiguousarray(W.transpose(2, 1, 0)),
            cost0=self.model.state_cost0(x0),
            backoff=None if b is None else np.ascontiguousarray(b.T[:, :, None]),
        )
        deadline = t_start + self.options.max_time
        for qp in self._qps.values():  # no hot start carries over from another problem
            qp.reset()
        ro, status, success, iterations, extra = self._sqp(data, u0, deadline=deadline)
        first_status, first_iterations = status, iterations
        extra["restarts"] = {}
        for name in self._restart_names(ro):
            if time.perf_counter() >= deadline:
                extra["restarts"][name] = "no_time"
                continue
            # The problem is not convex: try another start, abandon it once it cannot
            # plausibly beat the best plan so far, and keep the better plan.
            u_alt = self._restart_guess(name, ro.u)
            bar = ro.merit + self.options.restart_margin * abs(ro.merit)
            ro2, status2, success2, iterations2, extra2 = self._sqp(
                data, u_alt, bar, ro.u, deadline=deadline
            )
            iterations += iterations2
            for key in (
                "qp_solves",
                "qp_retries",
                "qp_rounds_exhausted",
                "soc_steps",
                "merit_evals",
            ):
                extra[key] += extra2[key]
            extra["qp_rows"] = max(extra["qp_rows"], extra2["qp_rows"])
            for key, count in extra2["qp_calls"].items():
                extra["qp_calls"][key] = extra["qp_calls"].get(key, 0) + count
            better = ro2.merit < ro.merit - 1e-12 * (1.0 + abs(ro.merit))
            keep = better and (success2 or not success)
            extra["restarts"][name] = "kept" if keep else status2.lower()
            if keep:
                ro, status, success = ro2, status2, success2
        extra["backend"] = self.backend
        extra["qp_solver"] = self.options.qp_solver
        extra["first_start"] = {"status": first_status, "iterations": first_iterations}

        u = ro.u.reshape(n, nu).copy()
        self._prev_u = u.copy()
        return MPCSolution(
            u=u,
            objective=ro.merit,
            slack=ro.slack,
            status=status,
            success=success,
            solve_time=time.perf_counter() - t_start,
            iterations=iterations,
            predicted=np.ascontiguousarray(ro.X.transpose(2, 0, 1)),
            extra=extra,
        )

    # ------------------------------------------------------------------ extra starts

    def _restart_names(self, ro: Rollout) -> list[str]:
        """The extra starts worth trying after a first plan ``ro`` (see :meth:`solve`)."""
        opt, system = self.options, self.problem.system
        mirrored = list(system.mirror_inputs)
        if not mirrored or not opt.restarts:
            return []
        nu = self.problem.nu
        frac = opt.restart_threshold - 1e-6
        u = ro.u.reshape(-1, nu)[:, mirrored]
        lower, upper = frac * system.input_lower[mirrored], frac * system.input_upper[mirrored]
        hard = bool(np.any((u <= lower) | (u >= upper)))
        names = []
        if "mirror" in opt.restarts and hard:
            names.append("mirror")
        if "straight" in opt.restarts and hard and ro.slack > opt.add_tol:
            names.append("straight")
        return names

    def _restart_guess(self, name: str, u: np.ndarray) -> np.ndarray:
        """Initial guess of the extra start ``name`` from the plan ``u`` ``(N nu,)``."""
        guess = u.copy().reshape(-1, self.problem.nu)
        mirrored = list(self.problem.system.mirror_inputs)
        if name == "mirror":  # the same manoeuvre, the other way
            guess[:, mirrored] *= -1.0
        else:  # "straight": the other inputs kept, the mirrored ones at zero
            guess[:, mirrored] = 0.0
        return np.clip(guess.ravel(), self._lower, self._upper)

    # ------------------------------------------------------------------ convexification

    def _convexify(
        self,
        H: np.ndarray,
        lin: Linearisation,
        active_pos: np.ndarray,
        active_shared: np.ndarray,
        active_bounds: np.ndarray,
    ) -> tuple[np.ndarray, float, np.ndarray]:
        """A positive definite QP Hessian that leaves the Newton step unchanged if it can.

        The Lagrangian's Hessian is often indefinite although it is positive definite on
        the null space of the active constraints (second-order sufficiency). Adding
        ``sigma J_A' J_A`` for the constraints ``A`` predicted active (hard-active rows and
        input bounds of the previous QP) then makes it positive definite without changing
        the QP's solution on that active set: only its multipliers shift, by
        ``sigma J_A d``. If that is not enough, eigenvalues below ``hessian_floor`` are
        raised to it.

        Returns:
            ``(H_qp, sigma, J_pos)`` with ``J_pos`` the Jacobian rows of ``active_pos``
            (``sigma = 0`` when no augmentation was used).
        """
        floor = self.options.hessian_floor
        w, V = np.linalg.eigh(H)
        self._last_eig = (float(w[0]), float(w[-1]))
        j_pos = np.empty((0, self._n_u))
        if w[0] >= floor:
            return H, 0.0, j_pos
        rows = []
        if active_pos.shape[0]:
            j_pos = self.model.rows(lin, active_pos)[0]
            rows.append(j_pos)
        if active_shared.size:
            rows.append(self._a_shared[active_shared])
        if active_bounds.size:
            rows.append(np.eye(self._n_u)[active_bounds])
        if rows:
            J = np.vstack(rows)
            G = J.T @ J
            sigma = float(np.max(np.abs(w))) / max(float(np.max(np.diag(G))), 1e-12)
            for _ in range(4):
                H_aug = H + sigma * G
                w_aug, V_aug = np.linalg.eigh(H_aug)
                if w_aug[0] >= floor:
                    return H_aug, sigma, j_pos
                if self.options.hessian_modification == "augmented":
                    # Negative curvature left on the active constraints' null space: raise
                    # only those eigenvalues, keeping the constraints' own curvature.
                    return (V_aug * np.maximum(w_aug, floor)) @ V_aug.T, sigma, j_pos
                sigma *= 10.0
        if self.options.hessian_modification == "abs":
            return (V * np.maximum(np.abs(w), floor)) @ V.T, 0.0, j_pos
        return (V * np.maximum(w, floor)) @ V.T, 0.0, j_pos

    # ------------------------------------------------------------------ QP subproblem

    def _qp(self, rows: int, groups: int) -> SlotQP:
        """The cached QP with room for ``rows`` scenario rows in ``groups`` groups.

        Capacities are rounded up to powers of two, so a few QP objects serve every solve
        and each keeps its own hot-start information and slot assignment.
        """
        groups = min(max(4, 1 << (groups - 1).bit_length()), self._n_groups)
        rows = max(8, 1 << (rows - 1).bit_length())
        key = (rows, groups)
        qp = self._qps.get(key)
        if qp is None:
            p, opt = self.problem, self.options
            qp = SlotQP(
                self._n_u,
                self._n_shared,
                rows,
                groups,
                opt.qp_solver,
                p.slack_penalty,
                opt.slack_regularisation,
                max_time=opt.max_time,
            )
            self._qps[key] = qp
        return qp

    def _screen(self, ro: Rollout) -> np.ndarray:
        """Initial scenario rows ``(r, 3)`` of ``(constraint, step index, scenario)``.

        In every (constraint, step) group whose largest value lies within
        ``screen_margin`` of activity: the ``screen_rows`` largest values within that
        margin, the scenario with the smallest value, and the scenarios extreme in each
        state the constraint depends on (scenarios differ mostly in how far they get along
        similar paths, so a step can make the other end of that family the worst one).
        """
        opt, m = self.options, self.model
        screened = self._screened
        if screened.size == 0:
            return np.empty((0, 3), dtype=int)
        n = self.problem.horizon
        G = ro.G[screened].reshape(screened.size * n, -1)
        ns = G.shape[1]
        active = np.nonzero(G.max(axis=1) >= -opt.screen_margin)[0]
        if active.size == 0:
            return np.empty((0, 3), dtype=int)
        Ga = G[active]
        keep = min(opt.screen_rows, ns)
        top = np.argpartition(Ga, ns - keep, axis=1)[:, ns - keep :]
        near = np.take_along_axis(Ga, top, axis=1) >= -opt.screen_margin
        sub, col = np.nonzero(near)
        flat = [active[sub] * ns + top[sub, col], active * ns + Ga.argmin(axis=1)]
        step = active % n
        j_of = screened[active // n]
        X = ro.X[1:]  # (N, nx, Ns)
        for state in range(self.problem.nx):
            users = m.depends[j_of, state]
            if users.any():
                steps = step[users]
                flat.append(active[users] * ns + X[steps, state].argmax(axis=1))
                flat.append(active[users] * ns + X[steps, state].argmin(axis=1))
        group, scen = np.divmod(np.unique(np.concatenate(flat)), ns)
        return np.column_stack([screened[group // n], group % n, scen])

    def _missing_rows(
        self, lin: Linearisation, d: np.ndarray, s_pos: np.ndarray, pos: np.ndarray
    ) -> np.ndarray:
        """Scenario rows of the full QP violated at the step ``(d, s_pos)``.

        Up to ``screen_rows`` of the worst per (constraint, step) group, so that rows that
        are close together enter in one round.
        """
        screened, n = self._screened, self.problem.horizon
        if screened.size == 0:  # every constraint is shared-linear: all rows are in the QP
            return np.empty((0, 3), dtype=int)
        viol = self.model.linearised_values(lin, d)  # (nP, N, Ns)
        viol -= s_pos[screened][:, :, None]
        where = np.searchsorted(screened, pos[:, 0])
        viol[where, pos[:, 1], pos[:, 2]] = -np.inf
        flat = viol.reshape(screened.size * n, -1)
        bad = np.nonzero(flat.max(axis=1) > self.options.add_tol)[0]
        if bad.size == 0:
            return np.empty((0, 3), dtype=int)
        flat = flat[bad]
        ns = flat.shape[1]
        keep = min(self.options.screen_rows, ns)
        worst = np.argpartition(flat, ns - keep, axis=1)[:, ns - keep :]
        sub, col = np.nonzero(np.take_along_axis(flat, worst, axis=1) > self.options.add_tol)
        group = bad[sub]
        return np.column_stack([screened[group // n], group % n, worst[sub, col]])

    def _solve_qp(
        self,
        lin: Linearisation,
        H: np.ndarray,
        u: np.ndarray,
        pos: np.ndarray,
        g_shared: np.ndarray,
        stats: dict,
    ) -> _QPStep | None:
        """Step of the full QP by check-and-add over the scenario rows; None on failure.

        ``g_shared``: the shared rows' values, ordered (step, constraint).
        """
        p, nu = self.problem, self._n_u
        n, ng = p.horizon, p.ng
        n_scen = lin.ro.X.shape[2]
        for round_ in range(self.options.max_qp_rounds):
            self._check_time()
            a_pos, g_pos = self.model.rows(lin, pos)
            group = pos[:, 0] * n + pos[:, 1]
            n_groups = np.unique(group).size
            qp = self._qp(max(pos.shape[0], 1), max(n_groups, 1))
            row, column = qp.assign(group * n_scen + pos[:, 2], group)
            lo, hi = self._lower - u, self._upper - u
            if self._radius > 0.0:
                lo = np.maximum(lo, -self._radius * self._range)
                hi = np.minimum(hi, self._radius * self._range)
            qp.set_problem(H, lin.grad, lo, hi, self._a_shared, g_shared)
            qp.set_position_rows(row, column, a_pos, g_pos)
            retried = qp.failures
            z, lam_all, ok = qp.solve()
            stats["qp_solves"] += 1
            stats["qp_calls"][qp.solver] = stats["qp_calls"].get(qp.solver, 0) + 1
            stats["qp_retries"] += qp.failures - retried
            if not ok:
                return None
            s_pos = np.zeros((ng, n))
            s_pos.reshape(-1)[group] = z[nu + self._n_shared + column]
            missing = self._missing_rows(lin, z[:nu], s_pos, pos)
            if missing.shape[0] == 0:
                break
            if round_ == self.options.max_qp_rounds - 1:  # keep the last QP's rows
                stats["qp_rounds_exhausted"] += 1
                break
            pos = np.concatenate([pos, missing])
        stats["qp_rows"] = max(stats["qp_rows"], pos.shape[0])
        return _QPStep(
            d=z[:nu],
            slack_sum=float(z[nu:].sum()),
            pos=pos,
            lam=lam_all[row],
            qp=qp,
            row=row,
            s_pos=s_pos,
            s_shared=z[nu : nu + self._n_shared],
            lam_shared=lam_all[: self._n_shared],
        )

    def _newton_step(
        self,
        lin: Linearisation,
        H: np.ndarray,
        u: np.ndarray,
        active_pos: np.ndarray,
        active_shared: np.ndarray,
        damping: float,
        stats: dict,
    ) -> tuple[_QPStep | None, np.ndarray]:
        """QP step with a convexified Hessian, and the scenario-row multipliers ``(ng, N, Ns)``.

        A constraint predicted active whose row the QP leaves slack (or whose multiplier
        turns negative) would have bent the step through the augmentation: it is dropped
        and the QP re-solved. ``damping`` (Levenberg-Marquardt) is added to the Hessian.
        """
        p = self.problem
        mu = np.zeros((p.ng, p.horizon, lin.ro.X.shape[2]))
        bounds = np.nonzero((u <= self._lower + 1e-12) | (u >= self._upper - 1e-12))[0]
        screened = self._screen(lin.ro)
        g_shared = lin.ro.G[self.model.shared].max(axis=2).T.ravel()
        for attempt in range(4):
            if attempt == 3:  # give up predicting: plain eigenvalue clipping
                active_pos, active_shared, bounds = active_pos[:0], active_shared[:0], bounds[:0]
            H_qp, sigma, j_pos = self._convexify(H, lin, active_pos, active_shared, bounds)
            self._last_sigma = sigma if sigma > 0 else (-1.0 if H_qp is not H else 0.0)
            if damping > 0.0:
                H_qp = H_qp + damping * np.eye(self._n_u)
            step = self._solve_qp(lin, H_qp, u, screened, g_shared, stats)
            if step is None:
                return None, mu
            step.curvature = float(step.d @ H_qp @ step.d)
            mu[:] = 0.0
            mu[step.pos[:, 0], step.pos[:, 1], step.pos[:, 2]] = step.lam
            if sigma == 0.0:
                return step, mu
            d, tol = step.d, 1e-8
            idx = (active_pos[:, 0], active_pos[:, 1], active_pos[:, 2])
            lin_d = j_pos @ d
            lam = mu[idx] + sigma * lin_d  # multipliers of the un-augmented QP
            keep_pos = (lam >= -tol) & (
                lin.ro.G[idx] + lin_d - step.s_pos[active_pos[:, 0], active_pos[:, 1]] >= -tol
            )
            mu[idx] = np.maximum(lam, 0.0)
            sh_d = self._a_shared[active_shared] @ d
            keep_shared = (step.lam_shared[active_shared] + sigma * sh_d >= -tol) & (
                g_shared[active_shared] + sh_d - step.s_shared[active_shared] >= -tol
            )
            u_new = u[bounds] + d[bounds]
            keep_bounds = (u_new <= self._lower[bounds] + 1e-10) | (
                u_new >= self._upper[bounds] - 1e-10
            )
            if keep_pos.all() and keep_shared.all() and keep_bounds.all():
                return step, mu
            active_pos = active_pos[keep_pos]
            active_shared = active_shared[keep_shared]
            bounds = bounds[keep_bounds]
        return step, mu

    # ------------------------------------------------------------------ SQP

    def _expand(
        self, evaluate: Any, u: np.ndarray, d: np.ndarray, accepted: Rollout, stats: dict
    ) -> tuple[Rollout, float]:
        """The best of ``u + t d`` for ``t = 1, 2, 4, ...`` while the merit keeps falling."""
        t = 1.0
        for _ in range(self.options.max_expand):
            self._check_time()
            u_try = np.clip(u + 2.0 * t * d, self._lower, self._upper)
            if np.array_equal(u_try, accepted.u):  # the bounds stop the step
                break
            trial = evaluate(u_try)
            stats["merit_evals"] += 1
            if not trial.merit < accepted.merit:
                break
            accepted, t = trial, 2.0 * t
        return accepted, t

    def _check_time(self) -> None:
        """Raise :class:`_OutOfTime` once the current solve's deadline has passed."""
        if time.perf_counter() >= self._deadline:
            raise _OutOfTime

    def _sqp(
        self,
        data: _Data,
        u0: np.ndarray,
        abandon_above: float = math.inf,
        rival: np.ndarray | None = None,
        deadline: float = math.inf,
    ) -> tuple[Rollout, str, bool, int, dict[str, Any]]:
        """SQP iterations from ``u0``: ``(final rollout, status, success, iterations, extra)``.

        ``abandon_above``: after ``restart_probe`` iterations, stop with status
        ``"Abandoned"`` when the merit plus ``restart_optimism`` times the directional
        derivative along the QP step (the local model's promise) is above this value.
        ``rival``: the best plan so far; stop with status ``"Duplicate"`` when an iterate
        comes within ``restart_same_tol`` of it (the same local optimum again).
        ``deadline``: a ``time.perf_counter()`` value; once past it, stop before the next
        QP solve or line-search trial with status ``"Maximum_WallTime_Exceeded"`` (not a
        success) and the last accepted iterate.
        """
        p, opt, model = self.problem, self.options, self.model
        nu, rho = self._n_u, p.slack_penalty
        ns = data.x0T.shape[1]
        mu = np.zeros((p.ng, p.horizon, ns))
        active_pos = np.empty((0, 3), dtype=int)
        active_shared = np.empty(0, dtype=int)
        stats: dict[str, Any] = {
            "qp_solves": 0,
            "qp_rows": 0,
            "qp_retries": 0,
            "qp_rounds_exhausted": 0,
            "soc_steps": 0,
            "merit_evals": 1,
            "qp_calls": {},
        }

        def evaluate(u: np.ndarray) -> Rollout:
            with np.errstate(all="ignore"):
                return model.evaluate(data.x0T, data.W, u, data.cost0, data.backoff)

        ro = evaluate(u0)
        if not math.isfinite(ro.merit):
            return ro, "Invalid_Initial_Point", False, 0, stats
        status, success, iterations = "Maximum_Iterations_Exceeded", False, 0
        prev_step = math.inf  # size of the last accepted full step
        damping = 0.0  # Levenberg-Marquardt term: grows while the quadratic model is poor
        self._radius = opt.trust_radius
        self._deadline = deadline
        try:
            while iterations < opt.max_iter:
                if time.perf_counter() >= deadline:
                    status = "Maximum_WallTime_Exceeded"
                    break
                iterations += 1
                u = ro.u
                with np.errstate(all="ignore"):
                    lin = model.linearise(ro, data.W_lanes)
                    H = model.hessian(lin, mu, data.W_lanes)
                if not (np.all(np.isfinite(H)) and np.all(np.isfinite(lin.grad))):
                    status = "Invalid_Derivatives"
                    break
                try:
                    qp_step, mu = self._newton_step(
                        lin, H, u, active_pos, active_shared, damping, stats
                    )
                except np.linalg.LinAlgError:  # eigen-decomposition failed: keep the best iterate
                    status = "Numerical_Error"
                    break
                if qp_step is None:
                    status = "QP_Failed"
                    break
                d, pos = qp_step.d, qp_step.pos
                # Hard-active constraints of this QP: the prediction for the next convexification.
                hard = (mu[pos[:, 0], pos[:, 1], pos[:, 2]] > 1e-9) & (
                    qp_step.s_pos[pos[:, 0], pos[:, 1]] <= 1e-9
                )
                active_pos = pos[hard]
                active_shared = np.nonzero(
                    (qp_step.lam_shared > 1e-9) & (qp_step.s_shared <= 1e-9)
                )[0]
                if np.max(np.abs(d)) <= opt.step_tol:
                    status, success = "Solve_Succeeded", True
                    break
                # Upper bound of the merit's directional derivative along d (< 0 unless d = 0).
                D = float(lin.grad @ d) + rho * (qp_step.slack_sum - ro.slack)
                cut = opt.trust_radius > 0.0 and bool(
                    np.max(np.abs(d) / self._range) >= 0.99 * self._radius
                )
                if -D <= opt.tol * (1.0 + abs(ro.merit)) and not cut:
                    # The QP step (not cut by the trust region) promises nothing beyond
                    # rounding: a KKT point up to the tolerance.
                    status, success = "Solve_Succeeded", True
                    break
                if (
                    iterations >= opt.restart_probe
                    and ro.merit + opt.restart_optimism * D > abandon_above
                ):
                    # Even a multiple of the decrease the local model promises leaves this
                    # start above the plan to beat: give it up.
                    status = "Abandoned"
                    break

                # --- line search on the exact-penalty merit, with second-order correction ---
                t = 1.0
                accepted = None
                while t >= opt.min_step:
                    self._check_time()
                    trial = evaluate(np.clip(u + t * d, self._lower, self._upper))
                    stats["merit_evals"] += 1
                    if trial.merit <= ro.merit + opt.armijo * t * D:
                        accepted = trial
                        break
                    if (
                        t == 1.0
                        and opt.second_order_correction
                        and trial.slack > ro.slack
                        and pos.shape[0]
                    ):
                        # The constraints' curvature made the full step infeasible: shift the
                        # rows by their second-order error and re-solve (Maratos effect).
                        a_pos, _ = model.rows(lin, pos)
                        g_try = trial.G[pos[:, 0], pos[:, 1], pos[:, 2]]
                        qp_step.qp.set_position_bounds(qp_step.row, g_try - a_pos @ d)
                        z_soc, _, ok_soc = qp_step.qp.solve()
                        stats["qp_solves"] += 1
                        calls, used = stats["qp_calls"], qp_step.qp.solver
                        calls[used] = calls.get(used, 0) + 1
                        if ok_soc:
                            soc = evaluate(np.clip(u + z_soc[:nu], self._lower, self._upper))
                            stats["merit_evals"] += 1
                            if soc.merit <= ro.merit + opt.armijo * D:
                                stats["soc_steps"] += 1
                                accepted = soc
                                break
                    t *= opt.backtrack
                if (
                    accepted is not None
                    and t == 1.0
                    and opt.max_expand > 0
                    and ro.merit - accepted.merit >= -opt.expand_ratio * D
                    # no fast local convergence under way: the last step was cut, or this
                    # QP step is not less than half the last full step
                    and (not math.isfinite(prev_step) or float(np.max(np.abs(d))) > 0.5 * prev_step)
                ):
                    accepted, t = self._expand(evaluate, u, d, accepted, stats)
                if accepted is None:
                    # No decrease along a descent direction: converged up to rounding if the
                    # predicted decrease is negligible, else a genuine failure.
                    if -D <= 1e3 * opt.tol * (1.0 + abs(ro.merit)):
                        status, success = "Solve_Succeeded", True
                    else:
                        status = "Line_Search_Failed"
                    break
                step = float(np.max(np.abs(accepted.u - u)))
                if self.trace is not None:
                    self.trace.append(
                        {
                            "merit": ro.merit,
                            "ratio": (accepted.merit - ro.merit) / D,
                            "slack": ro.slack,
                            "D": D,
                            "t": t,
                            "step": step,
                            "d": float(np.max(np.abs(d))),
                            "damping": damping,
                            "qp_solves": stats["qp_solves"],
                            "rows": pos.shape[0],
                            "eig0": self._last_eig[0],
                            "eig1": self._last_eig[1],
                            "sigma": self._last_sigma,
                            "radius": self._radius,
                        }
                    )
                slack_change = abs(accepted.slack - ro.slack)
                prev_merit = ro.merit
                ro = accepted
                if rival is not None and np.max(np.abs(ro.u - rival)) <= opt.restart_same_tol:
                    status = "Duplicate"
                    break
                # A trust region (or, without one, Levenberg-Marquardt damping) keeps steps
                # where the quadratic model holds: after heavy backtracking or a poor model
                # ratio (negative curvature floored, strongly curved constraints) the next
                # steps are shorter; good full steps lift the limit again, so the local
                # convergence stays fast.
                at_radius = False
                if opt.trust_radius > 0.0:
                    # The QP model's predicted decrease against the actual one at the full step.
                    size = float(np.max(np.abs(d) / self._range))
                    at_radius = cut  # (the radius has not changed since)
                    predicted = -(D + 0.5 * qp_step.curvature)
                    model_ratio = (prev_merit - ro.merit) / predicted if predicted > 0 else 1.0
                    if t < 1.0 or model_ratio < 0.25:
                        self._radius = max(0.5 * t * size, opt.min_trust_radius)
                    elif model_ratio > 0.25 and at_radius:
                        self._radius = min(2.0 * self._radius, 1.0)
                elif t < opt.damping_threshold:
                    damping = max(10.0 * damping, opt.damping_init)
                elif t == 1.0:
                    damping = (
                        opt.damping_decrease * damping if damping > 1e-3 * opt.damping_init else 0.0
                    )
                ratio = step / prev_step if math.isfinite(prev_step) else 1.0
                # (a step cut by the trust region says nothing about convergence)
                predicted_next = step * min(ratio, 1.0) if t == 1.0 and not at_radius else math.inf
                prev_step = step if t == 1.0 else math.inf
                if predicted_next <= opt.final_step_tol and (
                    ro.slack <= opt.add_tol or slack_change <= opt.add_tol * (1.0 + ro.slack)
                ):
                    status, success = "Solve_Succeeded", True
                    break
        except _OutOfTime:  # inside an iteration: keep the last accepted iterate
            status, success = "Maximum_WallTime_Exceeded", False
        return ro, status, success, iterations, stats


class _OutOfTime(Exception):
    """The solve's wall-clock limit (``max_time``) passed inside an SQP iteration."""


@dataclass
class _Data:
    """The data of one solve, in the layouts the condensed model works on."""

    x0T: np.ndarray  # (nx, Ns) initial states, component-major
    W: np.ndarray  # (N, Ns, nw) forces per step
    W_lanes: np.ndarray  # (nw, N, Ns) forces as evaluation points
    cost0: float  # averaged stage cost of the initial states (a constant)
    backoff: np.ndarray | None = None  # (ng, N, 1) constraint tightening, or None


__all__ = ["HESSIAN_MODIFICATIONS", "RESTARTS", "FastScenarioSolver", "FastSolverOptions"]
