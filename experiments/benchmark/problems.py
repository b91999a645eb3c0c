"""The problems the benchmark solves: closed-loop scenario problems recorded from the scenario
agent (:func:`record_closed_loop`: its ``x0``, ``W`` and estimate at every step), and
problems of other scenario counts drawn around them (:func:`scenario_draws`).
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
from tqdm.auto import tqdm

from controllers.config import ExperimentConfig, load_config
from controllers.problem import ScenarioProblem

ENV_ID = "lfm_env/SineTrack-v0"  # the default config's env (recordings use the config's env_id)
DEFAULT_CONFIG = "configs/paper.yaml"
DEFAULT_SEEDS = (0, 1, 2, 3, 4, 5)  # the closed-loop problems: paper episodes of seeds 0..5
RECORDING_SOLVER = "fast"  # the agent's solver while recording (the default controller)


class RecordedProblem(NamedTuple):
    """A scenario problem met in closed loop: ``(seed, step, x0, W)``."""

    seed: int  # env seed of the episode
    step: int  # step index within the episode
    x0: np.ndarray  # (nx,) or (Ns, nx) initial state(s), in the states' units
    W: np.ndarray  # (Ns, N, nw) latent forces, in the force's units


class SweepAnchor(NamedTuple):
    """A recorded estimate around which scenarios are drawn: ``(seed, step, x0, z)``."""

    seed: int  # env seed of the episode
    step: int  # step index within the episode
    x0: np.ndarray  # (nx,) estimated physical state
    z: np.ndarray  # (p,) estimated latent state of the GP


def config_path(config: Any) -> Any:
    """A config as :func:`~controllers.config.load_config` takes it (a preset's name, a path,
    ...); a relative ``configs/NAME.yaml`` that is missing here (the repository's presets
    folder, named from another folder) is the preset ``NAME``."""
    from lfm_env.config.presets import preset_path

    if isinstance(config, (str, os.PathLike)) and not Path(config).is_file():
        path = Path(config)
        preset = preset_path(path.name) if path.parent == Path("configs") else None
        if preset is not None:
            return str(preset)
    return config


def experiment_config(
    config: Any = DEFAULT_CONFIG, solver: str | None = None, horizon: int | None = None
) -> ExperimentConfig:
    """The resolved config (a preset's name, a YAML path, a dict, an ExperimentConfig or
    ``None``), with ``agents.solver`` or ``agents.horizon`` replaced when given (checked).
    """
    cfg = load_config(config_path(config))
    changes: dict[str, Any] = {}
    if solver is not None and solver != cfg.agents.solver:
        changes["solver"] = solver
    if horizon is not None and int(horizon) != cfg.agents.horizon:
        changes["horizon"] = int(horizon)
    if changes:
        # AgentConfig checks its fields on construction, so replace() checks the new values.
        cfg = dataclasses.replace(cfg, agents=dataclasses.replace(cfg.agents, **changes))
    return cfg


def problem_from_config(
    config: Any = DEFAULT_CONFIG, n_scenarios: int | None = None, horizon: int | None = None
) -> ScenarioProblem:
    """The scenario problem the agents of ``config`` solve, with ``Ns`` or ``N`` changed."""
    return experiment_config(config).make_problem(n_scenarios=n_scenarios, horizon=horizon)


def env_start(config: Any = DEFAULT_CONFIG, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """The env's initial physical state ``(nx,)`` and latent state ``(p,)`` for ``seed``.

    Read from the ``info`` of the env's reset (``true_state``, ``latent_state``).
    """
    import gymnasium as gym

    import lfm_env  # noqa: F401  (registers the env id)

    cfg = experiment_config(config)
    env = gym.make(cfg.env_id, config=cfg.env)
    try:
        _, info = env.reset(seed=int(seed))
    finally:
        env.close()
    x = np.asarray(info["true_state"], dtype=float)
    return x, np.asarray(info["latent_state"], dtype=float)


def record_closed_loop(
    config: Any = DEFAULT_CONFIG,
    seeds: Sequence[int] = DEFAULT_SEEDS,
    max_steps: int | None = None,
    progress: bool = False,
    solver: str = RECORDING_SOLVER,
    horizon: int | None = None,
) -> tuple[list[RecordedProblem], list[SweepAnchor]]:
    """Scenario-agent episodes (agent seeded with the env seed): every step's problem and estimate.

    Args:
        config: as for :func:`experiment_config`.
        seeds: env seeds, one episode each.
        max_steps: at most this many steps per episode; ``None``: whole episodes.
        progress: show a progress bar.
        solver: the agent's solver while recording.
        horizon: the agent's horizon ``N``; by default the config's.

    Returns:
        ``(problems, anchors)`` in closed-loop order: ``last_info["x0"]``, ``["W"]``, and the
        estimates split into physical and latent state.
    """
    import gymnasium as gym

    import lfm_env  # noqa: F401  (registers the env id)
    from controllers.agents import make_agent

    cfg = experiment_config(config, solver=solver, horizon=horizon)
    nx = cfg.make_system().nx
    problems: list[RecordedProblem] = []
    anchors: list[SweepAnchor] = []
    for seed in tqdm(list(seeds), desc="record episodes", disable=not progress):
        env = gym.make(cfg.env_id, config=cfg.env)
        try:
            obs, _ = env.reset(seed=int(seed))
            agent = make_agent("scenario", cfg)
            agent.reset(seed=int(seed))
            step, done = 0, False
            while not done and (max_steps is None or step < max_steps):
                action = agent.act(obs)
                info = agent.last_info
                x0 = np.array(info["x0"], dtype=float)
                W = np.array(info["W"], dtype=float)
                problems.append(RecordedProblem(int(seed), step, x0, W))
                estimate = np.asarray(info["estimate"], dtype=float)
                anchors.append(
                    SweepAnchor(int(seed), step, estimate[:nx].copy(), estimate[nx:].copy())
                )
                obs, _, terminated, truncated, _ = env.step(action)
                done = terminated or truncated
                step += 1
        finally:
            env.close()
    return problems, anchors


def record_problems(
    config: Any = DEFAULT_CONFIG,
    seeds: Sequence[int] = DEFAULT_SEEDS,
    max_steps: int | None = None,
    progress: bool = False,
) -> list[RecordedProblem]:
    """The closed-loop scenario problems of :func:`record_closed_loop` (without estimates)."""
    problems, _ = record_closed_loop(config, seeds, max_steps, progress)
    return problems


def anchors_per_seed(anchors: Sequence[SweepAnchor], steps_per_seed: int | None) -> list:
    """The first ``steps_per_seed`` anchors of every seed (``None``: all), in order."""
    counts: dict[int, int] = {}
    out = []
    for a in anchors:
        counts[a.seed] = counts.get(a.seed, 0) + 1
        if steps_per_seed is None or counts[a.seed] <= steps_per_seed:
            out.append(a)
    return out


def scenario_draws(
    problem: ScenarioProblem, anchors: Sequence[SweepAnchor], rng: np.random.Generator
) -> list[RecordedProblem]:
    """Problems of ``problem``'s size around recorded estimates, drawn as the agent draws
    (:meth:`~lfm_env.model.LatentForceModel.sample_latent_forecasts` from each anchor's ``z``).
    """
    model, ns = problem.model, problem.n_scenarios
    out = []
    for a in anchors:
        z0 = np.broadcast_to(a.z, (ns, a.z.size))
        W = model.sample_latent_forecasts(z0, problem.horizon, rng)
        out.append(RecordedProblem(a.seed, a.step, a.x0, W))
    return out
