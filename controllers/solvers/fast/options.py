"""Settings of the fast SQP solver (:mod:`controllers.solvers.fast.solver`)."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

from controllers.solvers.fast.qp.slot_qp import QP_SOLVERS

RESTARTS = ("mirror", "straight")
# How an indefinite Hessian is made positive definite when adding sigma J_A' J_A of the
# predicted active constraints does not do it (see FastScenarioSolver._convexify):
# "floor": negative eigenvalues raised to hessian_floor; "abs": replaced by their absolute
# values (at least the floor); "augmented": the floor applied to the augmented Hessian.
HESSIAN_MODIFICATIONS = ("floor", "abs", "augmented")
# When the QP subproblem gets its slack variables (see SubproblemMixin._solve_qp):
# "on_demand": the QP is solved without slacks first, and with them only when that QP is
# infeasible or a multiplier (a group's sum) exceeds the slack penalty; "always": with them;
# "carried": on demand, but a solve's first QP is without slacks only if the last QP of the
# solver's previous solve needed none (what a limited solve, FastSolverOptions.limited,
# takes: a real-time iteration is one QP step, and where the problems need slack from step
# to step the QP without slacks first only costs).
ELASTIC_MODES = ("on_demand", "always", "carried")
MAX_THREADS = 256  # threads above this is surely a mistake
# Which nominal inputs v_k of a feedback problem keep the input bounds (see
# FastSolverOptions.feedback_bounds): "first" only v_0, the input applied now; "all" every v_k.
FEEDBACK_BOUNDS = ("first", "all")


@dataclass(frozen=True)
class FastSolverOptions:
    """Settings of the fast SQP solver; the defaults suit the paper's problem.

    Tolerances are in the units of the inputs and constraints (the paper's problem: m/s^2,
    rad, m, m/s).
    """

    # SQP iterations per start. Long horizons need many: on 36 recorded N = 30 problems
    # (infeasible for every input, flat penalty valleys; solved in closed-loop order) first
    # starts took up to 132 with the stagnation stop below, and at a limit of 50, 9 of the
    # 36 solves stopped while still converging.
    max_iter: int = 150
    # Predicted merit decrease, relative to the merit, that counts as converged (1e3 times
    # it after a failed line search, where rounding stops the search).
    tol: float = 1e-10
    # Stagnation stop (after IPOPT's "acceptable" level): acceptable_iter accepted steps in a
    # row that each lowered the merit by at most acceptable_tol of it end the start with
    # status "Solved_To_Acceptable_Level" (a success). On the flat, infeasible valleys of long
    # horizons an SQP can otherwise creep for a hundred iterations at ~1e-9 of the merit each.
    acceptable_tol: float = 1e-8
    acceptable_iter: int = 15
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
    # A full step accepted with less than this fraction of the QP model's predicted decrease
    # while the slack grew also gets the correction (kept if it lowers the merit further):
    # otherwise the trust region shrinks to its minimum on the constraints' curvature and
    # the SQP creeps along the constraint. 0: only failed full steps are corrected.
    soc_below_ratio: float = 0.25
    damping_init: float = 1.0  # first Levenberg-Marquardt damping (trust_radius=0 only)
    damping_threshold: float = 0.1  # line-search step below which the damping grows
    damping_decrease: float = 0.1  # factor on the damping after a full step
    # One of QP_SOLVERS; "auto": qpOASES on small QPs, the elastic interior point on large
    # ones (slot_qp).
    qp_solver: str = "auto"
    hessian_modification: str = "floor"  # one of HESSIAN_MODIFICATIONS
    # One of ELASTIC_MODES. The exact-penalty QP needs one slack per shared row and per
    # (constraint, step) group, which makes it several times as wide as the N nu inputs;
    # while the linearised constraints can be met, the QP without slacks has the same step
    # (its multipliers then certify it), so "on_demand" tries that one first, as long as
    # the last QP step of the start needed no slack.
    elastic_qp: str = "on_demand"
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
    # [m/s^2, rad] An extra start this close to the best plan, still worse than it and
    # closer than at its last iterate, is on its way back to it: the same plan too.
    restart_near_tol: float = 0.25
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
    # Threads of the C library's rollouts, linearisations and Hessians (the scenarios
    # in that many chunks; results equal to rounding for every count). Worth it for many
    # scenarios: on a 2-core machine with 2 threads, N = 7 solves took 0.73x the time at
    # Ns = 500, 0.70x at 1000 and 0.58x at 5000, but 1.3x at the paper's Ns = 150 (waking
    # the second thread costs more than it saves). Leave it at 1 when processes already
    # share the cores (lfm-evaluate --jobs). Needs the compiler's OpenMP; without it the
    # chunks run one after another.
    threads: int = 1
    # Wall-clock limit of one solve [s], checked between SQP iterations: a solve that
    # reaches it returns its best iterate with success=False, status
    # "Maximum_WallTime_Exceeded" (IPOPT's name), and tries no further start.
    max_time: float = math.inf
    # Feedback problems (ScenarioProblem(..., prediction="feedback")): the decision is the
    # nominal inputs v, every scenario applies u_{s,k} = v_k + K_k (x_{s,k} - r_k) and each of
    # those inputs is bounded by a soft row. "first": v_0 (applied now, shared by the
    # scenarios) keeps the input bounds and v_k (k >= 1) is free (the trust region still
    # measures steps in the inputs' ranges); "all": every v_k keeps them (the formulation
    # of the exact open-loop rewrite the other solvers run, controllers.solvers.feedback).
    feedback_bounds: str = "first"
    # The initial trust radius of a solve limited to a few iterations (solve(...,
    # iterations=k): real-time iterations, agents.iterations: rti), a fraction of each input's
    # range as trust_radius. A real-time iteration starts from the plan shifted by one step
    # and takes one QP step: cut to a quarter of the range, the closed loop of the paper's
    # scenario agent at N = 30 (feedback) stalled short of the goal for 100 steps; with the
    # whole range (1.0) it reached it in 55 steps (45 with converged solves).
    rti_trust_radius: float = 1.0
    # The scenario rows per (constraint, step) group a limited solve screens and adds per
    # check-and-add round (screen_rows). The rounds make the QP's step exact whatever the
    # screening, so this is a question of time only: on the closed-loop problems of the
    # paper's scenario agent at N = 30 (feedback, one iteration per step, the compiled loop),
    # 2 took a step 20.7 ms of CPU (median) against 25.3 ms with 4; at N = 15 2.9 vs 3.0 ms.
    # (At most screen_rows: the C loop's buffers are sized by it.)
    rti_screen_rows: int = 2

    def limited(self, iterations: int | None) -> FastSolverOptions:
        """These options for one solve of at most ``iterations`` SQP iterations, no extra
        starts, the trust radius ``rti_trust_radius``, ``rti_screen_rows`` rows per group
        and the QP without slacks first only where the last solve's last QP needed none
        (``elastic_qp="carried"``; real-time iterations); ``None``: these options.

        Raises:
            ValueError: for ``iterations`` not ``None`` or an int >= 1.
        """
        if iterations is None:
            return self
        if isinstance(iterations, bool) or not isinstance(iterations, int) or iterations < 1:
            raise ValueError(f"iterations={iterations!r}: must be None or an int >= 1")
        elastic = "carried" if self.elastic_qp == "on_demand" else self.elastic_qp
        return dataclasses.replace(
            self,
            max_iter=iterations,
            restarts=(),
            trust_radius=self.rti_trust_radius,
            elastic_qp=elastic,
            screen_rows=min(self.rti_screen_rows, self.screen_rows),
        )

    def __post_init__(self) -> None:
        def check(name: str, ok: bool, allowed: str) -> None:
            if not ok:
                raise ValueError(
                    f"FastSolverOptions.{name}={getattr(self, name)!r}: must be {allowed}"
                )

        for name in (
            "max_iter",
            "screen_rows",
            "max_qp_rounds",
            "restart_probe",
            "acceptable_iter",
            "rti_screen_rows",
        ):
            value = getattr(self, name)
            check(name, isinstance(value, int) and value >= 1, "an int >= 1")
        value = self.threads
        ok = isinstance(value, int) and not isinstance(value, bool) and 1 <= value <= MAX_THREADS
        check("threads", ok, f"an int in [1, {MAX_THREADS}]")
        for name in (
            "tol",
            "acceptable_tol",
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
        value = self.restart_near_tol
        ok = isinstance(value, (int, float)) and value >= self.restart_same_tol
        check("restart_near_tol", ok and math.isfinite(value), ">= restart_same_tol, finite")
        check("armijo", 0 < self.armijo < 0.5, "in (0, 0.5)")
        check("soc_below_ratio", 0 <= self.soc_below_ratio <= 1, "in [0, 1]")
        check("backtrack", 0 < self.backtrack < 1, "in (0, 1)")
        check("damping_threshold", 0 < self.damping_threshold <= 1, "in (0, 1]")
        check("damping_decrease", 0 <= self.damping_decrease < 1, "in [0, 1)")
        for name in ("trust_radius", "min_trust_radius", "rti_trust_radius"):
            value = getattr(self, name)
            ok = isinstance(value, (int, float)) and not isinstance(value, bool) and 0 <= value <= 1
            check(name, ok, "in [0, 1] (a fraction of each input's range; 0: none)")
        ok = self.trust_radius == 0 or self.min_trust_radius <= self.trust_radius
        check("min_trust_radius", ok, f"<= trust_radius ({self.trust_radius})")
        ok = self.rti_trust_radius == 0 or self.min_trust_radius <= self.rti_trust_radius
        check("rti_trust_radius", ok, f"0 or >= min_trust_radius ({self.min_trust_radius})")
        value = self.max_time
        ok = isinstance(value, (int, float)) and not isinstance(value, bool) and value > 0
        check("max_time", ok and not math.isnan(value), "a number of seconds > 0 (inf: none)")
        check("qp_solver", self.qp_solver in QP_SOLVERS, f"one of {QP_SOLVERS}")
        ok = self.hessian_modification in HESSIAN_MODIFICATIONS
        check("hessian_modification", ok, f"one of {HESSIAN_MODIFICATIONS}")
        check("elastic_qp", self.elastic_qp in ELASTIC_MODES, f"one of {ELASTIC_MODES}")
        ok = self.feedback_bounds in FEEDBACK_BOUNDS
        check("feedback_bounds", ok, f"one of {FEEDBACK_BOUNDS}")
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


__all__ = [
    "ELASTIC_MODES",
    "FEEDBACK_BOUNDS",
    "HESSIAN_MODIFICATIONS",
    "RESTARTS",
    "FastSolverOptions",
]
