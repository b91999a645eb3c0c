"""Solvers of the scenario MPC problem, under one vocabulary.

:data:`SOLVER_SPECS` is the registry: one :class:`SolverSpec` per solver (its name, where its
class lives, what it is, how the common options reach it and what it can do).
``make_solver(problem, name, **options)`` builds any of them; each is a
:class:`ScenarioSolver` (``solve(x0, W, u_guess=None, backoff=None) -> MPCSolution`` and
``reset()``) and minimises the same :meth:`controllers.problem.ScenarioProblem.objective`.
On a problem with ``prediction="feedback"`` the fast SQP (``"fast"``, ``"fast_c"``) solves it
natively (:mod:`controllers.solvers.fast.closed_loop`); the others run through the exact
rewrite of :mod:`controllers.solvers.feedback` (the fast SQP too where no C compiler works).
Every one's ``solve`` then also takes the feedback law (``law=``).
``"fast"``, the project's condensed SQP (:mod:`controllers.solvers.fast`), is
``make_solver``'s default, and ``"fast_c"``, the same SQP with its loop compiled, the agents'
(``agents.solver``); the others are built on CasADi's plugins
(:mod:`controllers.solvers.casadi`).
"""

from __future__ import annotations

import importlib
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from controllers.problem import MPCSolution, ScenarioProblem
from controllers.threads import limit_blas_threads


class ScenarioSolver(Protocol):
    """What every solver of the registry is: built once for a problem, then solved at every
    step, warm-started from its previous solution until :meth:`reset`."""

    def solve(
        self,
        x0: np.ndarray,
        W: np.ndarray,
        u_guess: np.ndarray | None = None,
        backoff: np.ndarray | None = None,
    ) -> MPCSolution:
        """The plan for initial state(s) ``x0`` and latent forces ``W`` (``u_guess``: the
        initial inputs; ``backoff``: the constraint tightening, as for
        :meth:`ScenarioProblem.check_backoff`)."""
        ...

    def reset(self) -> None:
        """Forget the warm start: the next solve starts afresh."""
        ...


@dataclass(frozen=True)
class SolverSpec:
    """One solver of the registry.

    Attributes:
        name: the name ``make_solver``, the config (``agents.solver``) and the benchmark use.
        entry_point: ``"module:Class"``, imported when the solver is built.
        description: what it is, in one line.
        arguments: keyword arguments of the class fixed by this name.
        max_iter_option: the options dict that ``max_iter=`` goes into (e.g.
            ``"ipopt_options"``); ``None``: the class takes ``max_iter`` itself.
        max_horizon: the longest horizon ``N`` it is practical at (the config refuses
            longer ones up front); ``None``: no such limit.
        threaded: it takes ``threads=T`` (its C library's threads; ``agents.solver_threads``).
        native_feedback: it solves a feedback problem itself (else through the rewrite).
        real_time: its ``solve`` takes ``iterations=`` (a per-call SQP iteration limit without
            extra starts: real-time iterations, ``agents.iterations: rti``).
    """

    name: str
    entry_point: str
    description: str
    arguments: Mapping[str, Any] = field(default_factory=dict)
    max_iter_option: str | None = None
    max_horizon: int | None = None
    threaded: bool = False
    native_feedback: bool = False
    real_time: bool = False

    def build(self, problem: ScenarioProblem, **options: Any) -> ScenarioSolver:
        """The solver for ``problem`` with ``options`` (see :func:`make_solver`); for a
        feedback problem, this solver itself if it solves those natively (and its C library
        can be built), else through the exact rewrite of
        :class:`~controllers.solvers.feedback.FeedbackScenarioSolver`. Sets the process's
        BLAS threads first (:func:`controllers.threads.limit_blas_threads`)."""
        limit_blas_threads()
        if problem.prediction == "feedback":
            from controllers.solvers.fast.codegen.build import CodegenUnavailable, notice
            from controllers.solvers.feedback import FeedbackScenarioSolver

            if self.native_feedback:
                try:
                    return self._build(problem, **options)
                except CodegenUnavailable as err:
                    notice(
                        f"{self.name}: a feedback problem without the C library ({err}); "
                        "solving it through the exact open-loop rewrite"
                    )
            return FeedbackScenarioSolver(problem, self, **options)
        return self._build(problem, **options)

    def _build(self, problem: ScenarioProblem, **options: Any) -> ScenarioSolver:
        """The class of :attr:`entry_point` on ``problem``, with the options routed."""
        module, _, name = self.entry_point.partition(":")
        cls = getattr(importlib.import_module(module), name)
        key = self.max_iter_option
        if key is not None and "max_iter" in options:  # (the one option every solver takes)
            options = dict(options)
            inner = dict(options.get(key) or {})
            inner.setdefault("max_iter", options.pop("max_iter"))
            options[key] = inner
        return cls(problem, **self.arguments, **options)


