"""The benchmark's other parts: :func:`sweep_horizons` (fast and condensed IPOPT at several
``N``), :func:`sweep_scenarios` (solve time against ``Ns``), :func:`first_solve` (build and
first solve, in an empty C library cache then warm), :func:`time_particle_filter` and
:func:`time_episode`. Everything is built from the config.
"""

from __future__ import annotations

import contextlib
import math
import time
from collections.abc import Sequence
from typing import Any

import numpy as np

from controllers.feasibility import INFEASIBLE_TOL, SharedConstraints, shared_slack_bound
from controllers.solvers.fast.codegen.build import fresh_cache
from experiments.benchmark.failures import failures_of
from experiments.benchmark.problems import (
    DEFAULT_CONFIG,
    DEFAULT_SEEDS,
    RECORDING_SOLVER,
    SweepAnchor,
    anchors_per_seed,
    env_start,
    experiment_config,
    record_closed_loop,
    scenario_draws,
)
from experiments.benchmark.solvers import (
    GAP_TOL,
    SOLVER_VARIANTS,
    accuracy_summary,
    build_solver,
    build_solvers,
    p95,
    relative_gap,
    run_interleaved,
    speedups,
    timing_summary,
)

DEFAULT_SWEEP_NS = (10, 50, 150, 500, 1000, 5000)
DEFAULT_SWEEP_STEPS = 5  # anchors per seed in the sweep (IPOPT takes ~0.3 s per problem at 150)
DEFAULT_HORIZONS = (7, 15, 30)
# Closed-loop problems per seed timed at each horizon (the first steps of each episode);
# IPOPT takes ~1 s per problem at N = 15 and ~3 s at N = 30 (Ns = 150). At the config's
# own horizon the main closed-loop comparison (whole episodes) is reused.
DEFAULT_HORIZON_STEPS = {15: 8, 30: 2}
HORIZON_SOLVERS = ("fast", "ipopt")  # the second is the objective reference
# Wall-clock limits of one solve in the horizon sweep [s]: IPOPT at N = 30 takes seconds
# (about 10 s on a busy 2-core machine) and can spend minutes on a hard problem; a solve
# that reaches its limit is a failed solve (kind wall_time).
HORIZON_MAX_TIME_S = {"fast": 10.0, "ipopt": 30.0}
SWEEP_SOLVERS = ("fast", "fast_c")  # timed at every Ns
# Timed from this Ns on, and at the largest Ns of a shorter sweep: the solver variants
# (experiments.benchmark.solvers.SOLVER_VARIANTS; the fast solver's C library on two threads,
# which pays for many scenarios).
SWEEP_VARIANTS_MIN_NS = 500
SWEEP_REFERENCE = "ipopt"  # timed, and the objective reference, up to ipopt_max_ns
SWEEP_IPOPT_MAX_NS = 150
DEFAULT_PF_SIZES = (1000, 7000, 20000)
# The particle filter tracks a truth driven by this constant input: the centre of the input
# box plus this fraction of its half width (for the sine track: 0.5 m/s^2, 2.5 deg).
PF_INPUT_OFFSET = 0.1


