"""The agent protocol (``controllers.agents.protocol``): the Agent check, last_info, and
stable-baselines3's ``predict`` on the MPC agents."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import pytest
import yaml

import lfm_env  # noqa: F401  (registers the envs)
from controllers.agents import AGENT_REGISTRY, make_agent
from controllers.agents.protocol import (
    INFO_DEFAULTS,
    Agent,
    AgentInfo,
    SB3Policy,
    SB3Predict,
    is_agent,
    last_info,
)
from controllers.config import load_config

REPO = Path(__file__).resolve().parents[2]
TINY = {
    "env": {"max_steps": 15},
    "agents": {"horizon": 5, "n_scenarios": 5, "n_particles": 300},
}


class Recorder(SB3Predict):
    """Records its resets and the observations it is given; acts with zeros."""

    def __init__(self) -> None:
        self.resets: list[int | None] = []
        self.seen: list[np.ndarray] = []

    def reset(self, seed: int | None = None) -> None:
        self.resets.append(seed)

    def act(self, obs: Any) -> np.ndarray:
        self.seen.append(np.asarray(obs))
        return np.zeros(2)


def test_the_protocol_check():
    agent = make_agent("nominal", TINY)
    assert isinstance(agent, Agent) and is_agent(agent)
    assert isinstance(Recorder(), Agent)
    assert not is_agent(Recorder)  # a class is a factory, not an agent
    assert not isinstance(object(), Agent) and not is_agent("reset act")
    # The MPC agents fill every documented last_info key.
    agent.reset(seed=0)
    agent.act(np.array([0.0, 0.0, 1.0, 0.7]))
    assert set(INFO_DEFAULTS) - set(last_info(agent)) <= {
        "latent_force",
        "latent_force_std",
        "filter_reset",
        "estimator",
    }  # the filtering agents' keys


def test_last_info_defaults_and_bad_types():
    assert set(AgentInfo.__annotations__) == set(INFO_DEFAULTS)  # one list of keys
    assert INFO_DEFAULTS["success"] is True and INFO_DEFAULTS["fallback"] == ""
    assert last_info(Recorder()) == {}
    bad = Recorder()
    bad.last_info = ["estimate"]  # type: ignore[attr-defined]
    with pytest.raises(TypeError, match="last_info of agent 'Recorder' is a list"):
        last_info(bad)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_predict_batches_resets_at_episode_starts_and_takes_float32(dtype):
    agent = Recorder()
    obs = np.array([[0.0, 1.0, 2.0, 0.5]], dtype=dtype)
    action, state = agent.predict(obs, episode_start=np.array([True]))
    assert action.shape == (1, 2) and action.dtype == np.float64 and state is None
    agent.predict(obs, episode_start=np.array([False]))
    agent.predict(obs, episode_start=np.array([True]))
    assert agent.resets == [0, 1]  # episode k is reset with seed predict_seed + k
    single, _ = agent.predict(obs[0])  # an unbatched observation gives a plain action
    assert single.shape == (2,) and agent.resets == [0, 1]
    assert all(np.array_equal(seen, obs[0]) for seen in agent.seen)

    fresh = Recorder()
    fresh.predict_seed = 10
    fresh.predict(obs[0])  # no episode_start: reset at the first call only
    fresh.predict(obs[0])
    assert fresh.resets == [10]


def test_predict_refuses_more_than_one_env():
    with pytest.raises(ValueError, match=r"shape \(3, 4\); one agent controls one env"):
        Recorder().predict(np.zeros((3, 4)), episode_start=np.ones(3, bool))
    with pytest.raises(ValueError, match=r"shape \(1, 2, 4\)"):
        Recorder().predict(np.zeros((1, 2, 4)))


def test_sb3_policy_wraps_any_agent():
    class Plain:
        def reset(self, seed=None):
            self.seed = seed

        def act(self, obs):
            return -np.asarray(obs)[:2]

    plain = Plain()
    policy = SB3Policy(plain, predict_seed=5)
    action, _ = policy.predict(np.ones((1, 4), np.float32), episode_start=np.array([True]))
    assert np.array_equal(action, [[-1.0, -1.0]]) and plain.seed == 5
    assert policy.last_info == {}
    with pytest.raises(TypeError, match="no reset"):
        SB3Policy(object())


def quick_config(max_steps: int) -> dict:
    config = yaml.safe_load((REPO / "configs" / "quick.yaml").read_text())
    config.setdefault("env", {})["max_steps"] = max_steps
    return config


def test_sb3_evaluate_policy_runs_the_scenario_agent_as_our_evaluation_does():
    pytest.importorskip("stable_baselines3")
    from stable_baselines3.common.evaluation import evaluate_policy
    from stable_baselines3.common.monitor import Monitor
    from stable_baselines3.common.vec_env import DummyVecEnv

    from experiments.evaluation.run import agent_seed, run_episode

    cfg = load_config(quick_config(max_steps=12))
    vec_env = DummyVecEnv([lambda: Monitor(gym.make(cfg.env_id, config=cfg.env))])
    vec_env.seed(3)
    agent = make_agent("scenario", cfg)
    agent.predict_seed = agent_seed(3, "scenario")  # the seed our evaluation gives it
    rewards, lengths = evaluate_policy(
        agent, vec_env, n_eval_episodes=2, return_episode_rewards=True, warn=False
    )
    assert lengths == [12, 12] and all(np.isfinite(rewards))
    assert agent.last_info["success"] in (True, False) and "estimate" in agent.last_info

    # SB3's loop and ours run the same first episode: same env seed, same agent seed.
    row, _ = run_episode("scenario", cfg, seed=3, record=False)
    assert rewards[0] == pytest.approx(-row["cost"], rel=1e-9)
    assert rewards[1] != rewards[0]  # the second episode is another one


def test_every_agent_with_an_estimator_refuses_zero_measurement_noise():
    from controllers.agents import check_agent_config, needs_measurement_noise

    config = load_config({"env": {"measurement_noise_std": [0.15, 0.0, 0.15, 0.5]}})
    needing = sorted(n for n in AGENT_REGISTRY if needs_measurement_noise(n))
    assert {"pf", "scenario", "scenario_particles", "robust"} <= set(needing)
    for name in needing:
        with pytest.raises(ValueError, match=rf"env\.measurement_noise_std=.*all > 0.*'{name}'"):
            check_agent_config(name, config)
    for name in sorted(set(AGENT_REGISTRY) - set(needing) - {"rl"}):
        check_agent_config(name, config)  # nominal and oracle read no noise
    # rl reads no noise either; it stops only at its missing policy (agents.rl_policy).
    with pytest.raises(ValueError, match=r"agents\.rl_policy"):
        check_agent_config("rl", config)
