"""The quadrotor world's ``env`` section: vehicle, attitude loop, tunnel, noise, gust, goal,
limits."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from lfm_env.config.loading import FieldChecker
from lfm_env.config.world import (
    MAX_STEPS,
    LatentForceConfig,
    WorldConfig,
    check_goal_and_start,
)
from lfm_env.worlds.quadrotor.system import (
    Corridor,
    attitude_euler_radius,
    attitude_frequency_bound,
    quadrotor_gust_system,
)


@dataclass(frozen=True)
class QuadrotorLatentForceConfig(LatentForceConfig):
    """The quadrotor's gust: a :class:`LatentForceConfig` whose defaults are the gust's.

    Matern 3/2 (a gust spectrum is a low-order filtered noise), std 2.0 m/s^2 on the
    horizontal acceleration: about half the horizontal authority of a hovering vehicle
    tilted to the 0.4 rad bound (``g tan(0.4) = 4.1 m/s^2`` with the altitude held), so
    the gust exceeds that authority 4% of the time, for about a second at a time. More
    push needs more thrust, which climbs out of the tunnel within a fraction of a second:
    a gust held beyond the authority blows the vehicle back whatever it does. At std
    2.5 m/s^2 (``QuadrotorGust-v0``) it did so to the oracle, which knows the gust, on 5
    of seeds 0..199; at 2.0 the oracle survives all 200 (closest approach to the safety
    box's back edge 1.0 m). Lengthscale 2.5 s: predictable over the MPC's 1 s horizon once
    estimated (at 1 s the open-loop spread of the position, times the tunnel's slope,
    exceeded the tunnel's height and every scenario plan hovered at a crest). A partial
    ``latent_force:`` section keeps these defaults for the keys it omits.
    """

    nu: float = 1.5  # Matern smoothness
    variance: float = 4.0  # sigma^2 [(m/s^2)^2], std 2.0 m/s^2
    lengthscale: float = 2.5  # [s]


@dataclass(frozen=True)
class QuadrotorGustConfig(WorldConfig):
    """The QuadrotorGust world: vehicle, attitude loop, tunnel, noise, gust, goal, limits.

    Vectors over the state ``[p_x, p_z, theta, v_x, v_z, omega]`` give the pitch in
    **degrees** and the pitch rate in **deg/s** for readability; the env converts to
    radians. The input bounds and ``R`` are in the inputs' units ``[N, rad]``.
    """

    ANGLE_STATES = (2, 5)

    dt: float = 0.1  # [s] sampling time (one Euler step per sample)
    mass: float = 0.027  # [kg] Crazyflie (safe-control-gym quadrotor_2D)
    gravity: float = 9.81  # [m/s^2]
    thrust_max: float = 0.52974  # [N] action bound 0 <= T <= thrust_max (2 m g)
    pitch_max: float = 0.4  # [rad] action bound |theta_cmd| <= pitch_max (about 23 deg)
    attitude_frequency: float = 10.0  # [rad/s] natural frequency wn of the attitude loop
    attitude_damping: float = 0.8  # damping ratio zeta of the attitude loop
    corridor_centre: float = 1.0  # [m] altitude z_0 about which the tunnel bends
    corridor_amplitude: float = 0.5  # [m] of the centre line z_0 + A sin(2 pi x / lambda)
    corridor_wavelength: float = 4.0  # [m] lambda of the centre line
    corridor_half_height: float = 0.35  # [m] allowed |p_z - centre_z(p_x)|
    x_min: float = -0.5  # [m] lower bound on p_x
    x_max: float = 9.0  # [m] upper bound on p_x
    initial_state: tuple[float, float, float, float, float, float] = (
        0.0,
        1.0,
        0.0,
        0.0,
        0.0,
        0.0,
    )  # [m, m, deg, m/s, m/s, deg/s]
    goal: tuple[float, float] = (8.0, 1.0)  # [m] goal position (p_x, p_z)
    goal_radius: float = 0.3  # [m] success when the path comes this close to the goal
    goal_state: tuple[float, float, float, float, float, float] = (
        8.0,
        1.0,
        0.0,
        1.0,
        0.0,
        0.0,
    )  # [m, m, deg, m/s, m/s, deg/s] the reward's goal: the tunnel's end at cruise speed
    Q: tuple[float, float, float, float, float, float] = (
        0.1,
        2.0,
        0.5,
        2.0,
        1.0,
        0.0,
    )  # reward's state weights (on SI units: theta in rad); small on p_x: cruise, not dash
    R: tuple[float, float] = (1.0, 1.0)  # reward's input weights on [T (N), theta_cmd (rad)]
    measurement_noise_std: tuple[float, float, float, float, float, float] = (
        0.02,
        0.02,
        1.0,
        0.05,
        0.05,
        5.0,
    )  # [m, m, deg, m/s, m/s, deg/s]
    process_noise_diffusion: tuple[float, float, float, float, float, float] = (
        0.005,
        0.005,
        0.5,
        0.02,
        0.02,
        2.0,
    )  # per sqrt(s) [m, m, deg, m/s, m/s, deg/s]
    max_steps: int = 120  # truncation after this many steps (12 s at dt = 0.1 s)
    safety_margin: float = 1.0  # [m] failure when this far outside the tunnel or x bounds
    latent_force: QuadrotorLatentForceConfig = field(default_factory=QuadrotorLatentForceConfig)

    def __post_init__(self) -> None:
        c = FieldChecker(self)
        c.positive("dt", "mass", "gravity", "thrust_max", "pitch_max", "attitude_frequency")
        c.positive("attitude_damping", "corridor_wavelength", "corridor_half_height")
        c.positive("goal_radius", "max_steps", "safety_margin")
        c("max_steps", self.max_steps <= MAX_STEPS, f"an integer in [1, {MAX_STEPS}]")
        c.non_negative("corridor_amplitude", "Q", "R")
        c.non_negative("measurement_noise_std", "process_noise_diffusion")
        c("dt", self.dt <= 10.0, "<= 10 s")
        hover = self.mass * self.gravity
        c("thrust_max", self.thrust_max > hover, f"> m g = {hover:.6g} N (to hover)")
        c("pitch_max", self.pitch_max < math.pi / 2, "in (0, pi/2) rad")
        bound = attitude_frequency_bound(self.attitude_damping, self.dt)
        radius = attitude_euler_radius(self.attitude_frequency, self.attitude_damping, self.dt)
        c(
            "attitude_frequency",
            self.attitude_frequency < bound and radius < 1.0,
            f"< {bound:.6g} rad/s with attitude_damping={self.attitude_damping} and "
            f"dt={self.dt} s (2 zeta / dt for zeta <= 1): the explicit Euler step of the "
            f"attitude loop diverges otherwise (|1 + dt lambda| = {radius:.4g} >= 1)",
        )
        c("x_max", self.x_max > self.x_min, f"> x_min={self.x_min}")
        inside = f"inside the tunnel (|p_z - centre_z(p_x)| <= {self.corridor_half_height} m)"
        check_goal_and_start(c, self, self.corridor.corridor_excess, inside, "tunnel")

    @property
    def corridor(self):
        """The tunnel geometry as a :class:`~lfm_env.worlds.quadrotor.system.Corridor`."""
        return Corridor(
            centre=self.corridor_centre,
            amplitude=self.corridor_amplitude,
            wavelength=self.corridor_wavelength,
            half_height=self.corridor_half_height,
            x_min=self.x_min,
            x_max=self.x_max,
        )

    @property
    def hover_thrust(self) -> float:
        """The thrust ``m g`` [N] that holds the vehicle level in still air."""
        return self.mass * self.gravity

    def make_system(self):
        """The quadrotor in this tunnel (:mod:`lfm_env.worlds.quadrotor.system`)."""
        return quadrotor_gust_system(
            corridor=self.corridor,
            mass=self.mass,
            gravity=self.gravity,
            thrust_max=self.thrust_max,
            pitch_max=self.pitch_max,
            attitude_frequency=self.attitude_frequency,
            attitude_damping=self.attitude_damping,
        )


__all__ = ["QuadrotorGustConfig", "QuadrotorLatentForceConfig"]