def sweep_scenarios(
    ns_list: Sequence[int] = DEFAULT_SWEEP_NS,
    horizon: int | None = None,
    config: Any = DEFAULT_CONFIG,
    anchors: Sequence[SweepAnchor] | None = None,
    seeds: Sequence[int] = DEFAULT_SEEDS,
    steps_per_seed: int | None = DEFAULT_SWEEP_STEPS,
    ipopt_max_ns: int = SWEEP_IPOPT_MAX_NS,
    rng_seed: int = 0,
    progress: bool = False,
) -> dict[str, Any]:
    """Solve time against the scenario count ``Ns`` on problems drawn around recorded estimates
    (:func:`.problems.scenario_draws`), each seed's anchors in closed-loop order, warm-started.
    The fast solver runs at every ``Ns``, its variants from :data:`SWEEP_VARIANTS_MIN_NS` and at
    the largest, IPOPT (the objective reference) up to ``ipopt_max_ns``.

    Args:
        ns_list: scenario counts.
        horizon: prediction steps ``N``; by default the config's.
        config: a YAML path, a dict (whole file), an ExperimentConfig or ``None``.
        anchors: recorded estimates; by default recorded here from ``seeds``.
        seeds: env seeds used when ``anchors`` is ``None``.
        steps_per_seed: at most this many anchors per seed (``None``: all).
        ipopt_max_ns: largest ``Ns`` at which IPOPT is timed.
        rng_seed: seed of the scenario draws (the same for every solver).
        progress: show progress bars.

    Returns:
        ``{"horizon", "n_anchors", "results": [{"n_scenarios", "solvers", "summary",
        "speedup", "failures"}]}``, times in milliseconds.
    """
    cfg = experiment_config(config)
    if anchors is None:
        _, anchors = record_closed_loop(cfg, seeds, steps_per_seed, progress)
    sequence = anchors_per_seed(anchors, steps_per_seed)
    results = []
    problem = None
    for ns in ns_list:
        problem = cfg.make_problem(n_scenarios=int(ns), horizon=horizon)
        problems = scenario_draws(problem, sequence, np.random.default_rng([rng_seed, int(ns)]))
        names = list(SWEEP_SOLVERS) + ([SWEEP_REFERENCE] if ns <= ipopt_max_ns else [])
        if ns >= min(SWEEP_VARIANTS_MIN_NS, max(ns_list)):
            names += list(SOLVER_VARIANTS)
        built, info = build_solvers(
            problem, [(name, *SOLVER_VARIANTS.get(name, (name, {}))) for name in names]
        )
        records = run_interleaved(
            built, problem, problems, warmup=True, progress=progress, desc=f"sweep Ns={ns}"
        )
        summary = {name: timing_summary(recs) for name, recs in records.items()}
        if SWEEP_REFERENCE in records:
            for name, recs in records.items():
                summary[name].update(accuracy_summary(recs, records[SWEEP_REFERENCE]))
        results.append(
            {
                "n_scenarios": int(ns),
                "solvers": info,
                "summary": summary,
                "speedup": speedups(summary, records),
                "failures": failures_of(records, "ns_sweep", problem.horizon, int(ns)),
            }
        )
    n = cfg.agents.horizon if problem is None else problem.horizon
    return {"horizon": int(n), "n_anchors": len(sequence), "results": results}


def objective_agreement(
    records: list[dict[str, Any]], reference: list[dict[str, Any]], tol: float = GAP_TOL
) -> dict[str, Any]:
    """Per-problem relative objective gaps to a reference: *within* means at most ``tol`` above
    it (a failed solve never is), over every problem the reference solved.

    Returns:
        ``{"n_compared", "n_within", "share_within_pct", "n_within_abs", "gaps"}``.
    """
    gaps, within, within_abs = [], 0, 0
    for rec, ref in zip(records, reference, strict=True):
        if not ref["success"]:
            continue
        gap = relative_gap(rec, ref) if rec["success"] else math.nan
        gaps.append({"seed": rec["seed"], "step": rec["step"], "rel_gap": gap})
        within += bool(gap <= tol)
        within_abs += bool(abs(gap) <= tol)
    n = len(gaps)
    return {
        "n_compared": n,
        "n_within": within,
        "share_within_pct": 100.0 * within / n if n else math.nan,
        "n_within_abs": within_abs,
        "gaps": gaps,
    }


def feasibility_summary(
    problem: Any, problems: Sequence[Any], records: list[dict[str, Any]] | None = None
) -> dict[str, Any]:
    """How many problems no input can satisfy (:func:`controllers.feasibility.shared_slack_bound`).

    Args:
        problem: the scenario problem of these data.
        problems: ``(seed, step, x0, W)`` tuples.
        records: a solver's :func:`solve_record` per problem, to compare its slack with the bound.

    Returns:
        ``{"n_problems", "n_infeasible", "seeds_infeasible", "bound_median", "bound_max",
        "slack_over_bound_median", "infeasible"}`` (bounds in constraint units).
    """
    shared = SharedConstraints.of(problem)
    bounds = np.array(
        [shared_slack_bound(problem, x0, W, shared=shared).total for _, _, x0, W in problems]
    )
    infeasible = bounds > INFEASIBLE_TOL
    ratio = math.nan
    if records is not None and infeasible.any():
        slack = np.array([rec.get("slack", math.nan) for rec in records], dtype=float)
        if slack.size == bounds.size:
            ratio = float(np.nanmedian(slack[infeasible] / bounds[infeasible]))
    seeds = sorted({int(p[0]) for p, bad in zip(problems, infeasible, strict=True) if bad})
    listed = [
        {"seed": int(p[0]), "step": int(p[1]), "least_slack": float(b)}
        for p, b, bad in zip(problems, bounds, infeasible, strict=True)
        if bad
    ]
    return {
        "n_problems": int(bounds.size),
        "n_infeasible": int(infeasible.sum()),
        "seeds_infeasible": seeds,
        "bound_median": float(np.median(bounds)) if bounds.size else math.nan,
        "bound_max": float(np.max(bounds)) if bounds.size else math.nan,
        "slack_over_bound_median": ratio,
        "infeasible": listed,
    }


