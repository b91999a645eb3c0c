"""Real-time iterations (``agents.iterations: rti``): one SQP iteration per control step.

An RTI agent solves its first problem to convergence, then takes ``rti_iterations`` SQP
iterations per step from the plan shifted by one step (no extra starts), and notices a bad
step (:func:`~controllers.agents.mpc.rti_step_problem`: its merit not below the shifted plan's,
or its slack above it) and solves that problem again to convergence. Checked: the config's
choices, a recorded problem on which one iteration raises the slack
(``data/rti_bad_step.npz``, ``data/make_rti_bad_step.py``) noticed by both fast loops and
re-solved by the agent, and a paper episode at ``N = 15`` steered to the goal by RTI as by
converged solves.
"""

from __future__ import annotations

import time
from collections import Counter
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest

import lfm_env  # noqa: F401  (registers the worlds)
from controllers.agents import make_agent
from controllers.agents.mpc import rti_step_problem
from controllers.config import AgentConfig, ConfigError, load_config
from controllers.solvers import make_solver

DATA = dict(np.load(Path(__file__).resolve().parents[1] / "data" / "rti_bad_step.npz"))


def test_the_config_takes_rti_with_the_fast_solvers_only() -> None:
    for solver in ("fast", "fast_c"):
        assert AgentConfig(iterations="rti", solver=solver).iterations == "rti"
    with pytest.raises(ConfigError, match="iterations='rti'.*'converged' with solver 'ipopt'"):
        AgentConfig(iterations="rti", solver="ipopt")
    with pytest.raises(ConfigError, match="iterations='often'"):
        AgentConfig(iterations="often")
    with pytest.raises(ConfigError, match="rti_iterations=0"):
        AgentConfig(iterations="rti", rti_iterations=0)
    with pytest.raises(ConfigError, match="rti_iterations=200"):
        AgentConfig(iterations="rti", rti_iterations=200, max_iter=150)
    assert AgentConfig().iterations == "converged"


def _bad_case():
    problem = load_config("paper").make_problem(
        horizon=int(DATA["horizon"]), n_scenarios=int(DATA["n_scenarios"])
    )
    return problem, DATA["x0"], DATA["W"], DATA["u"]


@pytest.mark.parametrize("name", ["fast", "fast_c"])
def test_one_iteration_that_raises_the_slack_is_noticed(name) -> None:
    problem, x0, W, u = _bad_case()
    rti = make_solver(problem, name).solve(x0, W, u_guess=u, iterations=1)
    assert rti.iterations == 1 and rti.usable  # the merit fell ...
    assert rti.extra["start_merit"] > rti.objective
    assert rti.slack > rti.extra["start_slack"] + 1e-3  # ... and the slack grew
    assert rti_step_problem(rti) == "slack"
    converged = make_solver(problem, name).solve(x0, W, u_guess=u)
    assert converged.success and rti_step_problem(converged) == ""
    assert converged.objective < rti.objective


def test_a_step_without_a_decrease_is_not_usable() -> None:
    problem, x0, W, u = _bad_case()
    # no time for a single iteration: the plan is the shifted one, not below its merit
    stuck = make_solver(problem, "fast", max_time=1e-9).solve(x0, W, u_guess=u, iterations=1)
    assert not stuck.usable and rti_step_problem(stuck) == "not_usable"


def test_the_agent_solves_a_bad_step_again_to_convergence() -> None:
    _, x0, W, _ = _bad_case()
    settings = ["agents.horizon=15", "agents.n_scenarios=20", "agents.iterations=rti"]
    agent = make_agent("scenario", load_config("paper", [*settings, "agents.solver=fast"]))
    # the last step's plan, which the Python loop shifts into the bad case's warm start
    agent.solver._prev_u = DATA["prev"]
    agent._rti_ready = True
    sol, how, _ = agent._solve(x0, W, None, time.perf_counter())
    assert how == "rti_fallback:slack"
    assert sol.success and sol.iterations > 1  # (the RTI iteration counted too)
    # and an ordinary step is a real-time iteration
    _, how, _ = agent._solve(x0, W, None, time.perf_counter())
    assert how == "rti"


def test_rti_steers_a_paper_episode_to_the_goal_as_converged_solves_do() -> None:
    """N = 15, feedback prediction, the compiled loop, env and agent seed 0: every RTI step
    applies its plan, RTI steps are the rule, and the car reaches the goal within two steps of
    the converged agent (measured: 46 against 47 steps, two fallbacks on slack)."""
    settings = ["agents.horizon=15", "agents.prediction=feedback", "agents.solver=fast_c"]
    finished = {}
    for mode in ("converged", "rti"):
        cfg = load_config("paper", [*settings, f"agents.iterations={mode}"])
        env = gym.make(cfg.env_id, config=cfg.env)
        agent = make_agent("scenario", cfg)
        obs, _ = env.reset(seed=0)
        agent.reset(seed=0)
        how = Counter()
        for step in range(80):
            u = agent.act(obs)
            info = agent.last_info
            assert info["usable"] and info["fallback"] == "", (mode, step)
            how[info["sqp_iterations"].split(":")[0]] += 1
            obs, _, terminated, truncated, env_info = env.step(u)
            if terminated or truncated:
                break
        env.close()
        assert env_info.get("is_success"), mode
        finished[mode] = step + 1
        if mode == "rti":
            assert how["converged"] == 1  # the first step
            assert how["rti"] >= 0.8 * finished[mode]
    assert abs(finished["rti"] - finished["converged"]) <= 2


@pytest.mark.parametrize("prediction", ["open_loop", "feedback"])
def test_both_loops_take_the_same_real_time_iterations(prediction) -> None:
    # a converged solve, then one iteration per problem (the limited options: no extra
    # starts, the whole range as trust region, the QP without slacks first only after a
    # QP that needed none, two screened rows per group) on the recorded closed-loop problems
    data = dict(np.load(Path(__file__).resolve().parents[1] / "data" / "recorded_problems.npz"))
    problem = load_config("paper").make_problem(prediction=prediction)
    loops = [make_solver(problem, name, qp_solver="elastic_ipm") for name in ("fast", "fast_c")]
    for i, (x0, W) in enumerate(zip(data["x0"][:6], data["W"][:6], strict=True)):
        a, b = (s.solve(x0, W, iterations=None if i == 0 else 1) for s in loops)
        assert (a.status, a.iterations) == (b.status, b.iterations), i
        assert a.extra["qp_solves"] == b.extra["qp_solves"], i
        np.testing.assert_allclose(a.u, b.u, atol=1e-9)
        assert i == 0 or a.iterations == 1
    # the limit is for that call only: the next solve converges
    assert loops[1].solve(x0, W).success
