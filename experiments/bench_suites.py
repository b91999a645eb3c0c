"""The benchmark's other parts: the scenario-count sweep, the particle filter, one episode.

* :func:`sweep_scenarios`: solve time against the scenario count ``Ns`` on problems drawn
  around recorded closed-loop estimates, as the scenario agent draws them.
* :func:`time_particle_filter`: one filter step (model transition + update) and the update
  alone, for several particle counts.
* :func:`time_episode`: the wall time of a whole scenario-agent episode.

The closed-loop solver comparison is :func:`experiments.bench_solvers.time_solvers`.
Everything is built from the config; nothing here knows the system.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from typing import Any

import numpy as np

from experiments.bench_problems import (
    DEFAULT_CONFIG,
    DEFAULT_SEEDS,
    ENV_ID,
    RECORDING_SOLVER,
    SweepAnchor,
    anchors_per_seed,
    env_start,
    experiment_config,
    record_closed_loop,
    scenario_draws,
)
from experiments.bench_solvers import (
    accuracy_summary,
    build_solver,
    p95,
    run_interleaved,
    speedups,
    timing_summary,
)

DEFAULT_SWEEP_NS = (10, 50, 150, 500, 1000)
DEFAULT_SWEEP_STEPS = 10  # anchors per seed in the sweep (IPOPT takes ~1 s per problem at 150)
SWEEP_SOLVERS = ("fast", "fast_bicycle")  # timed at every Ns
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
    """Solve time against the scenario count ``Ns`` on closed-loop-like problems.

    For each anchor (a recorded estimate: physical state ``x0``, latent state ``z``) the
    ``Ns`` scenarios are drawn by :func:`experiments.bench_problems.scenario_draws`. The
    anchors of each seed are solved in closed-loop order with warm starts (reset at each
    seed). The fast solvers (:data:`SWEEP_SOLVERS`) run at every ``Ns``; IPOPT on the
    condensed NLP, the objective reference, only for ``Ns <= ipopt_max_ns``.

    Args:
        ns_list: scenario counts.
        horizon: prediction steps ``N``; by default the config's.
        config: a YAML path, a dict (whole file), an ExperimentConfig or ``None``.
        anchors: recorded estimates; by default recorded here from ``seeds``.
        seeds: env seeds used when ``anchors`` is ``None``.
        steps_per_seed: use at most this many anchors per seed (``None``: all).
        ipopt_max_ns: largest ``Ns`` at which IPOPT is timed.
        rng_seed: seed of the scenario draws (the same draws for every solver).
        progress: show progress bars.

    Returns:
        ``{"horizon", "n_anchors", "results": [{"n_scenarios", "solvers", "summary",
        "speedup"}]}``, times in milliseconds.
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
        built, info = {}, {}
        for name in names:
            solver, build_time, reason = build_solver(name, problem)
            info[name] = {"available": solver is not None, "reason": reason}
            info[name]["build_time_s"] = build_time
            if solver is not None:
                built[name] = solver
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
            }
        )
    n = cfg.agents.horizon if problem is None else problem.horizon
    return {"horizon": int(n), "n_anchors": len(sequence), "results": results}


def time_particle_filter(
    n_particles: Sequence[int] = DEFAULT_PF_SIZES,
    config: Any = DEFAULT_CONFIG,
    n_steps: int = 200,
    seed: int = 0,
) -> dict[str, Any]:
    """Time one particle-filter step (model transition + update) and the update alone.

    The filter is the filtering agents' (their model's transition, the Gaussian likelihood
    of the full-state measurement, the config's resampling rule, the prior around the
    first measurement). It tracks a truth simulated with the env's model from the env's
    start, driven by a constant input (:data:`PF_INPUT_OFFSET`), so every update sees a
    plausible measurement.

    Args:
        n_particles: filter sizes.
        config: a YAML path, a dict (whole file), an ExperimentConfig or ``None``.
        n_steps: timed steps per size.
        seed: seed of the env start, the simulation and the filter.

    Returns:
        ``{"n_steps", "results": [{"n_particles", "step_ms_median", "step_ms_p95",
        "step_ms_max", "update_ms_median", "update_ms_p95", "predict_ms_median"}]}``.
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
        pf = ParticleFilter(
            model.transition,
            log_lik,
            prior,
            rng,
            resampling=cfg.agents.resampling,
            ess_threshold=cfg.agents.ess_threshold,
        )
        t_step, t_update, t_predict = [], [], []
        for _ in range(n_steps):
            truth = truth_model.transition(truth[None], u, rng)[0]
            y = truth[:nx] + rng.standard_normal(nx) * meas_std
            # pf.step(u, y) is exactly predict(u) then update(y); timing the halves apart
            # gives both figures from one run.
            t0 = time.perf_counter()
            pf.predict(u)
            t1 = time.perf_counter()
            pf.update(y)
            t2 = time.perf_counter()
            t_step.append(t2 - t0)
            t_update.append(t2 - t1)
            t_predict.append(t1 - t0)
        ms = 1e3
        results.append(
            {
                "n_particles": int(n),
                "step_ms_median": ms * float(np.median(t_step)),
                "step_ms_p95": ms * p95(np.asarray(t_step)),
                "step_ms_max": ms * float(np.max(t_step)),
                "update_ms_median": ms * float(np.median(t_update)),
                "update_ms_p95": ms * p95(np.asarray(t_update)),
                "predict_ms_median": ms * float(np.median(t_predict)),
            }
        )
    return {"n_steps": int(n_steps), "results": results}


def time_episode(
    config: Any = DEFAULT_CONFIG, seed: int = 0, solver: str = RECORDING_SOLVER
) -> dict[str, Any]:
    """Wall time of one whole scenario-agent episode.

    ``setup_s`` (making the env and the agent, i.e. building the solver) is reported apart
    from ``episode_s``, the wall time from ``env.reset`` to the end of the episode.

    Args:
        config: a YAML path, a dict (whole file), an ExperimentConfig or ``None``.
        seed: env seed; the agent is seeded with it too.
        solver: the agent's solver.
    """
    import gymnasium as gym

    import lfm_env  # noqa: F401  (registers the env id)
    from controllers.agents import make_agent

    cfg = experiment_config(config, solver=solver)
    t0 = time.perf_counter()
    env = gym.make(ENV_ID, config=cfg.env)
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
    ms = 1e3
    return {
        "solver": solver,
        "seed": int(seed),
        "setup_s": setup,
        "episode_s": episode,
        "steps": len(step_wall),
        "reached_goal": bool(info.get("is_success", False)),
        "solver_successes": int(successes),
        "step_ms_median": ms * float(np.median(step_wall)),
        "step_ms_max": ms * float(np.max(step_wall)),
        "solve_ms_median": ms * float(np.median(solve)),
        "solve_ms_p95": ms * p95(np.asarray(solve)),
        "solve_ms_max": ms * float(np.max(solve)),
        "estimate_ms_median": ms * float(np.median(estimate)),
    }


__all__ = [
    "DEFAULT_PF_SIZES",
    "DEFAULT_SWEEP_NS",
    "DEFAULT_SWEEP_STEPS",
    "sweep_scenarios",
    "time_episode",
    "time_particle_filter",
]
