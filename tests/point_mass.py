"""The planar point mass the tests define as a user would: ``[p_x, p_y, v_x, v_y]`` pushed by
the inputs and a latent force on both axes."""

from __future__ import annotations

from typing import Any

from lfm_env.system import ControlSystem
from lfm_env.xp import xp


def point_mass_rhs(x, u, w):
    """``d[p_x, p_y, v_x, v_y]/dt = [v_x, v_y, a_x + w_x, a_y + w_y]``."""
    _, _, vx, vy = xp.unstack(x)
    ax, ay = xp.unstack(u)
    wx, wy = xp.unstack(w)
    return xp.stack([vx, vy, ax + wx, ay + wy])


def point_mass_system(name: str = "point_mass", **constraints: Any) -> ControlSystem:
    """The point mass in SI units with ``|a| <= 1 m/s^2`` on each axis and the given
    constraint fields (``constraints``, ``constraint_names``, ...; none by default)."""
    return ControlSystem(
        name=name,
        state_names=("p_x [m]", "p_y [m]", "v_x [m/s]", "v_y [m/s]"),
        input_names=("a_x [m/s^2]", "a_y [m/s^2]"),
        force_names=("w_x [m/s^2]", "w_y [m/s^2]"),
        rhs=point_mass_rhs,
        input_lower=(-1.0, -1.0),
        input_upper=(1.0, 1.0),
        **constraints,
    )
