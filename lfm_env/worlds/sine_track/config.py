"""The sine-track world's ``env`` section: vehicle, track, noise, latent force, goal, limits."""

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
from lfm_env.worlds.sine_track.system import SineTrack, sine_track_system


@dataclass(frozen=True)
class SineTrackConfig(WorldConfig):
    """The SineTrack world: vehicle, track, noise, latent force, goal and episode limits.

    Vectors over the state ``[p_x, p_y, v, psi]`` give the heading in **degrees** for
    readability; the env converts to radians.
    """

    ANGLE_STATES = (3,)

    dt: float = 0.2  # [s] sampling time (one Euler step per sample)
    vehicle_length: float = 0.5  # [m] l of the bicycle
    track_amplitude: float = 3.0  # [m] of the centre line y = A sin(omega x)
    track_pulsation: float = 0.2  # [rad/m] omega of the centre line
    track_half_width: float = 1.0  # [m] allowed |p_y - centre_y(p_x)|
    x_min: float = -1.0  # [m] lower bound on p_x
    x_max: float = 70.0  # [m] upper bound on p_x
    speed_min: float = 0.0  # [m/s] speed constraint (recorded, not enforced)
    speed_max: float = 8.0  # [m/s]
    accel_max: float = 5.0  # [m/s^2] action bound |a|
    steer_max_deg: float = 25.0  # [deg] action bound |delta|
    initial_state: tuple[float, float, float, float] = (0.0, 0.0, 1.0, 45.0)  # [m, m, m/s, deg]
    goal: tuple[float, float] = (62.83, 0.0)  # [m] goal position
    goal_radius: float = 1.0  # [m] success when the path comes this close to the goal
    goal_state: tuple[float, float, float, float] = (62.83, 0.0, 4.0, 0.0)  # [m, m, m/s, deg]
    Q: tuple[float, float, float, float] = (2.0, 2.0, 1.0, 0.0)  # reward's state weights
    R: tuple[float, float] = (0.5, 10.0)  # reward's input weights on [a, delta (rad)]
    measurement_noise_std: tuple[float, float, float, float] = (
        0.15,
        0.15,
        0.15,
        0.5,
    )  # [m, m, m/s, deg]
    process_noise_diffusion: tuple[float, float, float, float] = (
        0.01,
        0.01,
        0.01,
        0.5,
    )  # per sqrt(s) [m, m, m/s, deg]
    max_steps: int = 150  # truncation after this many steps (30 s at dt = 0.2 s)
    safety_margin: float = 10.0  # [m] failure when the car is this far outside the track box
    latent_force: LatentForceConfig = field(default_factory=LatentForceConfig)

    def __post_init__(self) -> None:
        c = FieldChecker(self)
        c.positive("dt", "vehicle_length", "track_half_width", "accel_max", "goal_radius")
        c.positive("max_steps", "safety_margin")
        c("max_steps", self.max_steps <= MAX_STEPS, f"an integer in [1, {MAX_STEPS}]")
        c.non_negative("track_amplitude", "track_pulsation", "Q", "R")
        c.non_negative("measurement_noise_std", "process_noise_diffusion")
        c("x_max", self.x_max > self.x_min, f"> x_min={self.x_min}")
        c("speed_max", self.speed_max > self.speed_min, f"> speed_min={self.speed_min}")
        c("steer_max_deg", 0 < self.steer_max_deg < 90, "in (0, 90) deg")
        c("dt", self.dt <= 10.0, "<= 10 s")
        on_track = f"on the track (|y - centre_y(x)| <= {self.track_half_width} m)"
        check_goal_and_start(c, self, self.track.track_excess, on_track, "track")

    @property
    def track(self) -> SineTrack:
        """The track geometry as a :class:`~lfm_env.worlds.sine_track.system.SineTrack`."""
        return SineTrack(
            amplitude=self.track_amplitude,
            pulsation=self.track_pulsation,
            half_width=self.track_half_width,
            x_min=self.x_min,
            x_max=self.x_max,
        )

    @property
    def steer_max(self) -> float:
        """Steering bound [rad]."""
        return math.radians(self.steer_max_deg)

    def make_system(self):
        """The bicycle on this track (:func:`sine_track_system`)."""
        return sine_track_system(
            track=self.track,
            vehicle_length=self.vehicle_length,
            speed_min=self.speed_min,
            speed_max=self.speed_max,
            accel_max=self.accel_max,
            steer_max=self.steer_max,
        )


__all__ = ["SineTrackConfig"]
