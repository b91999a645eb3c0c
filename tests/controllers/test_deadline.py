"""agents.deadline: a step's compute budget, and what the agent applies when it stops a solve.

The budgets here are far below any solve (a microsecond), so what happens does not depend
on the machine's speed: every solve stops at its warm start (not usable), and the agent
applies its previous plan shifted while it has one, else the system's fallback input.
"""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

import lfm_env  # noqa: F401
from controllers.agents import make_agent
from controllers.config import ConfigError, load_config


@pytest.mark.parametrize(
    ("text", "value"),
    [("control_period", "control_period"), ("0.15", 0.15), ("null", None), ("none", None)],
)
def test_the_setting_reads_a_keyword_seconds_or_null(text, value):
    cfg = load_config("quick", [f"agents.deadline={text}"])
    assert cfg.agents.deadline == value
    assert load_config({"base": "quick", "agents": {"deadline": value}}).agents.deadline == value


@pytest.mark.parametrize("text", ["soon", "-1", "0", "1e9", "true"])
def test_a_bad_deadline_names_the_field(text):
    with pytest.raises(ConfigError, match="agents.deadline"):
        load_config("quick", [f"agents.deadline={text}"])


def test_the_budget_in_seconds():
    cfg = load_config("quick", ["agents.deadline=control_period"])
    assert cfg.agents.deadline_seconds(cfg.make_model().dt) == pytest.approx(0.2)
    assert load_config("quick").agents.deadline_seconds(0.2) is None


def test_a_solver_without_a_time_limit_refuses_a_deadline():
    cfg = load_config("quick", ["agents.deadline=0.1", "agents.solver=ipopt"])
    with pytest.raises(ConfigError, match="agents.deadline"):
        make_agent("pf", cfg)


def _run(agent_name: str, settings: list[str], steps: int) -> list[dict]:
    cfg = load_config("quick", settings)
    env = gym.make(cfg.env_id, config=cfg.env)
    agent = make_agent(agent_name, cfg)
    obs, _ = env.reset(seed=0)
    agent.reset(seed=0)
    infos = []
    for _ in range(steps):
        obs, *_ = env.step(agent.act(obs))
        infos.append(dict(agent.last_info))
    return infos


def test_a_budget_too_small_for_any_solve_applies_shifted_plans_then_the_fallback():
    # Two converged steps build a plan; then every solve is cut at its warm start.
    free = _run("pf", [], 2)
    assert all(i["deadline_stop"] == "" and i["usable"] for i in free)
    infos = _run("pf", ["agents.deadline=1.0e-9"], 9)
    stops = [i["deadline_stop"] for i in infos]
    assert all(i["status"] == "Maximum_WallTime_Exceeded" for i in infos)
    # No plan yet: the fallback input; then never a usable plan, so again the fallback.
    assert stops == ["fallback"] * 9
    assert all(i["fallback"] == "fallback" for i in infos)


def test_a_plan_is_shifted_under_the_budget_once_one_exists():
    cfg = load_config("quick")
    env = gym.make(cfg.env_id, config=cfg.env)
    agent = make_agent("pf", cfg)
    obs, _ = env.reset(seed=0)
    agent.reset(seed=0)
    obs, *_ = env.step(agent.act(obs))  # a converged plan of N = 7 steps
    plan = agent.last_info["plan"].copy()
    agent.solver.set_max_time(1e-9)  # the agent's own limit takes over from here:
    agent._deadline = 1e-9  # (the budget agents.deadline sets, after one free step)
    stops, actions = [], []
    for _ in range(8):
        action = agent.act(obs)
        obs, *_ = env.step(action)
        stops.append(agent.last_info["deadline_stop"])
        actions.append(action)
    n = plan.shape[0]
    assert stops == ["previous_plan"] * (n - 1) + ["fallback"] * (8 - n + 1)
    np.testing.assert_allclose(actions[0], agent.system.clip_input(plan)[1])


def test_without_a_deadline_nothing_is_stopped_by_it():
    infos = _run("scenario", [], 4)
    assert [i["deadline_stop"] for i in infos] == [""] * 4
