"""The rl agent: loads a policy freshly trained by lfm-train, acts on the observation only
(float64 actions in the inputs' units), refuses a missing or foreign policy naming
agents.rl_policy, and runs in the same evaluation as the MPC agents."""

from __future__ import annotations

import json
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest

pytest.importorskip("stable_baselines3")

from controllers.agents import AGENT_REGISTRY, make_agent  # noqa: E402
from controllers.agents.rl import RLAgent, policy_features  # noqa: E402
from controllers.config import load_config  # noqa: E402
from experiments.evaluation.run import evaluate  # noqa: E402
from experiments.rl_training import make_training_env, train  # noqa: E402
from lfm_env.config import ConfigError  # noqa: E402

SHORT = {"env": {"max_steps": 12}}
CONFIGS = Path(__file__).resolve().parents[2] / "configs"


@pytest.fixture(scope="module")
def policy(tmp_path_factory):
    """A policy of a short PPO run on the sine track (its .zip path)."""
    out = tmp_path_factory.mktemp("rl")
    train(SHORT, "ppo", timesteps=256, out=out, n_envs=2, seed=1, progress=False)
    return str(out / "policy.zip")


def config_with(policy: str | None) -> dict:
    return {**SHORT, "agents": {"rl_policy": policy}}


def test_rl_is_an_agent_name():
    assert AGENT_REGISTRY["rl"].agent_class is RLAgent


def test_agent_acts_in_the_inputs_units_from_the_observation(policy):
    config = config_with(policy)
    agent = make_agent("rl", config)
    env = gym.make("lfm_env/SineTrack-v0", config=config["env"])
    obs, _ = env.reset(seed=0)
    agent.reset(seed=0)
    system = env.unwrapped.system
    for _ in range(5):
        u = agent.act(obs)
        assert u.dtype == np.float64 and u.shape == (2,)
        assert np.all(u >= system.input_lower) and np.all(u <= system.input_upper)
        assert set(agent.last_info) >= {"estimate", "estimate_std", "solve_time", "success"}
        np.testing.assert_array_equal(agent.last_info["estimate"], obs)
        obs, *_ = env.step(u)


def test_agent_matches_the_training_pipeline(policy):
    """Same features, normalisation and action rescaling as in training."""
    from stable_baselines3 import PPO

    config = load_config(config_with(policy))
    agent = make_agent("rl", config)
    model = PPO.load(policy, device="cpu")
    stats = np.load(policy.replace(".zip", ".npz"))
    env = make_training_env(config)  # the training env's action rescaling
    obs = np.array([3.0, 1.5, 2.0, 0.3])
    z = (policy_features(agent.system, obs) - stats["mean"]) / np.sqrt(
        stats["var"] + stats["epsilon"]
    )
    a, _ = model.predict(np.clip(z, -10, 10).astype(np.float32), deterministic=True)
    rescale = env
    while not isinstance(rescale, gym.wrappers.RescaleAction):
        rescale = rescale.env
    expected = env.unwrapped.system.clip_input(rescale.action(np.clip(a, -1, 1)).astype(float))
    np.testing.assert_allclose(agent.act(obs), expected, rtol=1e-6, atol=1e-7)


def test_features_are_the_state_and_the_constraint_values():
    system = load_config(None).make_model().system
    y = np.array([10.0, 0.5, 3.0, 0.1])
    f = policy_features(system, y)
    np.testing.assert_array_equal(f[:4], y)
    np.testing.assert_allclose(f[4:], np.asarray(system.constraint_values(y)).ravel())


def test_bad_observation_is_refused(policy):
    agent = make_agent("rl", config_with(policy))
    with pytest.raises(ValueError, match="obs"):
        agent.act([0.0, np.nan, 1.0, 0.0])
    with pytest.raises(ValueError, match="obs"):
        agent.act([0.0, 1.0])


def test_agent_never_gets_the_env(policy):
    env = gym.make("lfm_env/SineTrack-v0")
    with pytest.raises(ValueError, match="only the oracle"):
        make_agent("rl", config_with(policy), env=env)


@pytest.mark.parametrize(
    "setting, match",
    [
        (None, r"agents\.rl_policy=None: the 'rl' agent needs a trained policy"),
        ("no/such/policy.zip", r"agents\.rl_policy='no/such/policy.zip': no such file"),
    ],
)
def test_missing_policy_names_the_field(setting, match):
    with pytest.raises(ConfigError, match=match):
        make_agent("rl", config_with(setting))


def test_policy_without_its_normalisation_names_the_field(policy, tmp_path):
    lone = tmp_path / "policy.zip"
    lone.write_bytes(open(policy, "rb").read())
    with pytest.raises(ConfigError, match=r"agents\.rl_policy=.*policy\.npz is missing"):
        make_agent("rl", config_with(str(lone)))


def test_damaged_policy_names_the_field(policy, tmp_path):
    import shutil

    for suffix in (".npz", ".json"):
        shutil.copy(policy.replace(".zip", suffix), tmp_path / f"policy{suffix}")
    (tmp_path / "policy.zip").write_bytes(b"not a zip")
    # Not the archive its set recorded: refused before it is opened.
    with pytest.raises(ConfigError, match=r"agents\.rl_policy=.*policy\.zip does not match"):
        make_agent("rl", config_with(str(tmp_path / "policy.zip")))
    # A set written before the files' SHA-256 were recorded: the archive itself is refused.
    summary = json.loads((tmp_path / "policy.json").read_text())
    del summary["files"]
    (tmp_path / "policy.json").write_text(json.dumps(summary))
    with pytest.raises(ConfigError, match=r"agents\.rl_policy=.*cannot be loaded as ppo"):
        make_agent("rl", config_with(str(tmp_path / "policy.zip")))


def test_policy_of_another_world_is_refused(policy):
    import yaml

    config = yaml.safe_load(open(CONFIGS / "quadrotor.yaml"))
    config["agents"]["rl_policy"] = policy  # trained on the sine track
    # Both worlds happen to have 10 features (nx + ng): the system's name tells them apart.
    with pytest.raises(ConfigError, match=r"agents\.rl_policy=.*trained on the sine_track sys"):
        make_agent("rl", config)


def test_rl_runs_in_the_evaluation_with_an_mpc_agent(policy, tmp_path):
    config = {
        **config_with(policy),
        "agents": {"rl_policy": policy, "horizon": 5, "n_scenarios": 5},
    }
    rows = evaluate(["nominal", "rl"], [0, 1], config, out=tmp_path / "eval", progress=False)
    assert sorted((r["agent"], r["seed"]) for r in rows) == [
        ("nominal", 0),
        ("nominal", 1),
        ("rl", 0),
        ("rl", 1),
    ]
    assert all(r["error"] == "" for r in rows)
    assert all(r["steps"] >= 1 for r in rows if r["agent"] == "rl")