def _horizon_row(
    horizon: int,
    problem: Any,
    records: dict[str, list[dict[str, Any]]],
    info: dict[str, Any],
    source: str,
    part: str,
    problems: Sequence[Any] | None = None,
) -> dict[str, Any]:
    fast, ref = HORIZON_SOLVERS
    summary = {name: timing_summary(recs) for name, recs in records.items()}
    agreement = None
    if fast in records and ref in records:
        agreement = objective_agreement(records[fast], records[ref])
    n = len(next(iter(records.values()), []))
    feasibility = None
    failures = failures_of(records, part, horizon, problem.n_scenarios)
    if problems is not None and len(problems) == n:
        feasibility = feasibility_summary(problem, problems, records.get(fast))
        least = {(f["seed"], f["step"]): f["least_slack"] for f in feasibility["infeasible"]}
        for f in failures:  # a failure on a problem no input can satisfy says so
            f["least_slack"] = least.get((f["seed"], f["step"]), 0.0)
    return {
        "horizon": int(horizon),
        "n_scenarios": int(problem.n_scenarios),
        "n_problems": n,
        "source": source,
        "solvers": info,
        "summary": summary,
        "agreement": agreement,
        "feasibility": feasibility,
        "failures": failures,
    }


def sweep_horizons(
    horizons: Sequence[int] = DEFAULT_HORIZONS,
    config: Any = DEFAULT_CONFIG,
    seeds: Sequence[int] = DEFAULT_SEEDS,
    steps_per_seed: dict[int, int] | int | None = None,
    closed_loop: dict[str, Any] | None = None,
    max_time: dict[str, float] | float | None = None,
    progress: bool = False,
    closed_loop_problems: Sequence[Any] | None = None,
    solvers: Sequence[str] = HORIZON_SOLVERS,
) -> dict[str, Any]:
    """The fast solver and IPOPT (condensed) side by side at several horizons ``N``, on problems
    recorded by the scenario agent at that ``N``, in closed-loop order, warm-started,
    interleaved (at ``closed_loop``'s horizon its records are reused).

    Args:
        horizons: prediction steps ``N``.
        config: a YAML path, a dict (whole file), an ExperimentConfig or ``None``.
        seeds: env seeds.
        steps_per_seed: problems per seed, one count or a dict by ``N``
            (:data:`DEFAULT_HORIZON_STEPS`); ``None``: whole episodes.
        closed_loop: the result of :func:`.solvers.time_solvers`.
        max_time: wall-clock limit of one solve [s], one or a dict by solver
            (:data:`HORIZON_MAX_TIME_S`); reaching it fails (kind ``wall_time``).
        progress: show progress bars.
        closed_loop_problems: the problems of ``closed_loop`` (its feasibility figures).
        solvers: the solvers timed (:data:`HORIZON_SOLVERS`; ``("fast",)``: no agreement).

    Returns:
        ``{"results": [{"horizon", "n_scenarios", "n_problems", "source", "solvers",
        "summary", "agreement", "feasibility", "failures"}]}``, times in milliseconds.
    """
    cfg = experiment_config(config)
    counts = DEFAULT_HORIZON_STEPS if steps_per_seed is None else steps_per_seed
    max_time = HORIZON_MAX_TIME_S if max_time is None else max_time
    rows = []
    for n in horizons:
        n = int(n)
        reuse = closed_loop or {}
        if reuse.get("problem", {}).get("horizon") == n and all(
            name in reuse.get("records", {}) for name in solvers
        ):
            records = {name: reuse["records"][name] for name in solvers}
            info = {name: reuse["solvers"][name] for name in solvers}
            problem = cfg.make_problem(horizon=n)
            rows.append(
                _horizon_row(
                    n, problem, records, info, "closed_loop", "closed_loop", closed_loop_problems
                )
            )
            continue
        steps = counts.get(n, 5) if isinstance(counts, dict) else counts
        problems, _ = record_closed_loop(cfg, seeds, steps, progress, horizon=n)
        problem = experiment_config(cfg, horizon=n).make_problem()
        limits = {
            name: max_time.get(name) if isinstance(max_time, dict) else max_time for name in solvers
        }
        built, info = build_solvers(
            problem, [(name, name, {"max_time": limits[name]}) for name in solvers]
        )
        records = run_interleaved(
            built, problem, problems, warmup=True, progress=progress, desc=f"horizon N={n}"
        )
        rows.append(_horizon_row(n, problem, records, info, "recorded", "horizon_sweep", problems))
    return {"results": rows}


