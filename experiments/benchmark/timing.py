"""Timing harness of the scenario MPC solvers on synthetic closed-loop problem sequences.

Where :mod:`experiments.benchmark.run` records the problems of real agent episodes, this
harness makes closed loops of its own, fast to set up and with a chosen scenario spread:
:func:`closed_loop_problems` makes sequences of warm-started problems (``x0``, ``W``)
driven by a random-walk latent force (:func:`latent_force_scenarios`), :func:`time_solvers`
times several solvers on exactly the same sequences, :func:`format_timing_table` prints the
result and :func:`default_benchmark` does all of it for the recipes of :data:`RECIPES`.
Solvers are built through the registry (:func:`controllers.solvers.make_solver`); the
problem comes from the config, and nothing here knows the system.

Timing uses ``time.perf_counter`` around each ``solve`` call (so every solver is charged
for its own pre- and post-processing), on the same machine in one run. On a shared
machine the wall times include the waits for the CPU: compare medians of one run.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from controllers.problem import ScenarioProblem
from controllers.solvers import ScenarioSolver, make_solver
from experiments.benchmark.problems import DEFAULT_CONFIG, experiment_config

Problem = tuple[np.ndarray, np.ndarray]  # (x0 (nx,) or (Ns, nx), W (Ns, N, nw) or (Ns, N))


def latent_force_scenarios(
    rng: np.random.Generator,
    n_scenarios: int,
    horizon: int,
    mean: float | np.ndarray = 0.0,
    spread: float = 2.0,
    walk_std: float = 0.3,
    n_forces: int | None = None,
) -> np.ndarray:
    """Latent-force scenarios ``W``: a random start plus a random walk, in the force's units.

    Args:
        rng: random generator.
        n_scenarios: ``Ns``.
        horizon: ``N``.
        mean: centre of the first value (scalar, ``(Ns,)``, or ``(Ns, nw)`` with
            ``n_forces``).
        spread: standard deviation of the first value around ``mean``; 2 m/s^2 is the
            stationary std of the sine track's force (``sigma^2 = 4``), a particle
            filter's posterior is narrower.
        walk_std: standard deviation of each later increment (per step).
        n_forces: ``nw``; ``None`` for one component without its axis.

    Returns:
        ``(Ns, N)``, or ``(Ns, N, n_forces)`` when ``n_forces`` is given.
    """
    nw = 1 if n_forces is None else int(n_forces)
    mean = np.asarray(mean, dtype=float)
    if n_forces is None:
        mean = mean[..., None]
    w0 = mean + spread * rng.standard_normal((n_scenarios, nw))
    steps = walk_std * rng.standard_normal((n_scenarios, horizon - 1, nw))
    W = np.concatenate([w0[:, None], w0[:, None] + np.cumsum(steps, axis=1)], axis=1)
    return W[:, :, 0] if n_forces is None else W


def force_std(problem: ScenarioProblem) -> np.ndarray:
    """Stationary standard deviation of each force component ``(nw,)`` of the problem's model."""
    model = problem.model
    cov = model.H @ model.stationary_latent_covariance() @ model.H.T
    return np.sqrt(np.maximum(np.diag(cov), 0.0))


