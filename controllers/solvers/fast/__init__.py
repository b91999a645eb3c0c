"""The project's fast solver: a condensed exact-Hessian SQP (:mod:`.solver`) with its
settings (:mod:`.options`), extra starts (:mod:`.restarts`), one iteration's QP step
(:mod:`.subproblem`), the line search and trust region (:mod:`.globalisation`), the condensed
model and its derivatives (:mod:`.condensed`), the row selection (:mod:`.screening`), the
vectorised lanes (:mod:`.lanes`), the QP solvers (:mod:`.qp`) and the C code generated from
the system (:mod:`.codegen`)."""

from controllers.solvers.fast.options import FastSolverOptions
from controllers.solvers.fast.solver import FastScenarioSolver

__all__ = ["FastScenarioSolver", "FastSolverOptions"]
