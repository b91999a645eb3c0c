"""The second case study as a Gymnasium env: a planar quadrotor in a gust, through a tunnel."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from lfm_env.config import QuadrotorGustConfig
from lfm_env.worlds.goal import GoalReachingEnv
from lfm_env.worlds.quadrotor.system import Corridor


class QuadrotorGustEnv(GoalReachingEnv):
    """A planar quadrotor flying through a bending tunnel, pushed by a hidden gust.

    ## Description
    The second case study of the latent-force scenario MPC (the first is
    :class:`~lfm_env.worlds.sine_track.env.SineTrackEnv`), built from the generic layer alone. An
    attitude-controlled planar quadrotor with the Crazyflie's mass
    (:func:`lfm_env.worlds.quadrotor.system.quadrotor_gust_system`) flies from ``[0, 1] m``
    through a tunnel whose centre line ``z_c(x) = 1 + 0.5 sin(2 pi x / 4 m)`` bends,
    with floor ``z_c - 0.35 m`` and ceiling ``z_c + 0.35 m``, to the goal ``[8, 1] m``.
    An unmeasured gust ``w(t)``, a Gaussian process with a Matern 3/2 covariance
    (std 2.5 m/s^2, lengthscale 2.5 s), acts on the horizontal acceleration:
    ``dv_x/dt = T sin(theta) / m + w``. Where the tunnel slopes, a horizontal push turns
    into an altitude error with respect to the tunnel. The GP is simulated exactly through
    its state-space form.

    ## Action Space
    ``Box([0, -theta_max], [T_max, theta_max], (2,), float32)``: collective thrust ``T``
    [N] and pitch command ``theta_cmd`` [rad]; by default ``T_max = 2 m g = 0.53 N`` and
    ``theta_max = 0.4 rad``; hovering takes ``T = m g = 0.265 N``. Actions are read in
    float64; out-of-range actions are clipped to the system's bounds (the applied action
    is in ``info["applied_action"]``); non-finite actions, a wrong shape or a dtype that is
    not real numbers raise ``ValueError``.

    ## Observation Space
    The physical state plus Gaussian measurement noise; the gust is hidden.

    | Num | Observation | Unit | Noise std (default) |
    |-----|-------------|------|---------------------|
    | 0   | ``p_x`` horizontal position | m | 0.02 |
    | 1   | ``p_z`` altitude | m | 0.02 |
    | 2   | ``theta`` pitch (positive tilts the thrust to +x) | rad | 1 deg |
    | 3   | ``v_x`` horizontal velocity | m/s | 0.05 |
    | 4   | ``v_z`` vertical velocity | m/s | 0.05 |
    | 5   | ``omega`` pitch rate | rad/s | 5 deg/s |

    ``Box(-inf, inf, (6,), float64)``.

    ## Rewards
    Minus the stage cost on the true state before the step and the applied action:
    ``-[(x - x_g)^T Q (x - x_g) + u^T R u]`` with ``Q = diag(0.1, 2, 0.5, 2, 1, 0)``,
    ``R = diag(1, 1)`` and ``x_g = [8, 1, 0, 1 m/s, 0, 0]``, the tunnel's end at a cruise
    speed of 1 m/s (:meth:`~lfm_env.config.WorldConfig.make_cost`).

    ## Starting State
    True state ``[0, 1, 0, 0, 0, 0]`` (hovering at the tunnel's entrance); the latent
    state is drawn from the GP's stationary distribution (or zero, ``disturbance.start:
    zero``). The first observation is the noisy start state.

    ## Episode End
    * ``terminated`` with ``info["is_success"] = True`` when the segment flown in the step
      passes within ``goal_radius`` (0.3 m) of the goal.
    * ``terminated`` with failure when the vehicle leaves the safety box: farther than
      ``safety_margin`` (1 m) above the ceiling, below the floor or outside the x bounds,
      or a state that is not finite.
    * ``truncated`` by ``gym.make``'s time limit after ``max_steps`` (120 steps, 12 s), or
      ``max_episode_steps`` when given; the env itself never truncates.
    Constraint violations (tunnel, x bounds) are recorded in ``info``, not enforced.

    ## Info
    ``true_state`` (6,), ``disturbance`` (``w`` [m/s^2] acting during the step just taken;
    at reset, the one that will act next), ``latent_state`` (z), ``corridor_excess`` [m]
    and ``x_excess`` [m] (each 0 inside the bounds; the system's constraint groups),
    ``constraint_excess`` (4,) in the order corridor_floor, corridor_ceiling, x_min,
    x_max [m], ``cost`` (the number of violated constraint groups, 0 to 2),
    ``is_success``, ``failure``, ``applied_action``, ``time`` [s].

    ## Arguments
    ``gym.make("lfm_env/QuadrotorGust-v0", config=None, render_mode=None,
    screen_size=(600, 300), scaling=None)``: ``config`` is a YAML path, a dict (whole file
    or its ``env`` section) or a :class:`~lfm_env.config.QuadrotorGustConfig`;
    ``scaling`` is pixels per metre with the view centred on the vehicle, or ``None`` to
    show the whole tunnel. ``reset(options=...)`` accepts ``initial_state`` (``[m, m,
    rad, m/s, m/s, rad/s]``) and ``latent_state`` overrides. The env exposes ``config``,
    ``system``, ``model`` (the truth), ``cost`` and ``corridor``.

    ## Version History
    * v0: initial version; then Gymnasium's conventions: a float32 action space, an
      unbounded observation space, ``info["cost"]`` and the time limit as a ``TimeLimit``
      wrapper (same episodes).
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 10}

    CONFIG = QuadrotorGustConfig
    SAFETY_GROUPS = ("corridor", "x")

    def __init__(
        self,
        config: Any = None,
        render_mode: str | None = None,
        screen_size: tuple[int, int] = (600, 300),
        scaling: float | None = None,
    ) -> None:
        self.screen_size = (int(screen_size[0]), int(screen_size[1]))
        if min(self.screen_size) < 1:
            raise ValueError(f"screen_size={screen_size!r}: must be two integers >= 1 [px]")
        if scaling is not None and not (math.isfinite(scaling) and scaling > 0.0):
            raise ValueError(f"scaling={scaling!r}: must be None or > 0 px/m")
        self.scaling = None if scaling is None else float(scaling)
        super().__init__(config, render_mode)
        self.corridor = self.config.corridor

    def _make_scene(self) -> CorridorScene:
        """The tunnel, the goal and the vehicle drawn by matplotlib (:class:`CorridorScene`)."""
        return CorridorScene(
            self.corridor,
            screen_size=self.screen_size,
            scaling=self.scaling,
            goal=self._goal,
            goal_radius=self.config.goal_radius,
        )


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


__all__ = ["CorridorScene", "QuadrotorGustEnv"]
