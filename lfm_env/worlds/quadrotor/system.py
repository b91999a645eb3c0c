"""The second case study: a planar quadrotor in a horizontal gust, through a bending tunnel.

State ``[p_x, p_z, theta, v_x, v_z, omega]`` in ``[m, m, rad, m/s, m/s, rad/s]`` (``theta``
the pitch, positive tilting the thrust towards +x); input ``[T, theta_cmd]`` in ``[N, rad]``
(collective thrust and pitch command); one latent force ``w`` [m/s^2], the gust, added to
the horizontal acceleration::

    dp_x/dt = v_x,                       dp_z/dt = v_z,
    dv_x/dt = T sin(theta) / m + w,      dv_z/dt = T cos(theta) / m - g,
    dtheta/dt = omega,                   domega/dt = wn^2 (theta_cmd - theta) - 2 zeta wn omega

**An attitude-controlled model.** The bare Crazyflie's pitch dynamics (safe-control-gym's
``quadrotor_2D``: mass ``m = 0.027 kg``, ``g = 9.81 m/s^2``, inertia ``I = 1.4e-5 kg m^2``,
arm ``L = 0.0397 m``) have a torque-to-inertia gain ``L / I = 2836 1/(kg m)``: their time
scales would need ``dt ~ 0.01 s`` and horizons of about 100 steps, too many for the
scenario MPC. The onboard attitude controller makes the pitch a
second-order response to a pitch command, as in safe-control-gym's attitude-control
quadrotor mode; we model that loop by its natural frequency ``wn`` [rad/s] and damping
``zeta``. Its explicit Euler step is stable when ``|1 + dt lambda| < 1`` for both
eigenvalues ``lambda`` of ``[[0, 1], [-wn^2, -2 zeta wn]]``, i.e. ``wn < 2 zeta / dt`` for
``zeta <= 1`` (:func:`attitude_frequency_bound`); at the defaults ``wn = 10 rad/s``,
``zeta = 0.8``, ``dt = 0.1 s``, ``lambda = -8 +- 6i`` and ``|1 + dt lambda| = 0.63``.
The mass and ``g`` are safe-control-gym's (``quadrotor_2D``); the thrust bound
``T_max = 2 m g`` is the Crazyflie's order of magnitude (thrust-to-weight about 2).

**The gust** is a Gaussian process in time (Matern 3/2 by default: a gust spectrum is a
low-order filtered noise), estimated and predicted by the scenario MPC of "Model
Predictive Control of Nonlinear Latent Force Models: A Scenario-Based Approach" (ICRA
2021; this project's paper). The defaults of :class:`lfm_env.config.QuadrotorLatentForceConfig` (std
2.0 m/s^2, lengthscale 2.5 s) make it matter against the available thrust: at the pitch
bound ``theta_max = 0.4 rad`` a hovering vehicle can push ``g tan(0.4) = 4.1 m/s^2``
sideways, so a one-sigma gust takes half the horizontal authority and the gust exceeds it
4% of the time, for about a second at a time.

**The task**: a tunnel along x whose centre line ``z_c(x) = z_0 + A sin(2 pi x / lambda +
phase)`` bends; floor ``z_c - h`` and ceiling ``z_c + h``. Where the tunnel slopes, the
gust's horizontal push turns into an altitude error with respect to the tunnel. The four
constraints ``g(x) <= 0`` [m] are, in order: corridor floor (``z_c(p_x) - h - p_z``),
corridor ceiling (``p_z - z_c(p_x) - h``), ``x_min - p_x`` and ``p_x - x_max``. This
module is the only place that writes the quadrotor and the tunnel.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from lfm_env.system import ControlSystem
from lfm_env.xp import xp

STATE_NAMES = (
    "p_x [m]",
    "p_z [m]",
    "theta [rad]",
    "v_x [m/s]",
    "v_z [m/s]",
    "omega [rad/s]",
)
INPUT_NAMES = ("T [N]", "theta_cmd [rad]")
FORCE_NAMES = ("w [m/s^2]",)
CONSTRAINT_NAMES = ("corridor_floor [m]", "corridor_ceiling [m]", "x_min [m]", "x_max [m]")
#: Groups reported by the metrics: the excess over the tunnel (either side), the x bounds.
CONSTRAINT_GROUPS = {"corridor": (0, 1), "x": (2, 3)}

MASS = 0.027  # [kg] Crazyflie (safe-control-gym quadrotor_2D)
GRAVITY = 9.81  # [m/s^2] safe-control-gym quadrotor_2D


@dataclass(frozen=True)
class Corridor:
    """Geometry of the bending tunnel; all lengths in metres."""

    centre: float = 1.0  # [m] altitude z_0 about which the centre line bends
    amplitude: float = 0.5  # [m] A of the centre line
    wavelength: float = 4.0  # [m] lambda of the centre line
    phase: float = 0.0  # [rad]
    half_height: float = 0.35  # [m] h: allowed |p_z - centre_z(p_x)|
    x_min: float = -0.5  # [m] lower bound on p_x
    x_max: float = 9.0  # [m] upper bound on p_x

    def centre_z(self, x: Any) -> Any:
        """Centre-line altitude [m] at abscissa ``x`` [m] (NumPy or CasADi)."""
        return self.centre + self.amplitude * xp.sin(
            2.0 * math.pi * x / self.wavelength + self.phase
        )

    def floor_z(self, x: Any) -> Any:
        """Floor altitude [m] at ``x`` [m]."""
        return self.centre_z(x) - self.half_height

    def ceiling_z(self, x: Any) -> Any:
        """Ceiling altitude [m] at ``x`` [m]."""
        return self.centre_z(x) + self.half_height

    def vertical_offset(self, x: Any, z: Any) -> Any:
        """Signed offset ``z - centre_z(x)`` [m] from the centre line."""
        return z - self.centre_z(x)

    def corridor_excess(self, x: Any, z: Any) -> Any:
        """How far [m] a position lies above the ceiling or below the floor (0 inside)."""
        return np.maximum(np.abs(self.vertical_offset(x, z)) - self.half_height, 0.0)

    def x_excess(self, x: Any) -> Any:
        """How far [m] ``x`` lies outside ``[x_min, x_max]`` (0 inside)."""
        return np.maximum(np.maximum(self.x_min - x, x - self.x_max), 0.0)


def attitude_euler_radius(frequency: float, damping: float, dt: float) -> float:
    """Spectral radius of the explicit Euler step of the attitude loop (stable below 1).

    Args:
        frequency: natural frequency ``wn`` [rad/s].
        damping: damping ratio ``zeta``.
        dt: step [s].
    """
    a = np.array([[0.0, 1.0], [-(frequency**2), -2.0 * damping * frequency]])
    return float(np.max(np.abs(np.linalg.eigvals(np.eye(2) + dt * a))))


def attitude_frequency_bound(damping: float, dt: float) -> float:
    """The largest natural frequency [rad/s] whose attitude loop's Euler step is stable.

    ``2 zeta / dt`` for ``zeta <= 1`` (complex eigenvalues), ``2 / (dt (zeta +
    sqrt(zeta^2 - 1)))`` for ``zeta > 1``; frequencies strictly below it are stable.
    """
    if damping <= 1.0:
        return 2.0 * damping / dt
    return 2.0 / (dt * (damping + math.sqrt(damping * damping - 1.0)))


def quadrotor_rhs(
    x: Any,
    u: Any,
    w: Any,
    mass: float = MASS,
    gravity: float = GRAVITY,
    frequency: float = 10.0,
    damping: float = 0.8,
) -> Any:
    """``dx/dt`` of the attitude-controlled planar quadrotor with a horizontal gust ``w``.

    Args:
        x: ``[p_x, p_z, theta, v_x, v_z, omega]`` [m, m, rad, m/s, m/s, rad/s], NumPy
            ``(..., 6)`` or a CasADi column.
        u: ``[T, theta_cmd]`` [N, rad], broadcast against ``x``.
        w: ``[w]`` [m/s^2], the gust on the horizontal acceleration.
        mass: ``m`` [kg].
        gravity: ``g`` [m/s^2].
        frequency: ``wn`` [rad/s] of the attitude loop.
        damping: ``zeta`` of the attitude loop.
    """
    _, _, theta, vx, vz, omega = xp.unstack(x)
    thrust, theta_cmd = xp.unstack(u)
    (gust,) = xp.unstack(w)
    accel = thrust / mass
    return xp.stack(
        [
            vx,
            vz,
            omega,
            accel * xp.sin(theta) + gust,
            accel * xp.cos(theta) - gravity,
            frequency * frequency * (theta_cmd - theta) - 2.0 * damping * frequency * omega,
        ]
    )


def corridor_constraints(x: Any, corridor: Corridor) -> Any:
    """The four constraints ``g(x) <= 0`` [m] of :data:`CONSTRAINT_NAMES` (NumPy or CasADi)."""
    px, pz = xp.unstack(x)[:2]
    off = corridor.vertical_offset(px, pz)
    return xp.stack(
        [
            -off - corridor.half_height,
            off - corridor.half_height,
            corridor.x_min - px,
            px - corridor.x_max,
        ]
    )


@dataclass(frozen=True)
class _QuadrotorRhs:
    """Picklable ``f(x, u, w)`` bound to the vehicle's parameters."""

    mass: float
    gravity: float
    frequency: float
    damping: float

    def __call__(self, x: Any, u: Any, w: Any) -> Any:
        return quadrotor_rhs(x, u, w, self.mass, self.gravity, self.frequency, self.damping)