def _compile_info(solver: Any) -> dict[str, Any]:
    """What a fast solver says about its C library (read defensively): its condensed model's."""
    model = getattr(solver, "condensed", None)
    info: dict[str, Any] = {"backend": getattr(solver, "backend", None)}
    for key in ("compile_time", "build_time"):
        value = getattr(model, key, None)
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            info[f"codegen_{key}_s"] = float(value)
    for key in dir(model) if model is not None else ():
        if "cache" in key.lower() and not key.startswith("__"):
            value = getattr(model, key, None)
            if isinstance(value, (bool, np.bool_)):
                info["cache_hit"] = bool(value)
                info["cache_flag"] = key
    return info


def first_solve(
    config: Any = DEFAULT_CONFIG,
    problem_data: tuple[np.ndarray, np.ndarray] | None = None,
    solver: str = RECORDING_SOLVER,
    builds: int = 2,
    cold: bool = True,
) -> dict[str, Any]:
    """Build a solver and time its first solve, ``builds`` times in a row; with ``cold`` the
    first build in an empty temporary C library cache (``codegen_cache``: ``"fresh"`` or
    ``"as found"``).

    Args:
        config: a YAML path, a dict (whole file), an ExperimentConfig or ``None``.
        problem_data: ``(x0, W)`` of the first solve; by default the env's start.
        solver: the registry name.
        builds: how many times to build and solve.

    Returns:
        ``{"solver", "results": [{"build_s", "first_solve_ms", "total_s", "success",
        "backend", ...}]}``.
    """
    cfg = experiment_config(config)
    problem = cfg.make_problem()
    if problem_data is None:
        x0, _ = env_start(cfg, 0)
        z0 = np.zeros((problem.n_scenarios, problem.model.latent_dim))
        W = problem.model.sample_latent_forecasts(z0, problem.horizon, np.random.default_rng(0))
    else:
        x0, W = problem_data
    rows = []
    for b in range(builds):
        fresh = cold and b == 0
        with fresh_cache() if fresh else contextlib.nullcontext():
            t0 = time.perf_counter()
            built, _, reason = build_solver(solver, problem)
            t1 = time.perf_counter()
        cache = "fresh" if fresh else "as found"
        if built is None:
            rows.append({"build_s": math.nan, "error": reason, "codegen_cache": cache})
            continue
        sol = built.solve(x0, W)
        t2 = time.perf_counter()
        rows.append(
            {
                "build_s": t1 - t0,
                "first_solve_ms": 1e3 * (t2 - t1),
                "total_s": t2 - t0,
                "success": bool(sol.success),
                **_compile_info(built),
                "codegen_cache": cache,
            }
        )
    return {"solver": solver, "results": rows}


_STATISTICS = {
    "median": lambda t: float(np.median(t)),
    "p95": lambda t: p95(np.asarray(t)),
    "max": lambda t: float(np.max(t)),
}


def _milliseconds(name: str, seconds: Sequence[float], *statistics: str) -> dict[str, float]:
    """``{"<name>_ms_<statistic>": value [ms]}`` of wall times in seconds, for each of
    ``statistics`` (``"median"``, ``"p95"``, ``"max"``) in the order given."""
    return {f"{name}_ms_{s}": 1e3 * _STATISTICS[s](seconds) for s in statistics}


