"""The extra starts of the fast SQP: which to try, from where, and when one is the best plan again.

The scenario problem is not convex; :class:`~controllers.solvers.fast.solver.FastScenarioSolver`
runs its SQP from further starts when the first plan drives an input the system declares
mirror-symmetric (``ControlSystem.mirror_inputs``) hard (see its ``solve``).
:class:`RestartMixin` holds the choices; the solver's ``solve`` and ``_sqp`` run them.
"""

from __future__ import annotations

import numpy as np

from controllers.problem import ScenarioProblem
from controllers.solvers.fast.iterate import Rollout
from controllers.solvers.fast.options import FastSolverOptions


class RestartMixin:
    """Extra-start decisions of :class:`~controllers.solvers.fast.solver.FastScenarioSolver` (a base
    class of it: reads its problem, options and input bounds)."""

    problem: ScenarioProblem
    options: FastSolverOptions
    _lower: np.ndarray  # (N nu,) input bounds
    _upper: np.ndarray

    def _restart_names(self, ro: Rollout) -> list[str]:
        """The extra starts worth trying after a first plan ``ro`` (see the solver's ``solve``)."""
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

    def _bound_for(self, rival: np.ndarray, u_prev: np.ndarray, ro: Rollout, bar: float) -> bool:
        """Whether an extra start, stepping from ``u_prev`` to ``ro``, heads for the plan
        ``rival`` it has to beat (merit ``bar``): within ``restart_same_tol`` of it, or within
        ``restart_near_tol`` and closer than before while still worse. (Steps that approach
        a plan from afar and are still above its merit end in that plan; the extra starts
        kept on the recorded problems ended 0.5 or more from the plan they beat.)"""
        opt = self.options
        gap = float(np.max(np.abs(ro.u - rival)))
        if gap <= opt.restart_same_tol:
            return True
        closer = gap < float(np.max(np.abs(u_prev - rival)))
        return gap <= opt.restart_near_tol and closer and ro.merit > bar


__all__ = ["RestartMixin"]
