"""The sinusoidal track of the case study, on NumPy and CasADi.

Centre line ``y = A sin(omega x + phase)`` (highway-env's ``SineLane`` laid along
the x axis), half width ``track_half_width`` [m], and simple bounds on ``x``.
Constraint functions return values that are ``<= 0`` when satisfied, in metres.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import casadi as ca
import numpy as np

from lfm_env.vehicle import is_symbolic


@dataclass(frozen=True)
class SineTrack:
    """Geometry of the sinusoidal track; all lengths in metres."""

    amplitude: float = 3.0  # [m] of the centre line
    pulsation: float = 0.2  # [rad/m] of the centre line
    phase: float = 0.0  # [rad]
    half_width: float = 1.0  # [m] allowed lateral distance |p_y - centre_y(p_x)|
    x_min: float = -1.0  # [m] lower bound on p_x
    x_max: float = 70.0  # [m] upper bound on p_x

    def centre_y(self, x: Any) -> Any:
        """Centre-line ordinate [m] at abscissa ``x`` [m] (NumPy or CasADi)."""
        sin = ca.sin if is_symbolic(x) else np.sin
        return self.amplitude * sin(self.pulsation * x + self.phase)

    def lateral_offset(self, x: Any, y: Any) -> Any:
        """Signed vertical offset ``y - centre_y(x)`` [m] from the centre line."""
        return y - self.centre_y(x)

    def constraints(self, state: Any) -> Any:
        """Track and x-bound constraints ``g(x) <= 0`` [m] of a state.

        Returns ``[off - w, -off - w, x_min - p_x, p_x - x_max]`` where ``off`` is the
        lateral offset and ``w`` the half width; the last axis for NumPy (``(..., 4)``),
        a ``(4, 1)`` vector for CasADi.
        """
        if is_symbolic(state):
            px, py = state[0], state[1]
            off = self.lateral_offset(px, py)
            return ca.vertcat(
                off - self.half_width, -off - self.half_width, self.x_min - px, px - self.x_max
            )
        state = np.asarray(state, dtype=float)
        px, py = state[..., 0], state[..., 1]
        off = self.lateral_offset(px, py)
        return np.stack(
            [off - self.half_width, -off - self.half_width, self.x_min - px, px - self.x_max],
            axis=-1,
        )

    def track_excess(self, x: Any, y: Any) -> Any:
        """How far [m] a position lies outside the track band (0 inside)."""
        return np.maximum(np.abs(self.lateral_offset(x, y)) - self.half_width, 0.0)

    def x_excess(self, x: Any) -> Any:
        """How far [m] ``x`` lies outside ``[x_min, x_max]`` (0 inside)."""
        return np.maximum(np.maximum(self.x_min - x, x - self.x_max), 0.0)

    def make_lane(self):
        """The same centre line as a highway-env ``SineLane`` (for rendering)."""
        from highway_env.road.lane import LineType, SineLane

        return SineLane(
            [self.x_min, 0.0],
            [self.x_max, 0.0],
            amplitude=self.amplitude,
            pulsation=self.pulsation,
            phase=self.phase + self.pulsation * self.x_min,
            width=2.0 * self.half_width,
            line_types=(LineType.CONTINUOUS, LineType.CONTINUOUS),
        )