@dataclass(frozen=True)
class _CorridorConstraints:
    """Picklable ``g(x)`` bound to a corridor."""

    corridor: Corridor

    def __call__(self, x: Any) -> Any:
        return corridor_constraints(x, self.corridor)


def _check_positive(**values: float) -> None:
    for name, value in values.items():
        if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0.0):
            raise ValueError(f"{name}={value!r}: must be finite and > 0")


def quadrotor_gust_system(
    corridor: Corridor | None = None,
    mass: float = MASS,
    gravity: float = GRAVITY,
    thrust_max: float | None = None,
    pitch_max: float = 0.4,
    attitude_frequency: float = 10.0,
    attitude_damping: float = 0.8,
) -> ControlSystem:
    """The attitude-controlled planar quadrotor in the tunnel (Crazyflie values by default).

    Args:
        corridor: the tunnel geometry; :class:`Corridor`'s defaults when ``None``.
        mass: ``m`` [kg].
        gravity: ``g`` [m/s^2].
        thrust_max: input bound ``0 <= T <= thrust_max`` [N], above the hover thrust
            ``m g``; ``2 m g`` when ``None``.
        pitch_max: input bound ``|theta_cmd| <= pitch_max`` [rad], in ``(0, pi/2)``.
        attitude_frequency: ``wn`` [rad/s] of the attitude loop.
        attitude_damping: ``zeta`` of the attitude loop (> 0).

    The fallback input, applied when a solve fails with no plan left, is the hover
    thrust ``m g`` with the pitch command 0. The Euler stability of the attitude loop
    depends on the step, so it is checked where ``dt`` is known
    (:class:`lfm_env.worlds.quadrotor.config.QuadrotorGustConfig`, with
    :func:`attitude_frequency_bound`).
    """
    corridor = Corridor() if corridor is None else corridor
    _check_positive(
        mass=mass,
        gravity=gravity,
        attitude_frequency=attitude_frequency,
        attitude_damping=attitude_damping,
    )
    hover = mass * gravity
    thrust_max = 2.0 * hover if thrust_max is None else thrust_max
    _check_positive(thrust_max=thrust_max)
    if not thrust_max > hover:
        raise ValueError(f"thrust_max={thrust_max!r}: must be > m g = {hover:.6g} N (to hover)")
    if not 0.0 < pitch_max < math.pi / 2:
        raise ValueError(f"pitch_max={pitch_max!r}: must be in (0, pi/2) rad")
    if not corridor.half_height > 0.0:
        raise ValueError(f"corridor.half_height={corridor.half_height!r}: must be > 0 m")
    if not corridor.wavelength > 0.0:
        raise ValueError(f"corridor.wavelength={corridor.wavelength!r}: must be > 0 m")
    if not corridor.x_max > corridor.x_min:
        raise ValueError(f"corridor.x_max={corridor.x_max!r}: must be > x_min={corridor.x_min}")
    return ControlSystem(
        name="quadrotor_gust",
        state_names=STATE_NAMES,
        input_names=INPUT_NAMES,
        force_names=FORCE_NAMES,
        rhs=_QuadrotorRhs(
            float(mass), float(gravity), float(attitude_frequency), float(attitude_damping)
        ),
        input_lower=(0.0, -pitch_max),
        input_upper=(thrust_max, pitch_max),
        constraints=_CorridorConstraints(corridor),
        constraint_names=CONSTRAINT_NAMES,
        constraint_groups=CONSTRAINT_GROUPS,
        # The metrics also count the steps beyond 1 cm and 5 cm outside the tunnel or the
        # x bounds: a plan riding a bound exceeds it by millimetres of process noise.
        violation_tolerances={"corridor": (0.01, 0.05), "x": (0.01, 0.05)},
        fallback_input=(hover, 0.0),  # hover, level
    )


def corridor_of(system: ControlSystem) -> Corridor:
    """The :class:`Corridor` of a system made by :func:`quadrotor_gust_system`."""
    g = system.constraints
    if not isinstance(g, _CorridorConstraints):
        raise ValueError(f"system {system.name!r} is not a quadrotor-gust system")
    return g.corridor


def hover_thrust(system: ControlSystem) -> float:
    """The hover thrust ``m g`` [N] of a system made by :func:`quadrotor_gust_system`."""
    f = system.rhs
    if not isinstance(f, _QuadrotorRhs):
        raise ValueError(f"system {system.name!r} is not a quadrotor-gust system")
    return f.mass * f.gravity


__all__ = [
    "CONSTRAINT_NAMES",
    "Corridor",
    "attitude_euler_radius",
    "attitude_frequency_bound",
    "corridor_constraints",
    "corridor_of",
    "hover_thrust",
    "quadrotor_gust_system",
    "quadrotor_rhs",
]
