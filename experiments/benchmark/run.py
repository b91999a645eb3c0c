"""Speed and accuracy benchmark of the scenario MPC solvers, the particle filter and an episode
(:func:`run_benchmark`; the command line is :mod:`experiments.cli.benchmark`).

Its parts: closed-loop problems recorded from the scenario agent (:mod:`.problems`), the
solvers side by side on them (:mod:`.solvers`), the horizon and scenario sweeps, first solve,
filter and episode (:mod:`.suites`), the compiled loop and the export (:mod:`.compiled`),
every failed solve, and the named checks and report (:mod:`.checks`, :mod:`.report`).
Figures are medians and percentiles of one run; a solver that cannot be built is listed as
unavailable with the reason and its checks are SKIP. See ``docs/benchmark.md``.
"""

from __future__ import annotations

import os
import platform
import time
from collections.abc import Sequence
from importlib import metadata
from typing import Any

from controllers.solvers import SOLVERS
from experiments.benchmark.checks import check_thresholds, run_checks
from experiments.benchmark.compiled import AGREEMENT_NS, time_compiled
from experiments.benchmark.problems import (
    DEFAULT_CONFIG,
    DEFAULT_SEEDS,
    RECORDING_SOLVER,
    experiment_config,
    record_closed_loop,
)
from experiments.benchmark.solvers import time_solvers
from experiments.benchmark.suites import (
    DEFAULT_HORIZONS,
    DEFAULT_PF_SIZES,
    DEFAULT_SWEEP_NS,
    DEFAULT_SWEEP_STEPS,
    HORIZON_SOLVERS,
    first_solve,
    sweep_horizons,
    sweep_scenarios,
    time_episode,
    time_particle_filter,
)

# Recorded steps per seed: a paper episode with the fast solver takes ~45 steps, so 50 keeps
# whole episodes while capping a failing one (151 steps).
DEFAULT_MAX_STEPS = 50
# csnlp (~0.8 s per problem) is left out of the default run to keep it near 10 minutes.
DEFAULT_SOLVERS = tuple(s for s in SOLVERS if s != "csnlp")


def _versions() -> dict[str, str | None]:
    out: dict[str, str | None] = {"python": platform.python_version()}
    for dist in ("numpy", "casadi", "csnlp", "scipy"):
        try:
            out[dist] = metadata.version(dist)
        except metadata.PackageNotFoundError:
            out[dist] = None
    return out


def _load() -> list[float] | None:
    try:
        return [float(x) for x in os.getloadavg()]
    except (AttributeError, OSError):
        return None


def all_failures(results: dict[str, Any]) -> list[dict[str, Any]]:
    """Every failed solve of a result: closed loop, horizons (not reused rows), Ns sweep."""
    out = list(results.get("closed_loop", {}).get("failures", []))
    for row in results.get("horizons", {}).get("results", []):
        if row.get("source") != "closed_loop":
            out += row["failures"]
    for row in results.get("sweep", {}).get("results", []):
        out += row.get("failures", [])
    return out


