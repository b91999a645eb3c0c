"""The benchmark's closed-loop problems (``experiments.benchmark.problems``)."""

from __future__ import annotations

import numpy as np

from experiments.benchmark import problems as benchmark_problems


def test_recording_keeps_the_agents_problems_and_estimates() -> None:
    cfg = benchmark_problems.experiment_config()
    problem = cfg.make_problem()
    problems, anchors = benchmark_problems.record_closed_loop(cfg, seeds=[3], max_steps=2)
    assert [(p.seed, p.step) for p in problems] == [(3, 0), (3, 1)]
    assert [(a.seed, a.step) for a in anchors] == [(3, 0), (3, 1)]
    for p, a in zip(problems, anchors, strict=True):
        x0, W = problem.check_data(p.x0, p.W)  # the agent's problem size
        assert np.array_equal(x0[0], a.x0)  # the scenarios start from the estimate
        assert a.z.shape == (problem.model.latent_dim,)
    # Draws of another size around the anchors, as the agent draws them.
    small = cfg.make_problem(n_scenarios=5)
    draws = benchmark_problems.scenario_draws(small, anchors, np.random.default_rng(0))
    assert [d.W.shape for d in draws] == [(5, small.horizon, small.nw)] * 2
    assert np.allclose(draws[0].W[:, 0], small.model.latent_force(anchors[0].z))


def test_the_recording_runs_the_configs_own_world() -> None:
    # The quadrotor's config records quadrotor problems (the env of its env_id).
    problems, anchors = benchmark_problems.record_closed_loop("quadrotor", seeds=[0], max_steps=2)
    cfg = benchmark_problems.experiment_config("quadrotor")
    assert [(p.seed, p.step) for p in problems] == [(0, 0), (0, 1)]
    assert problems[0].W.shape[1:] == (cfg.agents.horizon, cfg.make_system().nw)
    assert anchors[0].x0.shape == (cfg.make_system().nx,)
