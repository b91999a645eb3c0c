"""A planar point mass with a wall, an obstacle and a speed bound, defined here as a user
would, and a made-up episode of it: the figures' tests draw a system the library does not
know."""

from __future__ import annotations

import numpy as np

from lfm_env.system import ControlSystem
from lfm_env.xp import xp
from tests.point_mass import point_mass_rhs

WALL_Y = 2.0  # [m] the wall: y <= 2
OBSTACLE = (2.0, 1.6, 0.4)  # [m] centre x, centre y and radius of the round obstacle
SPEED_MAX = 1.5  # [m/s] bound on v_x
DT = 0.1  # [s]


def point_mass_constraints(x):
    px, py, vx, _ = xp.unstack(x)
    cx, cy, r = OBSTACLE
    return xp.stack([py - WALL_Y, r - xp.sqrt((px - cx) ** 2 + (py - cy) ** 2), vx - SPEED_MAX])


def point_mass_system() -> ControlSystem:
    return ControlSystem(
        name="point_mass",
        state_names=("q_x [m]", "q_y [m]", "v_x [m/s]", "v_y [m/s]"),
        input_names=("a_x [m/s^2]", "f_y [N]"),
        rhs=point_mass_rhs,
        input_lower=(-2.0, -3.0),
        input_upper=(2.0, 3.0),
        constraints=point_mass_constraints,
        constraint_names=("wall [m]", "obstacle [m]", "speed_x [m/s]"),
        force_names=("w_x [m/s^2]", "w_y [N]"),
        constraint_groups={"keep_out": (0, 1), "speed": (2,)},
    )


SYSTEM = point_mass_system()
GOAL = np.array([5.0, 0.5, 0.0, 0.0])


def synthetic_episode(T: int = 30) -> dict[str, np.ndarray]:
    """Arrays shaped as a saved episode of the point mass: a straight path below the obstacle."""
    t = np.arange(T + 1) * DT
    x = np.stack([t * 1.8, 0.3 + 0.3 * t, 1.8 + 0.05 * np.sin(t), np.full_like(t, 0.3)], axis=1)
    est = x[:T] + 0.02
    w = np.stack([np.sin(t[:T]), np.cos(t[:T])], axis=1)
    excess = np.maximum(SYSTEM.constraint_excess(x[1:]), 0.0)
    return {
        "true_state": x,
        "estimate": np.concatenate([est, np.zeros((T, 3))], axis=1),  # + latent states
        "estimate_std": np.full((T, 7), 0.05),
        "action": np.tile([0.5, -1.0], (T, 1)),
        "latent_force": w,
        "latent_force_est": w + 0.1,
        "latent_force_std": np.full((T, 2), 0.2),
        "keep_out_excess": excess[:, :2].max(axis=1),
        "speed_excess": excess[:, 2],
    }


def rendered(fig) -> np.ndarray:
    fig.canvas.draw()
    return np.asarray(fig.canvas.buffer_rgba())[..., :3]
