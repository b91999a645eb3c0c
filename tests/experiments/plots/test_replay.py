"""Replays of saved episodes through the world's own scene (``experiments.plots.replay``)."""

from __future__ import annotations

import types

import gymnasium as gym
import numpy as np
import pytest

from experiments import plots
from lfm_env import gp
from lfm_env.cost import QuadraticCost
from lfm_env.env import LatentForceEnv
from lfm_env.model import LatentForceModel
from tests.experiments.plots.point_mass import DT, GOAL, SYSTEM


class DotScene:
    """Draws the position as a white 2 x 2 block on black, 1 px per 0.1 m, below the caption."""

    def __init__(self) -> None:
        self.state = np.zeros(4)
        self.closed = False

    def update(self, state: np.ndarray) -> None:
        self.state = np.asarray(state, dtype=float)

    def draw(self) -> np.ndarray:
        frame = np.zeros((60, 80, 3), dtype=np.uint8)
        col, row = int(self.state[0] * 10), 30 + int(self.state[1] * 10)
        frame[row : row + 2, col : col + 2] = 255
        return frame

    def close(self) -> None:
        self.closed = True


class DotEnv(LatentForceEnv):
    """The point mass as an env whose renderer takes no size or scaling options."""

    def __init__(self, config=None, render_mode=None) -> None:
        model = LatentForceModel(
            SYSTEM, kernel=[gp.matern(1.5, 0.1, 1.0)] * 2, dt=DT, process_noise_std=[0.0] * 4
        )
        cost = QuadraticCost(Q=[1, 1, 0, 0], R=[0.1, 0.1], x_goal=GOAL)
        super().__init__(
            model,
            cost,
            initial_state=np.zeros(4),
            measurement_std=[0.01] * 4,
            render_mode=render_mode,
            scene_factory=lambda env: DotScene(),
        )


DOT_ID = "test_plots/Dot-v0"
if DOT_ID not in gym.registry:
    gym.register(DOT_ID, entry_point=DotEnv)


def test_replay_draws_saved_states_with_the_worlds_own_scene():
    states = np.array([[1.0, 1.0, 0, 0], [2.0, 1.5, 0, 0], [3.5, 2.5, 0, 0]])
    config = types.SimpleNamespace(env_id=DOT_ID, env={"any": "world config"})
    # screen_size and scaling are dropped: this world's env does not take them.
    frames = plots.replay_frames(states, config, screen_size=(10, 10), caption="dot")
    assert len(frames) == 3
    for frame, (x, y, _, _) in zip(frames, states, strict=True):
        assert frame.shape == (60, 80, 3)
        row, col = 30 + int(y * 10), int(x * 10)
        assert frame[row, col].tolist() == [255, 255, 255]
        assert frame[row + 3 :, col + 3 :].max() == 0  # nothing else drawn below-right
    assert frames[0][:12].std() > 0  # the caption strip
    with pytest.raises(ValueError, match="ENV_ID"):
        plots.replay_frames(states, object())
