"""The agents' default solver is the compiled loop (fast_c); without a C compiler it is the
Python loop after a one-line notice, and the agent runs on."""

from __future__ import annotations

import warnings

import gymnasium as gym

import lfm_env  # noqa: F401
from controllers.agents import make_agent
from controllers.config import AgentConfig, load_config
from controllers.solvers.fast.codegen import build
from controllers.solvers.fast.compiled import FALLBACK_NOTICE, CompiledScenarioSolver


def test_the_agents_default_is_the_compiled_loop():
    assert AgentConfig().solver == "fast_c"
    agent = make_agent("scenario", load_config("quick"))
    assert isinstance(agent.solver, CompiledScenarioSolver) and agent.solver.loop == "c"
    cfg = load_config("quick", ["agents.prediction=feedback"])
    agent = make_agent("scenario", cfg)  # feedback: natively in the compiled loop
    assert isinstance(agent.solver, CompiledScenarioSolver) and agent.solver.loop == "c"


def test_without_a_compiler_the_default_agent_runs_the_python_loop_after_one_notice(
    monkeypatch,
):
    monkeypatch.setenv("CC", "/nonexistent/lfm-no-cc")
    cfg = load_config("quick")
    with build.fresh_cache(), warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        agent = make_agent("pf", cfg)
        env = gym.make(cfg.env_id, config=cfg.env)
        obs, _ = env.reset(seed=0)
        agent.reset(seed=0)
        for _ in range(3):
            obs, *_ = env.step(agent.act(obs))
    notices = [w for w in caught if issubclass(w.category, RuntimeWarning)]
    assert len(notices) == 1 and str(notices[0].message).startswith(FALLBACK_NOTICE[:8])
    assert agent.solver.loop == "python"
    assert agent.last_info["solver_extra"]["loop"] == "python" and agent.last_info["usable"]