def run_benchmark(
    config: Any = DEFAULT_CONFIG,
    seeds: Sequence[int] = DEFAULT_SEEDS,
    max_steps: int = DEFAULT_MAX_STEPS,
    solvers: Sequence[str] = DEFAULT_SOLVERS,
    horizons: Sequence[int] = DEFAULT_HORIZONS,
    horizon_steps: dict[int, int] | int | None = None,
    horizon_max_time: dict[str, float] | float | None = None,
    horizon_solvers: Sequence[str] = HORIZON_SOLVERS,
    sweep_ns: Sequence[int] = DEFAULT_SWEEP_NS,
    sweep_steps_per_seed: int | None = DEFAULT_SWEEP_STEPS,
    pf_sizes: Sequence[int] = DEFAULT_PF_SIZES,
    pf_steps: int = 200,
    thresholds: dict[str, float] | None = None,
    progress: bool = True,
    compiled: bool = True,
) -> dict[str, Any]:
    """Run every part of the benchmark and judge the checks.

    Args:
        config: a YAML path, a dict (whole file), an ExperimentConfig or ``None``.
        seeds: episode seeds for the recorded problems.
        max_steps: recorded steps per seed.
        solvers: solvers of the closed-loop comparison (:data:`controllers.solvers.SOLVERS`).
        horizons: horizons ``N`` of the horizon sweep (empty: none).
        horizon_steps: problems per seed at each horizon (an int, or a dict by ``N``).
        horizon_max_time: wall-clock limit of one solve in the horizon sweep [s], one or a
            dict by solver name.
        horizon_solvers: the solvers of the horizon sweep (``("fast",)`` for a smoke run).
        sweep_ns: scenario counts of the sweep (empty: no sweep).
        sweep_steps_per_seed: anchors per seed in the sweep.
        pf_sizes: particle-filter sizes (empty: no filter timing).
        pf_steps: timed filter steps per size.
        thresholds: check bounds to change, by key (:data:`.checks.DEFAULT_THRESHOLDS`).
        progress: show progress bars.
        compiled: the compiled loop's plan agreement and the exported controllers.

    Returns:
        ``meta``, ``closed_loop``, ``horizons``, ``sweep``, ``first_solve``,
        ``particle_filter``, ``episode``, ``compiled``, ``failures`` and ``checks``.

    Raises:
        ValueError: for an unknown solver name or threshold key, or a bad config.
    """
    for name in solvers:
        if name not in SOLVERS:
            raise ValueError(f"unknown solver {name!r}; choose one of {SOLVERS}")
    thresholds = check_thresholds(thresholds)
    t0 = time.perf_counter()
    cfg = experiment_config(config)
    meta: dict[str, Any] = {
        "config": str(config),
        "seeds": list(seeds),
        "max_steps": int(max_steps),
        "solvers": list(solvers),
        "horizon_solvers": list(horizon_solvers),
        "recording_solver": RECORDING_SOLVER,
        "thresholds": thresholds,
        "started": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
        "platform": platform.platform(),
        "cpu_count": os.cpu_count(),
        "load_average_start": _load(),
        "versions": _versions(),
        "times_unit": "ms unless the key ends in _s",
    }
    part_times: dict[str, float] = {}
    meta["part_times_s"] = part_times

    def timed(name: str, fn: Any, *args: Any, **kwargs: Any) -> Any:
        start = time.perf_counter()
        out = fn(*args, **kwargs)
        part_times[name] = time.perf_counter() - start
        return out

    problems, anchors = timed("record", record_closed_loop, cfg, seeds, max_steps, progress)
    results: dict[str, Any] = {"meta": meta}
    results["closed_loop"] = timed(
        "closed_loop", time_solvers, problems, solvers, config=cfg, progress=progress
    )
    if horizons:
        results["horizons"] = timed(
            "horizons",
            sweep_horizons,
            horizons,
            config=cfg,
            seeds=seeds,
            steps_per_seed=horizon_steps,
            closed_loop=results["closed_loop"],
            max_time=horizon_max_time,
            progress=progress,
            closed_loop_problems=problems,
            solvers=horizon_solvers,
        )
    if sweep_ns:
        results["sweep"] = timed(
            "sweep",
            sweep_scenarios,
            sweep_ns,
            horizon=results["closed_loop"]["problem"]["horizon"],
            config=cfg,
            anchors=anchors,
            steps_per_seed=sweep_steps_per_seed,
            progress=progress,
        )
    first = (problems[0].x0, problems[0].W) if problems else None
    results["first_solve"] = timed("first_solve", first_solve, cfg, first)
    if pf_sizes:
        results["particle_filter"] = timed(
            "particle_filter", time_particle_filter, pf_sizes, config=cfg, n_steps=pf_steps
        )
    results["episode"] = timed("episode", time_episode, cfg, seed=int(seeds[0]))
    if compiled:
        large = tuple(ns for ns in AGREEMENT_NS if ns in sweep_ns)
        results["compiled"] = timed("compiled", time_compiled, cfg, problems, anchors, large)
    results["failures"] = all_failures(results)
    results["checks"] = run_checks(results, thresholds)
    meta["load_average_end"] = _load()
    meta["total_time_s"] = time.perf_counter() - t0
    return results
