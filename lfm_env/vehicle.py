"""Kinematic bicycle model (paper eq. VehSys), written once for NumPy and CasADi.

State ``[p_x, p_y, v, psi]`` in ``[m, m, m/s, rad]``; input ``[a, delta]`` in
``[m/s^2, rad]``. The functions below are pure: they take arrays whose *last*
axis is the state (or input), so a single state ``(4,)``, a batch of particles
``(n, 4)`` and a CasADi column vector (``SX``/``MX`` of shape ``(4, 1)``) all
work with the same code. This one right-hand side feeds the simulator, the
particle filter and the MPC.
"""

from __future__ import annotations

from typing import Any

import casadi as ca
import numpy as np

STATE_DIM = 4
ACTION_DIM = 2
STATE_NAMES = ("p_x", "p_y", "v", "psi")
STATE_UNITS = ("m", "m", "m/s", "rad")
ACTION_NAMES = ("a", "delta")
ACTION_UNITS = ("m/s^2", "rad")


def is_symbolic(x: Any) -> bool:
    """True for CasADi types (``SX``, ``MX``, ``DM``), False for NumPy data."""
    return isinstance(x, (ca.SX, ca.MX, ca.DM))


def slip_angle(delta: Any) -> Any:
    """Slip angle ``alpha = atan(0.5 tan(delta))`` [rad] for steering ``delta`` [rad]."""
    if is_symbolic(delta):
        return ca.atan(0.5 * ca.tan(delta))
    return np.arctan(0.5 * np.tan(delta))


def bicycle_rhs(
    state: Any, action: Any, disturbance: Any = 0.0, length: float = 0.5, axis: int = -1
) -> Any:
    """Continuous-time right-hand side ``dx/dt`` of the kinematic bicycle.

    Args:
        state: ``[p_x, p_y, v, psi]`` in ``[m, m, m/s, rad]``; shape ``(..., 4)``
            for NumPy or a ``(4, 1)`` CasADi vector.
        action: ``[a, delta]`` in ``[m/s^2, rad]``; shape ``(..., 2)`` (broadcast
            against ``state``) or a ``(2, 1)`` CasADi vector.
        disturbance: latent force ``w`` [m/s^2] added to the acceleration; a
            scalar, an array broadcastable to the state without its component axis, or a
            CasADi scalar.
        length: vehicle length ``l`` [m]; the rear axle sits at ``l/2``.
        axis: NumPy only: the axis of ``state``, ``action`` and the result that holds the
            components. ``0`` takes component-major data such as ``(4, n)`` particles,
            whose rows are contiguous and so several times faster to work on.

    Returns:
        ``[dp_x, dp_y, dv, dpsi]`` with the same layout as ``state``.
    """
    if is_symbolic(state) or is_symbolic(action) or is_symbolic(disturbance):
        v, psi = state[2], state[3]
        a, delta = action[0], action[1]
        alpha = slip_angle(delta)
        return ca.vertcat(
            v * ca.cos(psi + alpha),
            v * ca.sin(psi + alpha),
            a + disturbance,
            v / (length / 2.0) * ca.sin(alpha),
        )
    state = np.moveaxis(np.asarray(state, dtype=float), axis, 0)
    action = np.moveaxis(np.asarray(action, dtype=float), axis, 0)
    v, psi = state[2], state[3]
    a, delta = action[0], action[1]
    alpha = slip_angle(delta)
    heading = psi + alpha
    shape = np.broadcast_shapes(v.shape, heading.shape, np.shape(a), np.shape(disturbance))
    # Filled component by component: no stacking temporaries (this runs on 7000 particles
    # a step).
    out = np.empty((4,) + shape)
    np.multiply(v, np.cos(heading), out=out[0, ...])
    np.multiply(v, np.sin(heading), out=out[1, ...])
    np.add(a, disturbance, out=out[2, ...])
    np.multiply(v, np.sin(alpha) / (length / 2.0), out=out[3, ...])
    return np.moveaxis(out, 0, axis)


def euler_step(
    state: Any,
    action: Any,
    dt: float,
    disturbance: Any = 0.0,
    length: float = 0.5,
    axis: int = -1,
) -> Any:
    """One explicit Euler step ``x + dt * f(x, u, w)`` of the bicycle (no noise).

    Same conventions as :func:`bicycle_rhs` (``axis`` included); ``dt`` in [s]. This is the
    step the environment, the particle filter and the MPC predictions share.
    """
    return state + dt * bicycle_rhs(state, action, disturbance, length, axis)