_IPOPT = "controllers.solvers.casadi.ipopt:IpoptScenarioSolver"
SOLVER_SPECS: dict[str, SolverSpec] = {
    spec.name: spec
    for spec in (
        SolverSpec(
            "fast",
            "controllers.solvers.fast.solver:FastScenarioSolver",
            "the condensed exact-Hessian SQP whose derivatives CasADi generates from the "
            "system definition, its loop in Python (make_solver's default; every QP solver)",
            # Its work per iteration grows steeply with N. Measured with 150 scenarios (the
            # paper's scenario agent, feedback prediction, the compiled loop, CPU time): at
            # N = 50 a real-time iteration takes about 0.12 s per step and the agent reaches
            # the goal; beyond, not measured (docs/solvers.md, "Real-time iterations").
            max_horizon=50,
            threaded=True,
            native_feedback=True,
            real_time=True,
        ),
        SolverSpec(
            "fast_c",
            "controllers.solvers.fast.compiled:CompiledScenarioSolver",
            "the same SQP with its whole loop compiled (one C call per solve; the project's "
            "own QP solvers in C; the Python loop, with a notice, where no compiler works): "
            "the agents' default",
            max_horizon=50,
            threaded=True,
            native_feedback=True,
            real_time=True,
        ),
        SolverSpec(
            "ipopt",
            _IPOPT,
            "IPOPT on the condensed NLP (inputs and slacks only)",
            {"formulation": "condensed"},
            max_iter_option="ipopt_options",
        ),
        SolverSpec(
            "ipopt_multiple_shooting",
            _IPOPT,
            "IPOPT on the textbook multiple-shooting NLP (the reference)",
            {"formulation": "multiple_shooting"},
            max_iter_option="ipopt_options",
        ),
        SolverSpec(
            "sqpmethod",
            "controllers.solvers.casadi.sqpmethod:SqpMethodScenarioSolver",
            "CasADi's sqpmethod + qpOASES on the condensed NLP, JIT-compiled (the compiled SQP "
            "anchor; building it runs the C compiler)",
            max_iter_option="sqp_options",
        ),
        SolverSpec(
            "csnlp",
            "controllers.solvers.casadi.csnlp:CsnlpScenarioSolver",
            "csnlp's ScenarioBasedMpc + IPOPT (multiple shooting; needs the bench extra)",
            max_iter_option="ipopt_options",
        ),
    )
}
SOLVERS = tuple(SOLVER_SPECS)  # the names, in the registry's order


def solver_spec(name: str) -> SolverSpec:
    """The registry's record of solver ``name``.

    Raises:
        ValueError: for an unknown name (one line, listing the choices).
    """
    try:
        return SOLVER_SPECS[name]
    except (KeyError, TypeError):
        raise ValueError(f"unknown solver {name!r}; choose one of {SOLVERS}") from None


def make_solver(problem: ScenarioProblem, name: str = "fast", **options: Any) -> ScenarioSolver:
    """Build the solver ``name`` for ``problem`` (once; re-solve it every step).

    Args:
        problem: the scenario problem.
        name: one of :data:`SOLVERS`.
        **options: the solver's own settings:
            :class:`~controllers.solvers.fast.options.FastSolverOptions` fields for
            ``"fast"``; ``ipopt_options`` / ``warm_start_duals`` for the IPOPT solvers;
            ``sqp_options`` / ``jit`` / ``warm_start_duals`` for ``"sqpmethod"``;
            ``shooting`` / ``ipopt_options`` for ``"csnlp"``. ``max_iter`` and ``max_time``
            are understood by every solver (SQP or IPOPT iterations; seconds per solve).

    Raises:
        ValueError: for an unknown name or option.
    """
    return solver_spec(name).build(problem, **options)


__all__ = ["SOLVERS", "SOLVER_SPECS", "ScenarioSolver", "SolverSpec", "make_solver", "solver_spec"]
