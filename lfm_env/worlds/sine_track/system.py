"""The paper's case study: a kinematic bicycle on a sinusoidal track, as a :class:`ControlSystem`.

State ``[p_x, p_y, v, psi]`` in ``[m, m, m/s, rad]``; input ``[a, delta]`` in
``[m/s^2, rad]``; one latent force ``w`` [m/s^2] added to the acceleration (paper eq.
VehSys)::

    dp_x/dt = v cos(psi + alpha),  dp_y/dt = v sin(psi + alpha),
    dv/dt = a + w,                 dpsi/dt = v sin(alpha) / (l / 2),
    alpha = atan(tan(delta) / 2)   (slip angle; rear axle at l/2)

The track: centre line ``y = A sin(omega x + phase)`` (highway-env's ``SineLane`` laid
along the x axis), half width ``half_width``, bounds on ``p_x``, and speed bounds. Its
six constraints ``g(x) <= 0`` are, in order: track left (``y - c(x) - w_h``), track right
(``c(x) - y - w_h``), ``x_min - p_x``, ``p_x - x_max`` [m], ``v_min - v``, ``v - v_max``
[m/s]. This module is the only place that writes the bicycle and the track.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from lfm_env.system import ControlSystem
from lfm_env.xp import xp

STATE_NAMES = ("p_x [m]", "p_y [m]", "v [m/s]", "psi [rad]")
INPUT_NAMES = ("a [m/s^2]", "delta [rad]")
FORCE_NAMES = ("w [m/s^2]",)
CONSTRAINT_NAMES = (
    "track_left [m]",
    "track_right [m]",
    "x_min [m]",
    "x_max [m]",
    "speed_min [m/s]",
    "speed_max [m/s]",
)
#: Groups reported by the metrics: the excess over the band, the x bounds, the speed bounds.
CONSTRAINT_GROUPS = {"track": (0, 1), "x": (2, 3), "speed": (4, 5)}


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
        return self.amplitude * xp.sin(self.pulsation * x + self.phase)

    def lateral_offset(self, x: Any, y: Any) -> Any:
        """Signed vertical offset ``y - centre_y(x)`` [m] from the centre line."""
        return y - self.centre_y(x)

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


def slip_angle(delta: Any) -> Any:
    """Slip angle ``alpha = atan(0.5 tan(delta))`` [rad] for steering ``delta`` [rad]."""
    return xp.arctan(0.5 * xp.tan(delta))


def bicycle_rhs(x: Any, u: Any, w: Any, length: float = 0.5) -> Any:
    """``dx/dt`` of the kinematic bicycle with latent force ``w`` on the acceleration.

    Args:
        x: ``[p_x, p_y, v, psi]`` [m, m, m/s, rad], NumPy ``(..., 4)`` or a CasADi column.
        u: ``[a, delta]`` [m/s^2, rad], broadcast against ``x``.
        w: ``[w]`` [m/s^2], the latent force, ``(..., 1)`` or a CasADi scalar.
        length: vehicle length ``l`` [m].
    """
    _, _, v, psi = xp.unstack(x)
    a, delta = xp.unstack(u)
    (force,) = xp.unstack(w)
    alpha = slip_angle(delta)
    heading = psi + alpha
    return xp.stack(
        [v * xp.cos(heading), v * xp.sin(heading), a + force, v * (xp.sin(alpha) / (length / 2.0))]
    )


def track_constraints(
    x: Any, track: SineTrack, speed_min: float = 0.0, speed_max: float = 8.0
) -> Any:
    """The six constraints ``g(x) <= 0`` of :data:`CONSTRAINT_NAMES` (NumPy or CasADi)."""
    px, py, v, _ = xp.unstack(x)
    off = track.lateral_offset(px, py)
    return xp.stack(
        [
            off - track.half_width,
            -off - track.half_width,
            track.x_min - px,
            px - track.x_max,
            speed_min - v,
            v - speed_max,
        ]
    )


@dataclass(frozen=True)
class _BicycleRhs:
    """Picklable ``f(x, u, w)`` bound to a vehicle length."""

    length: float

    def __call__(self, x: Any, u: Any, w: Any) -> Any:
        return bicycle_rhs(x, u, w, self.length)


@dataclass(frozen=True)
class _TrackConstraints:
    """Picklable ``g(x)`` bound to a track and speed bounds."""

    track: SineTrack
    speed_min: float
    speed_max: float

    def __call__(self, x: Any) -> Any:
        return track_constraints(x, self.track, self.speed_min, self.speed_max)


@dataclass(frozen=True)
class _BrakeToStop:
    """Fallback law: decelerate towards standstill within one step, wheels straight.

    Full braking at a negative speed would drive the kinematic bicycle backwards (it has
    no stop at ``v = 0``), so the law brakes by ``v / dt`` at most ``accel_max``.
    """

    accel_max: float

    def __call__(self, x: Any, dt: float) -> np.ndarray:
        a = np.clip(-x[2] / dt, -self.accel_max, self.accel_max)
        return np.array([a, 0.0])


def sine_track_system(
    track: SineTrack | None = None,
    vehicle_length: float = 0.5,
    speed_min: float = 0.0,
    speed_max: float = 8.0,
    accel_max: float = 5.0,
    steer_max: float = math.radians(25.0),
) -> ControlSystem:
    """The bicycle on the sine track (paper values by default).

    Args:
        track: the track geometry; the paper's by default.
        vehicle_length: ``l`` [m].
        speed_min: lower speed bound [m/s] (a state constraint).
        speed_max: upper speed bound [m/s].
        accel_max: input bound ``|a| <= accel_max`` [m/s^2].
        steer_max: input bound ``|delta| <= steer_max`` [rad], below ``pi / 2``.
    """
    track = SineTrack() if track is None else track
    if not 0.0 < steer_max < math.pi / 2:
        raise ValueError(f"steer_max={steer_max!r}: must be in (0, pi/2) rad")
    if not vehicle_length > 0.0:
        raise ValueError(f"vehicle_length={vehicle_length!r}: must be > 0 m")
    return ControlSystem(
        name="sine_track",
        state_names=STATE_NAMES,
        input_names=INPUT_NAMES,
        force_names=FORCE_NAMES,
        rhs=_BicycleRhs(float(vehicle_length)),
        input_lower=(-accel_max, -steer_max),
        input_upper=(accel_max, steer_max),
        constraints=_TrackConstraints(track, float(speed_min), float(speed_max)),
        constraint_names=CONSTRAINT_NAMES,
        constraint_groups=CONSTRAINT_GROUPS,
        # A millimetre over the track edge is not a crash: count the steps beyond 1 and 5 cm
        # (and 5 cm/s over the speed bounds) apart from the raw counts.
        violation_tolerances={"track": (0.01, 0.05), "x": (0.01, 0.05), "speed": (0.05,)},
        mirror_inputs=(1,),  # a left turn and its mirrored right turn
        fallback_input=(-accel_max, 0.0),  # full braking, wheels straight
        fallback_law=_BrakeToStop(accel_max),  # ... but only down to standstill
    )


def track_of(system: ControlSystem) -> SineTrack:
    """The :class:`SineTrack` of a system made by :func:`sine_track_system`."""
    g = system.constraints
    if not isinstance(g, _TrackConstraints):
        raise ValueError(f"system {system.name!r} is not a sine-track system")
    return g.track


__all__ = [
    "CONSTRAINT_NAMES",
    "SineTrack",
    "bicycle_rhs",
    "sine_track_system",
    "slip_angle",
    "track_constraints",
    "track_of",
]