def time_particle_filter(
    n_particles: Sequence[int] = DEFAULT_PF_SIZES,
    config: Any = DEFAULT_CONFIG,
    n_steps: int = 200,
    seed: int = 0,
) -> dict[str, Any]:
    """Time one particle-filter step (transition + update) and the update alone, beside the same
    filter with NumPy's normals, tracking a truth simulated from the env's start under the
    constant input :data:`PF_INPUT_OFFSET`.

    Args:
        n_particles: filter sizes.
        config: a YAML path, a dict (whole file), an ExperimentConfig or ``None``.
        n_steps: timed steps per size.
        seed: seed of the env start, the simulation and the filter.

    Returns:
        ``{"n_steps", "results": [{"n_particles", "step_ms_median", ...}]}``.
    """
    from controllers.estimators.particle_filter import ParticleFilter, gaussian_log_likelihood
    from lfm_env.model import psd_factor

    cfg = experiment_config(config)
    model, truth_model = cfg.make_model(), cfg.env.make_model()
    nx, p = model.nx, model.latent_dim
    meas_std = np.asarray(cfg.measurement_std, dtype=float)
    log_lik = gaussian_log_likelihood(meas_std, np.arange(nx))
    latent_factor = psd_factor(model.stationary_latent_covariance())
    lower, upper = model.system.input_lower, model.system.input_upper
    u = 0.5 * (lower + upper) + PF_INPUT_OFFSET * 0.5 * (upper - lower)
    x_start, z_start = env_start(cfg, seed)
    results = []
    for n in n_particles:
        rng = np.random.default_rng([seed, int(n)])
        truth = np.concatenate([x_start, z_start])
        y = truth[:nx] + rng.standard_normal(nx) * meas_std
        prior = np.concatenate(
            [
                y + rng.standard_normal((int(n), nx)) * meas_std,
                rng.standard_normal((int(n), p)) @ latent_factor.T,
            ],
            axis=1,
        )
        # The filter as the agents run it, and beside it (same prior, same measurements,
        # interleaved) the same filter drawing its noise with NumPy's ziggurat.
        filters = {
            fast: ParticleFilter(
                model.transition,
                log_lik,
                prior,
                np.random.default_rng([seed, int(n), int(fast)]),
                resampling=cfg.agents.resampling,
                ess_threshold=cfg.agents.ess_threshold,
                fast_normals=fast,
            )
            for fast in (True, False)
        }
        t_step, t_update, t_predict, t_numpy = [], [], [], []
        for _ in range(n_steps):
            truth = truth_model.transition(truth[None], u, rng)[0]
            y = truth[:nx] + rng.standard_normal(nx) * meas_std
            # pf.step(u, y) is exactly predict(u) then update(y); timing the halves apart
            # gives both figures from one run.
            pf = filters[True]
            t0 = time.perf_counter()
            pf.predict(u)
            t1 = time.perf_counter()
            pf.update(y)
            t2 = time.perf_counter()
            filters[False].step(u, y)
            t3 = time.perf_counter()
            t_step.append(t2 - t0)
            t_update.append(t2 - t1)
            t_predict.append(t1 - t0)
            t_numpy.append(t3 - t2)
        results.append(
            {
                "n_particles": int(n),
                **_milliseconds("step", t_step, "median", "p95", "max"),
                **_milliseconds("update", t_update, "median", "p95"),
                **_milliseconds("predict", t_predict, "median"),
                **_milliseconds("numpy_normals_step", t_numpy, "median"),
            }
        )
    return {"n_steps": int(n_steps), "results": results}


def time_episode(
    config: Any = DEFAULT_CONFIG, seed: int = 0, solver: str = RECORDING_SOLVER
) -> dict[str, Any]:
    """Wall time of one whole scenario-agent episode: ``setup_s`` (env and agent) apart from
    ``episode_s`` (``env.reset`` to the end), with env and agent seed ``seed``.
    """
    import gymnasium as gym

    import lfm_env  # noqa: F401  (registers the env id)
    from controllers.agents import make_agent

    cfg = experiment_config(config, solver=solver)
    t0 = time.perf_counter()
    env = gym.make(cfg.env_id, config=cfg.env)
    agent = make_agent("scenario", cfg)
    setup = time.perf_counter() - t0
    solve, estimate, step_wall, successes = [], [], [], 0
    info: dict[str, Any] = {}
    try:
        t_start = time.perf_counter()
        obs, info = env.reset(seed=int(seed))
        agent.reset(seed=int(seed))
        done = False
        while not done:
            ts = time.perf_counter()
            action = agent.act(obs)
            obs, _, terminated, truncated, info = env.step(action)
            step_wall.append(time.perf_counter() - ts)
            solve.append(agent.last_info["solve_time"])
            estimate.append(agent.last_info["estimate_time"])
            successes += bool(agent.last_info["success"])
            done = terminated or truncated
        episode = time.perf_counter() - t_start
    finally:
        env.close()
    return {
        "solver": solver,
        "seed": int(seed),
        "setup_s": setup,
        "episode_s": episode,
        "steps": len(step_wall),
        "reached_goal": bool(info.get("is_success", False)),
        "solver_successes": int(successes),
        **_milliseconds("step", step_wall, "median", "max"),
        **_milliseconds("solve", solve, "median", "p95", "max"),
        **_milliseconds("estimate", estimate, "median"),
    }
