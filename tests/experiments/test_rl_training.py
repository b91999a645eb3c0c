"""The RL baseline's training (``experiments.rl_training``): a short PPO/SAC run through
gym.make saves a policy the rl agent can load; the training reward; fixed seeds; bad
arguments named."""

from __future__ import annotations

import json

import gymnasium as gym
import numpy as np
import pytest

pytest.importorskip("stable_baselines3")

from controllers.config import load_config  # noqa: E402
from experiments.rl_training import (  # noqa: E402
    TrainingReward,
    make_training_env,
    reward_scale,
    train,
)

SHORT = {"env": {"max_steps": 30}}


def test_ppo_smoke_run_saves_policy_stats_and_summary(tmp_path):
    summary = train(SHORT, "ppo", timesteps=256, out=tmp_path, n_envs=2, progress=False)
    for name in ("policy.zip", "policy.npz", "policy.json"):
        assert (tmp_path / name).is_file()
    saved = json.loads((tmp_path / "policy.json").read_text())
    assert saved == summary
    assert saved["algo"] == "ppo" and saved["env_id"] == "lfm_env/SineTrack-v0"
    assert saved["timesteps"] >= 256 and saved["n_envs"] == 2
    assert saved["n_features"] == 4 + 6  # the state and the six constraint values
    stats = np.load(tmp_path / "policy.npz")
    assert stats["mean"].shape == (10,) and np.all(stats["var"] > 0.0)


def test_sac_smoke_run(tmp_path):
    summary = train(SHORT, "sac", timesteps=120, out=tmp_path, n_envs=1, progress=False)
    assert summary["algo"] == "sac" and summary["timesteps"] >= 120
    assert (tmp_path / "policy.zip").is_file()


def test_same_seed_same_policy(tmp_path):
    from stable_baselines3 import PPO

    params = []
    for run in ("a", "b", "c"):
        seed = 3 if run != "c" else 4
        train(SHORT, "ppo", timesteps=128, out=tmp_path / run, seed=seed, n_envs=2, progress=False)
        policy = PPO.load(tmp_path / run / "policy.zip", device="cpu").policy
        params.append(np.concatenate([p.detach().numpy().ravel() for p in policy.parameters()]))
    np.testing.assert_array_equal(params[0], params[1])
    assert not np.array_equal(params[0], params[2])


def test_training_env_normalises_actions_and_features():
    env = make_training_env(load_config(SHORT))
    assert env.action_space.dtype == np.float32
    np.testing.assert_array_equal(env.action_space.low, [-1.0, -1.0])
    np.testing.assert_array_equal(env.action_space.high, [1.0, 1.0])
    obs, _ = env.reset(seed=0)
    assert obs.shape == (10,) and env.observation_space.contains(obs)
    assert env.spec.max_episode_steps == 30


def test_training_reward_scales_penalises_violations_and_failure():
    config = load_config(SHORT)
    scale = reward_scale(config)
    assert scale == pytest.approx(2 * 62.83**2 + (1.0 - 4.0) ** 2)  # Q = (2, 2, 1, 0)
    raw = gym.make(config.env_id, config=config.env)
    env = TrainingReward(gym.make(config.env_id, config=config.env), scale, 0.5, 30)
    # Well off the track: one step leaves the safety box (10 m beyond the band).
    start = {"initial_state": [20.0, 20.0, 3.0, 0.0]}
    raw.reset(seed=1, options=start)
    env.reset(seed=1, options=start)
    _, r_raw, term_raw, _, info = raw.step([0.0, 0.0])
    _, r, terminated, _, _ = env.step([0.0, 0.0])
    assert term_raw and terminated and info["failure"] and info["violated_groups"] >= 1.0
    per_step = r_raw / scale - 0.5 * info["violated_groups"]
    assert r == pytest.approx(per_step * 30)  # this step and the 29 the limit had left
    # Inside every constraint: the scaled reward only.
    raw.reset(seed=2)
    env.reset(seed=2)
    _, r_raw, *_ = raw.step([0.0, 0.0])
    _, r, *_ = env.step([0.0, 0.0])
    assert r == pytest.approx(r_raw / scale)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"algo": "dqn"}, r"^algo='dqn': must be one of"),
        ({"timesteps": 0}, r"^timesteps=0: must be an integer in \[1,"),
        ({"minutes": 0.0}, r"^minutes=0.0: must be > 0"),
        ({"minutes": float("nan")}, r"^minutes=nan: must be > 0"),
        ({"n_envs": 0}, r"^n_envs=0: must be an integer in \[1, 64\]"),
        ({"cost_weight": -1.0}, r"^cost_weight=-1.0: must be >= 0"),
    ],
)
def test_bad_arguments_name_the_argument(tmp_path, kwargs, match):
    with pytest.raises(ValueError, match=match):
        train(SHORT, **{"out": tmp_path, "progress": False, **kwargs})
    assert not (tmp_path / "policy.zip").exists()
