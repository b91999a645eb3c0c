"""Timing harness of the scenario MPC solvers on closed-loop-like problem sequences.

A benchmark script imports :func:`closed_loop_problems` to make sequences of warm-started
problems (``x0``, ``W``) and :func:`time_solvers` to time several solvers on exactly the
same sequences, side by side; :func:`format_timing_table` prints the result and
:func:`default_benchmark` does all of it for the two problem recipes of :data:`RECIPES`.
Timing uses ``time.perf_counter`` around each ``solve`` call (so every solver is charged
for its own pre- and post-processing), on the same machine in one run. On a shared
machine the wall times include the waits for the CPU: compare medians of one run.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from controllers.problem import MPCSolution, ScenarioProblem
from lfm_env.vehicle import euler_step

Problem = tuple[np.ndarray, np.ndarray]  # (x0 (4,) or (Ns, 4), W (Ns, N))


class ScenarioSolver(Protocol):
    """What :func:`time_solvers` needs of a solver."""

    def solve(
        self, x0: np.ndarray, W: np.ndarray, u_guess: np.ndarray | None = None
    ) -> MPCSolution: ...

    def reset(self) -> None: ...


def latent_force_scenarios(
    rng: np.random.Generator,
    n_scenarios: int,
    horizon: int,
    mean: float | np.ndarray = 0.0,
    spread: float = 2.0,
    walk_std: float = 0.3,
) -> np.ndarray:
    """Latent-force scenarios ``W`` ``(Ns, N)`` [m/s^2]: a random start plus a random walk.

    Args:
        rng: random generator.
        n_scenarios: ``Ns``.
        horizon: ``N``.
        mean: centre of the first value [m/s^2] (scalar or ``(Ns,)``).
        spread: standard deviation of the first value around ``mean`` [m/s^2]; 2 is the
            prior of the case study (``sigma^2 = 4``), a particle filter's posterior is
            narrower.
        walk_std: standard deviation of each later increment [m/s^2 per step].
    """
    w0 = np.asarray(mean, dtype=float) + spread * rng.standard_normal(n_scenarios)
    steps = walk_std * rng.standard_normal((n_scenarios, horizon - 1))
    return np.column_stack([w0, w0[:, None] + np.cumsum(steps, axis=1)])


def closed_loop_problems(
    problem: ScenarioProblem,
    controller: ScenarioSolver,
    n_steps: int = 40,
    seed: int = 0,
    x_start: Sequence[float] = (0.0, 0.0, 1.0, np.pi / 4),
    spread: float = 2.0,
    walk_std: float = 0.3,
    redraw: bool = False,
) -> list[Problem]:
    """The problems ``(x0, W)`` met by ``controller`` in a short simulated closed loop.

    The plant is the nominal Euler bicycle driven by ``u[0]`` and by the latent force of
    scenario 0. Two ways to move the scenarios on:

    * ``redraw=False``: shift ``W`` by one step and continue each scenario's random walk
      (the scenarios persist, so their spread grows along the run);
    * ``redraw=True``: like a particle filter, redraw the scenarios every step around the
      current true latent force (which itself follows a random walk) with ``spread``.

    Args:
        problem: the problem data (``Ns``, ``N``, ``dt``).
        controller: the solver that closes the loop (warm-started as usual).
        n_steps: number of problems.
        seed: seed of the scenario draws.
        x_start: initial state ``[p_x, p_y, v, psi]`` [m, m, m/s, rad].
        spread: scenario spread of the latent force [m/s^2] (see
            :func:`latent_force_scenarios`).
        walk_std: random-walk increment of the latent force [m/s^2 per step].
        redraw: the scenario update rule above.

    Returns:
        ``n_steps`` problems in closed-loop order.
    """
    rng = np.random.default_rng(seed)
    ns, n = problem.n_scenarios, problem.horizon
    x = np.asarray(x_start, dtype=float)
    w_true = spread * rng.standard_normal()
    W = latent_force_scenarios(rng, ns, n, w_true, spread, walk_std)
    controller.reset()
    problems: list[Problem] = []
    for _ in range(n_steps):
        problems.append((x.copy(), W.copy()))
        sol = controller.solve(x, W)
        w_applied = W[0, 0] if not redraw else w_true
        x = euler_step(x, sol.u[0], problem.dt, w_applied, problem.vehicle_length)
        if redraw:
            w_true += walk_std * rng.standard_normal()
            W = latent_force_scenarios(rng, ns, n, w_true, spread, walk_std)
        else:
            W = np.column_stack([W[:, 1:], W[:, -1] + walk_std * rng.standard_normal(ns)])
    return problems


@dataclass
class SolverTiming:
    """Per-problem records of one solver over the problem sequences."""

    name: str
    times: list[float] = field(default_factory=list)  # [s] wall time of each solve call
    iterations: list[int] = field(default_factory=list)
    success: list[bool] = field(default_factory=list)
    objective: list[float] = field(default_factory=list)
    slack: list[float] = field(default_factory=list)

    def summary(self) -> dict[str, float]:
        """Median, 95th percentile and max time [ms], mean iterations, failures."""
        t = 1e3 * np.asarray(self.times)
        return {
            "solves": float(t.size),
            "median_ms": float(np.median(t)),
            "p95_ms": float(np.percentile(t, 95)),
            "max_ms": float(np.max(t)),
            "mean_iterations": float(np.mean(self.iterations)),
            "failures": float(np.size(self.success) - np.sum(self.success)),
        }


def time_solvers(
    solvers: dict[str, Callable[[], ScenarioSolver]],
    sequences: Sequence[Sequence[Problem]],
    warmup: int = 1,
) -> dict[str, SolverTiming]:
    """Time every solver on the same warm-started problem sequences.

    Each solver is built once by its factory (build time is not charged), reset at the
    start of each sequence, and then solves the problems in order with its own warm start
    (the previous solution shifted by one step). ``warmup`` untimed solves of the first
    problem come first (first-call allocations, caches).

    Args:
        solvers: name -> factory of a solver of the sequences' problem size.
        sequences: problem sequences, e.g. from :func:`closed_loop_problems`.
        warmup: untimed solves before the timed ones.

    Returns:
        name -> per-problem records, in the order of ``solvers``.
    """
    results: dict[str, SolverTiming] = {}
    for name, factory in solvers.items():
        solver = factory()
        record = SolverTiming(name)
        for _ in range(warmup):
            solver.reset()
            solver.solve(*sequences[0][0])
        for seq in sequences:
            solver.reset()
            for x0, W in seq:
                t0 = time.perf_counter()
                sol = solver.solve(x0, W)
                record.times.append(time.perf_counter() - t0)
                record.iterations.append(sol.iterations)
                record.success.append(sol.success)
                record.objective.append(sol.objective)
                record.slack.append(sol.slack)
        results[name] = record
    return results


def objective_agreement(
    timing: SolverTiming, reference: SolverTiming, rtol: float = 1e-4
) -> dict[str, float]:
    """How often two solvers reach the same objective where both succeed.

    Along a closed loop each solver warm-starts from its own previous solution, so on
    these non-convex problems they may settle in different local optima; a disagreement is
    not by itself an error of either.
    """
    a, b = np.asarray(timing.objective), np.asarray(reference.objective)
    both = np.asarray(timing.success) & np.asarray(reference.success)
    rel = (a - b) / np.maximum(np.abs(b), 1e-12)
    return {
        "compared": float(both.sum()),
        "within_rtol": float(np.sum(np.abs(rel[both]) <= rtol)),
        "better": float(np.sum(rel[both] < -rtol)),
        "worse": float(np.sum(rel[both] > rtol)),
    }


def format_timing_table(results: dict[str, SolverTiming], baseline: str | None = None) -> str:
    """Plain-text table of :meth:`SolverTiming.summary`, with speed-ups over ``baseline``."""
    lines = [
        f"{'solver':<34}{'solves':>7}{'median ms':>11}{'p95 ms':>9}{'max ms':>9}"
        f"{'iters':>7}{'fails':>6}{'median x':>10}"
    ]
    base = results[baseline].summary()["median_ms"] if baseline in results else None
    for name, rec in results.items():
        s = rec.summary()
        ratio = f"{base / s['median_ms']:.1f}" if base else "-"
        lines.append(
            f"{name:<34}{s['solves']:>7.0f}{s['median_ms']:>11.2f}{s['p95_ms']:>9.2f}"
            f"{s['max_ms']:>9.2f}{s['mean_iterations']:>7.1f}{s['failures']:>6.0f}{ratio:>10}"
        )
    return "\n".join(lines)


RECIPES: dict[str, dict[str, Any]] = {
    # The case study's prior for every scenario (w0 ~ N(0, 4)), scenarios shifted along
    # the run: their spread grows, the problems soon need slack on the speed and the track
    # and are degenerate (penalty-dominated).
    "shift": {"spread": 2.0, "redraw": False, "n_steps": 40},
    # Scenarios redrawn every step around the true latent force with a particle-filter-like
    # spread: the vehicle drives the track to the goal.
    "redraw": {"spread": 0.5, "redraw": True, "n_steps": 60},
}


def default_benchmark(
    n_scenarios: Sequence[int] = (150,),
    recipe: str = "redraw",
    seeds: Sequence[int] = (0,),
    include_ipopt: bool = True,
    ipopt_max_scenarios: int = 150,
) -> dict[int, dict[str, SolverTiming]]:
    """Fast solver versus IPOPT (condensed, multiple shooting) on closed-loop sequences.

    For each scenario count the sequences come from the fast solver's closed loop
    (:func:`closed_loop_problems` with the settings of ``RECIPES[recipe]``, one sequence
    per seed); every solver is then timed on the same sequences. IPOPT (which needs
    :mod:`controllers.solvers.ipopt`) is timed only if ``include_ipopt`` and for at most
    ``ipopt_max_scenarios`` scenarios (about 1-2 s per solve at 150).

    Raises:
        ValueError: on an unknown recipe.
    """
    from controllers.solvers.fast import FastScenarioSolver

    if recipe not in RECIPES:
        raise ValueError(f"recipe={recipe!r}: must be one of {sorted(RECIPES)}")
    settings = dict(RECIPES[recipe])
    n_steps = settings.pop("n_steps")
    out: dict[int, dict[str, SolverTiming]] = {}
    for ns in n_scenarios:
        problem = ScenarioProblem(n_scenarios=ns)
        sequences = [
            closed_loop_problems(problem, FastScenarioSolver(problem), n_steps, seed=s, **settings)
            for s in seeds
        ]
        solvers: dict[str, Callable[[], ScenarioSolver]] = {
            "fast SQP": lambda problem=problem: FastScenarioSolver(problem)
        }
        if include_ipopt and ns <= ipopt_max_scenarios:
            from controllers.solvers.ipopt import IpoptScenarioSolver

            solvers["IPOPT condensed"] = lambda problem=problem: IpoptScenarioSolver(
                problem, formulation="condensed"
            )
            solvers["IPOPT multiple shooting"] = lambda problem=problem: IpoptScenarioSolver(
                problem, formulation="multiple_shooting"
            )
        out[ns] = time_solvers(solvers, sequences)
    return out
