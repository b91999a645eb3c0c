"""The fast SQP's globalisation: how far to go along a QP step.

:class:`GlobalisationMixin` holds, for :class:`~controllers.solvers.fast.solver.FastScenarioSolver`,
what its SQP loop does with a QP step (:class:`~controllers.solvers.fast.subproblem.QPStep`):
what the QP model promises along it (:meth:`~GlobalisationMixin._measure`), the backtracking
Armijo line search on the exact-penalty merit with the second-order correction against the
Maratos effect, the expansion of a good full step (2, 4, ... times as long while the merit
keeps falling), and the box trust region on the next step (or, with ``trust_radius=0``,
Levenberg-Marquardt damping). The solver's module docstring says why each is there.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any, NamedTuple

import numpy as np

from controllers.solvers.fast.iterate import Linearisation, Rollout
from controllers.solvers.fast.subproblem import QP, QPStep, SolverAttributes

Evaluate = Callable[[np.ndarray], Rollout]  # the rollout and merit of inputs (N nu,)


class ModelStep(NamedTuple):
    """A QP step and what its model says of it (:meth:`GlobalisationMixin._measure`)."""

    qp: QPStep
    D: float  # upper bound of the merit's directional derivative along the step (< 0)
    predicted: float  # the QP model's merit decrease
    cut: bool  # the trust region cut the step


class GlobalisationMixin(SolverAttributes):
    """Line search, second-order correction, expansion and trust region of
    :class:`~controllers.solvers.fast.solver.FastScenarioSolver` (a base class of it: reads
    its attributes, :class:`~controllers.solvers.fast.subproblem.SolverAttributes`, and
    keeps the trust radius)."""

    _count: Callable[[dict, QP], None]  # counts a QP call in the stats (the subproblem's)

    def _measure(self, ro: Rollout, lin: Linearisation, qp_step: QPStep) -> ModelStep:
        """What the QP model says of its step from ``ro``: the merit's directional
        derivative, the predicted decrease, and whether the trust region cut the step."""
        d = qp_step.d
        # Upper bound of the merit's directional derivative along d (< 0 unless d = 0).
        D = float(lin.grad @ d) + self.problem.slack_penalty * (qp_step.slack_sum - ro.slack)
        predicted = -(D + 0.5 * qp_step.curvature)  # the QP model's merit decrease
        cut = self.options.trust_radius > 0.0 and bool(
            np.max(np.abs(d) / self._range) >= 0.99 * self._radius
        )
        return ModelStep(qp_step, D, predicted, cut)

    def _line_search(
        self,
        evaluate: Evaluate,
        ro: Rollout,
        lin: Linearisation,
        step: ModelStep,
        prev_step: float,
        stats: dict[str, Any],
    ) -> tuple[Rollout | None, float]:
        """Backtracking Armijo search on the exact-penalty merit along the QP step from
        ``ro``, with second-order correction, then the expansion of a good full step
        (:meth:`_expand`; not while the steps shrink fast: ``prev_step``, the last full
        step's size): ``(the accepted rollout or None, its step length)``."""
        opt, qp_step, D = self.options, step.qp, step.D
        u, d = ro.u, qp_step.d
        soc_ok = opt.second_order_correction and qp_step.pos.shape[0] > 0
        t = 1.0
        accepted = None
        while t >= opt.min_step:
            self._check_time()
            trial = evaluate(np.clip(u + t * d, self._lower, self._upper))
            stats["merit_evals"] += 1
            if trial.merit <= ro.merit + opt.armijo * t * D:
                accepted = trial
                if (
                    t == 1.0
                    and soc_ok
                    and opt.soc_below_ratio > 0.0
                    and trial.slack > ro.slack
                    and ro.merit - trial.merit < opt.soc_below_ratio * step.predicted
                ):
                    # Accepted, but far below the model's promise while the slack
                    # grew: the same curvature error; keep the correction if better.
                    soc = self._corrected(evaluate, lin, qp_step, u, trial, stats)
                    if soc is not None and soc.merit < trial.merit:
                        stats["soc_steps"] += 1
                        accepted = soc
                break
            if t == 1.0 and soc_ok and trial.slack > ro.slack:
                soc = self._corrected(evaluate, lin, qp_step, u, trial, stats)
                if soc is not None and soc.merit <= ro.merit + opt.armijo * D:
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
        return accepted, t

    def _expand(
        self, evaluate: Evaluate, u: np.ndarray, d: np.ndarray, accepted: Rollout, stats: dict
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

    def _corrected(
        self,
        evaluate: Evaluate,
        lin: Linearisation,
        qp_step: QPStep,
        u: np.ndarray,
        trial: Rollout,
        stats: dict,
    ) -> Rollout | None:
        """The second-order correction of the full step that gave ``trial`` (or None).

        The constraints' curvature made the full step infeasible: the QP's scenario rows
        are shifted by their second-order error at ``trial`` and the QP re-solved (against
        the Maratos effect); returns the rollout of the corrected step. (When the step came
        from the QP without slacks, so does the correction, without the multiplier test: it
        is a candidate like any other, kept by the caller only if the merit falls.)
        """
        pos, d = qp_step.pos, qp_step.d
        a_pos, _ = self.condensed.rows(lin, pos)
        g_try = trial.G[pos[:, 0], pos[:, 1], pos[:, 2]]
        qp_step.qp.set_position_bounds(qp_step.row, g_try - a_pos @ d)
        z_soc, _, ok_soc = qp_step.qp.solve(self._deadline)
        self._count(stats, qp_step.qp)
        if not ok_soc:
            return None
        stats["merit_evals"] += 1
        return evaluate(np.clip(u + z_soc[: self._n_u], self._lower, self._upper))

    def _adapt_region(
        self, step: ModelStep, t: float, prev_merit: float, merit: float, damping: float
    ) -> tuple[bool, float]:
        """The trust region (or, without one, the Levenberg-Marquardt ``damping``) after a
        step of length ``t`` from merit ``prev_merit`` to ``merit``: ``(whether the step
        reached the region, the new damping)``.

        They keep steps where the quadratic model holds: after heavy backtracking or a poor
        model ratio (negative curvature floored, strongly curved constraints) the next
        steps are shorter; good full steps lift the limit again, so the local convergence
        stays fast."""
        opt = self.options
        at_radius = False
        if opt.trust_radius > 0.0:
            # The QP model's predicted decrease against the actual one at the full step.
            size = float(np.max(np.abs(step.qp.d) / self._range))
            at_radius = step.cut  # (the radius has not changed since)
            predicted = step.predicted
            model_ratio = (prev_merit - merit) / predicted if predicted > 0 else 1.0
            if t < 1.0 or model_ratio < 0.25:
                self._radius = max(0.5 * t * size, opt.min_trust_radius)
            elif model_ratio > 0.25 and at_radius:
                self._radius = min(2.0 * self._radius, 1.0)
        elif t < opt.damping_threshold:
            damping = max(10.0 * damping, opt.damping_init)
        elif t == 1.0:
            damping = opt.damping_decrease * damping if damping > 1e-3 * opt.damping_init else 0.0
        return at_radius, damping


__all__ = ["Evaluate", "GlobalisationMixin", "ModelStep"]