def closed_loop_problems(
    problem: ScenarioProblem,
    controller: ScenarioSolver,
    x_start: Sequence[float],
    n_steps: int = 40,
    seed: int = 0,
    spread: float = 2.0,
    walk_std: float = 0.3,
    redraw: bool = False,
) -> list[Problem]:
    """The problems ``(x0, W)`` met by ``controller`` in a short simulated closed loop.

    The plant is the model's noise-free step
    (:meth:`~lfm_env.model.LatentForceModel.physical_step`) driven by ``u[0]`` and by a
    latent force. Two ways to move the scenarios on:

    * ``redraw=False``: the plant feels scenario 0; ``W`` is shifted by one step and each
      scenario's random walk continues (the scenarios persist, so their spread grows);
    * ``redraw=True``: like a particle filter, the scenarios are redrawn every step around
      the current true force (which itself follows a random walk) with ``spread``.

    Args:
        problem: the problem data (model, ``Ns``, ``N``).
        controller: the solver that closes the loop (warm-started as usual).
        x_start: initial state ``(nx,)``, in the states' units.
        n_steps: number of problems.
        seed: seed of the scenario draws.
        spread: scenario spread of the latent force (see :func:`latent_force_scenarios`).
        walk_std: random-walk increment of the latent force per step.
        redraw: the scenario update rule above.

    Returns:
        ``n_steps`` problems in closed-loop order, ``W`` ``(Ns, N, nw)``.
    """
    rng = np.random.default_rng(seed)
    ns, n, nw = problem.n_scenarios, problem.horizon, problem.nw
    x = np.asarray(x_start, dtype=float)
    if x.shape != (problem.nx,):
        raise ValueError(f"x_start has shape {x.shape}; expected ({problem.nx},)")
    w_true = spread * rng.standard_normal(nw)
    W = latent_force_scenarios(rng, ns, n, w_true, spread, walk_std, n_forces=nw)
    controller.reset()
    problems: list[Problem] = []
    for _ in range(n_steps):
        problems.append((x.copy(), W.copy()))
        sol = controller.solve(x, W)
        w_applied = w_true if redraw else W[0, 0]
        x = problem.model.physical_step(x, sol.u[0], w_applied)
        if redraw:
            w_true = w_true + walk_std * rng.standard_normal(nw)
            W = latent_force_scenarios(rng, ns, n, w_true, spread, walk_std, n_forces=nw)
        else:
            last = W[:, -1] + walk_std * rng.standard_normal((ns, nw))
            W = np.concatenate([W[:, 1:], last[:, None]], axis=1)
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
    """Time every solver on the same warm-started problem sequences, one solver after another.

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


# Spreads and walks as fractions of the force's stationary std (the sine track's: 2 m/s^2).
RECIPES: dict[str, dict[str, Any]] = {
    # The stationary prior for every scenario, scenarios shifted along the run: their spread
    # grows, the problems soon need slack and are degenerate (penalty-dominated).
    "shift": {"spread": 1.0, "walk_std": 0.15, "redraw": False, "n_steps": 40},
    # Scenarios redrawn every step around the true force with a particle-filter-like
    # spread: on the sine track the vehicle drives to the goal.
    "redraw": {"spread": 0.25, "walk_std": 0.15, "redraw": True, "n_steps": 60},
}
TIMED_SOLVERS = ("fast", "ipopt", "ipopt_multiple_shooting")
IPOPT_SOLVERS = ("ipopt", "ipopt_multiple_shooting", "csnlp")  # about 1 s per solve at Ns=150


def default_benchmark(
    n_scenarios: Sequence[int] = (150,),
    recipe: str = "redraw",
    seeds: Sequence[int] = (0,),
    solvers: Sequence[str] = TIMED_SOLVERS,
    ipopt_max_scenarios: int = 150,
    config: Any = DEFAULT_CONFIG,
    x_start: Sequence[float] | None = None,
) -> dict[int, dict[str, SolverTiming]]:
    """Solvers of the registry timed on the fast solver's closed-loop sequences.

    For each scenario count the sequences come from the ``"fast"`` solver's closed loop
    (:func:`closed_loop_problems` with the settings of ``RECIPES[recipe]``, scaled by the
    force's stationary std, one sequence per seed); every solver of ``solvers`` is then
    timed on the same sequences, the IPOPT-based ones (:data:`IPOPT_SOLVERS`) only up to
    ``ipopt_max_scenarios`` scenarios.

    Args:
        n_scenarios: scenario counts.
        recipe: a key of :data:`RECIPES`.
        seeds: one sequence per seed.
        solvers: registry names.
        ipopt_max_scenarios: largest ``Ns`` at which IPOPT-based solvers run.
        config: a YAML path, a dict (whole file), an ExperimentConfig or ``None``.
        x_start: initial state ``(nx,)``; by default the env's (its reset with seed 0).

    Raises:
        ValueError: on an unknown recipe.
    """
    if recipe not in RECIPES:
        raise ValueError(f"recipe={recipe!r}: must be one of {sorted(RECIPES)}")
    settings = dict(RECIPES[recipe])
    n_steps = settings.pop("n_steps")
    cfg = experiment_config(config)
    if x_start is None:
        from experiments.benchmark.problems import env_start

        x_start, _ = env_start(cfg, seed=0)
    out: dict[int, dict[str, SolverTiming]] = {}
    for ns in n_scenarios:
        problem = cfg.make_problem(n_scenarios=int(ns))
        scale = float(np.max(force_std(problem)))
        loop = {**settings, "spread": settings["spread"] * scale}
        loop["walk_std"] = settings["walk_std"] * scale
        sequences = [
            closed_loop_problems(
                problem, make_solver(problem, "fast"), x_start, n_steps, seed=s, **loop
            )
            for s in seeds
        ]
        factories: dict[str, Callable[[], ScenarioSolver]] = {
            name: (lambda problem=problem, name=name: make_solver(problem, name))
            for name in solvers
            if name not in IPOPT_SOLVERS or ns <= ipopt_max_scenarios
        }
        out[ns] = time_solvers(factories, sequences)
    return out
