"""Solvers of the scenario MPC problem, under one vocabulary.

``make_solver(problem, name, **options)`` builds any of :data:`SOLVERS`; each has
``solve(x0, W, u_guess=None) -> MPCSolution`` and ``reset()``, and minimises the same
:meth:`controllers.problem.ScenarioProblem.objective`:

* ``"fast"``: the condensed exact-Hessian SQP whose derivatives CasADi generates from the
  system definition (:mod:`controllers.solvers.fast.solver`), the default;
* ``"ipopt"``: IPOPT on the condensed NLP (inputs and slacks only);
* ``"ipopt_multiple_shooting"``: IPOPT on the textbook multiple-shooting NLP (the reference);
* ``"sqpmethod"``: CasADi's ``sqpmethod`` + qpOASES on the condensed NLP, JIT-compiled
  (the compiled SQP anchor; building it runs the C compiler);
* ``"csnlp"``: csnlp's ``ScenarioBasedMpc`` (multiple shooting; needs the ``bench`` extra).
"""

from __future__ import annotations

from typing import Any

from controllers.problem import ScenarioProblem

SOLVERS = ("fast", "ipopt", "ipopt_multiple_shooting", "sqpmethod", "csnlp")


def make_solver(problem: ScenarioProblem, name: str = "fast", **options: Any):
    """Build the solver ``name`` for ``problem`` (once; re-solve it every step).

    Args:
        problem: the scenario problem.
        name: one of :data:`SOLVERS`.
        **options: the solver's own settings: :class:`~controllers.solvers.fast.solver.FastSolverOptions`
            fields for ``"fast"``; ``ipopt_options`` / ``warm_start_duals`` for the IPOPT
            solvers; ``sqp_options`` / ``jit`` / ``warm_start_duals`` for ``"sqpmethod"``;
            ``shooting`` / ``ipopt_options`` for ``"csnlp"``. ``max_iter`` is understood
            by every solver (SQP or IPOPT iterations).

    Raises:
        ValueError: for an unknown name or option.
    """
    if name not in SOLVERS:
        raise ValueError(f"unknown solver {name!r}; choose one of {SOLVERS}")
    if name == "fast":
        from controllers.solvers.fast.solver import FastScenarioSolver

        return FastScenarioSolver(problem, **options)
    if name == "csnlp":
        from controllers.solvers.casadi.csnlp import CsnlpScenarioSolver

        return CsnlpScenarioSolver(problem, **_ipopt_options(options))
    if name == "sqpmethod":
        from controllers.solvers.casadi.sqpmethod import SqpMethodScenarioSolver

        return SqpMethodScenarioSolver(problem, **_ipopt_options(options, "sqp_options"))
    from controllers.solvers.casadi.ipopt import IpoptScenarioSolver

    formulation = "multiple_shooting" if name == "ipopt_multiple_shooting" else "condensed"
    return IpoptScenarioSolver(problem, formulation, **_ipopt_options(options))


def _ipopt_options(options: dict[str, Any], key: str = "ipopt_options") -> dict[str, Any]:
    """``max_iter=`` folded into ``options[key]`` (the one option every solver takes)."""
    options = dict(options)
    if "max_iter" in options:
        inner = dict(options.get(key) or {})
        inner.setdefault("max_iter", options.pop("max_iter"))
        options[key] = inner
    return options


__all__ = ["SOLVERS", "make_solver"]
