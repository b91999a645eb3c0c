"""The quadrotor world's scene: the tunnel, the goal and the vehicle, drawn by matplotlib."""

from __future__ import annotations

import math

import numpy as np

from lfm_env.worlds.quadrotor.system import Corridor


class CorridorScene:
    """The tunnel (floor, ceiling), the goal and the quadrotor, drawn offscreen by matplotlib.

    The vehicle is a bar tilted by the pitch with a rotor at each end, drawn
    ``arm_length`` [m] from its centre (larger than a Crazyflie's 0.04 m arm, so it shows
    at the scale of the tunnel). Follows :class:`lfm_env.env.Scene`.

    Args:
        corridor: the tunnel geometry.
        screen_size: ``(width, height)`` [px] of the frame.
        scaling: pixels per metre with the view centred on the vehicle; ``None`` fits the
            whole tunnel.
        goal: goal position ``(2,)`` [m] drawn as a circle; ``None`` for none.
        goal_radius: its radius [m].
        arm_length: drawn half length [m] of the vehicle's bar.
    """

    DPI = 100

    def __init__(
        self,
        corridor: Corridor,
        screen_size: tuple[int, int] = (600, 300),
        scaling: float | None = None,
        goal: np.ndarray | None = None,
        goal_radius: float = 0.3,
        arm_length: float = 0.15,
    ) -> None:
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure
        from matplotlib.patches import Circle

        self.corridor = corridor
        self.size = (int(screen_size[0]), int(screen_size[1]))
        self.scaling = scaling
        self.arm_length = float(arm_length)
        width, height = self.size
        self.figure = Figure(figsize=(width / self.DPI, height / self.DPI), dpi=self.DPI)
        self.canvas = FigureCanvasAgg(self.figure)
        ax = self.figure.add_axes((0.0, 0.0, 1.0, 1.0))
        ax.set_axis_off()
        ax.set_facecolor("white")
        self.ax = ax
        c = corridor
        x = np.linspace(c.x_min, c.x_max, 400)
        floor, ceiling = c.floor_z(x), c.ceiling_z(x)
        ax.fill_between(x, ceiling, ceiling + 10.0, color=(0.55, 0.55, 0.6), lw=0)
        ax.fill_between(x, floor - 10.0, floor, color=(0.55, 0.55, 0.6), lw=0)
        ax.plot(x, floor, color=(0.15, 0.15, 0.2), lw=2)
        ax.plot(x, ceiling, color=(0.15, 0.15, 0.2), lw=2)
        ax.plot(x, c.centre_z(x), color=(0.7, 0.7, 0.75), lw=1, ls="--")
        if goal is not None:
            ax.add_patch(Circle(tuple(goal), goal_radius, fill=False, ec=(0.16, 0.67, 0.24), lw=2))
        (self._bar,) = ax.plot([], [], color=(0.1, 0.3, 0.8), lw=3, solid_capstyle="round")
        (self._rotors,) = ax.plot([], [], ls="", marker="o", ms=6, color=(0.85, 0.2, 0.1))
        self._state = np.zeros(6)
        if scaling is None:
            # The whole tunnel, centred, metres equal on both axes.
            z_mid = c.centre
            span_z = 2.0 * (c.amplitude + c.half_height) + 0.5
            span_x = c.x_max - c.x_min + 0.5
            per_m = min(width / span_x, height / span_z)
            self._set_view(0.5 * (c.x_min + c.x_max), z_mid, per_m)

    def _set_view(self, x_mid: float, z_mid: float, per_m: float) -> None:
        half_w = 0.5 * self.size[0] / per_m
        half_h = 0.5 * self.size[1] / per_m
        self.ax.set_xlim(x_mid - half_w, x_mid + half_w)
        self.ax.set_ylim(z_mid - half_h, z_mid + half_h)

    def update(self, state: np.ndarray) -> None:
        """Place the drawn vehicle at the true state ``[p_x, p_z, theta, ...]``."""
        self._state = np.asarray(state, dtype=float).copy()

    def draw(self) -> np.ndarray:
        """Draw; returns an ``(H, W, 3)`` uint8 RGB frame with +z up."""
        px, pz, theta = self._state[:3]
        # The thrust points along (sin theta, cos theta); the bar is perpendicular to it.
        dx, dz = self.arm_length * math.cos(theta), -self.arm_length * math.sin(theta)
        ends = np.array([[px - dx, pz - dz], [px + dx, pz + dz]])
        self._bar.set_data(ends[:, 0], ends[:, 1])
        self._rotors.set_data(ends[:, 0], ends[:, 1])
        if self.scaling is not None:
            self._set_view(px, pz, self.scaling)
        self.canvas.draw()
        rgba = np.asarray(self.canvas.buffer_rgba())
        frame = np.full((self.size[1], self.size[0], 3), 255, dtype=np.uint8)
        h, w = min(rgba.shape[0], self.size[1]), min(rgba.shape[1], self.size[0])
        frame[:h, :w] = rgba[:h, :w, :3]
        return frame

    def close(self) -> None:
        """Drop the figure (no window to close)."""
        self.figure.clear()


__all__ = ["CorridorScene"]
