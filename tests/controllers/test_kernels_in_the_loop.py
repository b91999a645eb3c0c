"""Other kernels for the hidden force (env) and for the agents' belief (agents.latent_force)."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

import lfm_env  # noqa: F401
from controllers.agents import make_agent
from lfm_env.config import ConfigError


@pytest.mark.parametrize(
    "latent_force",
    [
        {"kernel": "squared_exponential", "variance": 2.0, "lengthscale": 3.0, "order": 6},
        {"kernel": "periodic", "variance": 2.0, "lengthscale": 1.0, "period": 6.0},
    ],
    ids=["squared_exponential", "periodic"],
)
def test_env_draws_the_configured_kernel(latent_force):
    env = gym.make("lfm_env/SineTrack-v0", config={"env": {"latent_force": latent_force}})
    kernel = env.unwrapped.model.kernel
    w = []
    for seed in range(400):
        env.reset(seed=seed)
        w.append(env.unwrapped.preview_latent_force(6))
    w = np.array(w)
    # Variance at one time and covariance at lag 1 s against the kernel's state-space form.
    var_ss = float(kernel.state_space_covariance(np.array([0.0]))[0])
    cov_ss = float(kernel.state_space_covariance(np.array([1.0]))[0])
    n = len(w)
    assert np.var(w[:, 0]) == pytest.approx(var_ss, abs=5 * var_ss * np.sqrt(2 / n))
    emp_cov = np.mean(w[:, 0] * w[:, 5])
    assert emp_cov == pytest.approx(cov_ss, abs=5 * var_ss / np.sqrt(n))


def test_periodic_force_is_periodic():
    cfg = {"env": {"latent_force": {"kernel": "periodic", "lengthscale": 1.0, "period": 2.0}}}
    env = gym.make("lfm_env/SineTrack-v0", config=cfg)
    env.reset(seed=3)
    w = env.unwrapped.preview_latent_force(40)  # 8 s, period 2 s = 10 steps
    np.testing.assert_allclose(w[10:], w[:-10], atol=1e-6)


@pytest.mark.parametrize(
    "latent_force, key",
    [
        ({"kernel": "rbf"}, "kernel"),
        ({"kernel": "periodic", "lengthscale": 0.1}, "harmonics"),
        ({"kernel": "squared_exponential", "order": 20}, "order"),
        ({"kernel": "periodic", "period": -1.0}, "period"),
        ({"kernel": "periodic", "discretization": "euler_maruyama"}, "euler_maruyama"),
    ],
)
def test_bad_kernel_settings_name_the_problem(latent_force, key):
    with pytest.raises(ConfigError, match=key):
        gym.make("lfm_env/SineTrack-v0", config={"env": {"latent_force": latent_force}})


def test_agents_model_their_own_belief_of_the_force():
    cfg = {
        "env": {"max_steps": 3},
        "agents": {
            "n_particles": 300,
            "n_scenarios": 5,
            "latent_force": {"kernel": "squared_exponential", "variance": 1.0, "lengthscale": 2.0},
        },
    }
    agent = make_agent("scenario", cfg)
    assert type(agent.model.kernel).__name__ == "SquaredExponential"
    assert agent.model.latent_dim == 6
    env = gym.make("lfm_env/SineTrack-v0", config=cfg)
    assert env.unwrapped.model.latent_dim == 3  # the world keeps its Matern 5/2 force
    obs, _ = env.reset(seed=0)
    agent.reset(seed=0)
    for _ in range(3):
        obs, *_ = env.step(agent.act(obs))
    assert agent.last_info["estimate"].shape == (4 + 6,)
