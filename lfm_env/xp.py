"""The array namespace :data:`xp`: one spelling of the math a system is written with, for
NumPy data and CasADi expressions alike.

A system's right-hand side and constraints (:class:`lfm_env.system.ControlSystem`) are written
once with ``xp`` and run on NumPy batches (the env, the estimators' particles) and on CasADi
symbols (every solver)::

    from lfm_env.xp import xp

    def rhs(x, u, w):
        p, v = xp.unstack(x)          # components of the state
        (a,) = xp.unstack(u)
        (force,) = xp.unstack(w)
        return xp.stack([v, a + force])

* NumPy: ``x`` has shape ``(..., nx)``, ``u`` ``(..., nu)``, ``w`` ``(..., nw)``, broadcast
  against each other; the result has shape ``(..., nx)``.
* CasADi: ``x``, ``u`` and ``w`` are column vectors (``SX``/``MX``); the result is an
  ``(nx, 1)`` column.

What it offers: ``unstack`` and ``stack`` (components out of and back into a state); the
element-wise ``sin``, ``cos``, ``tan``, ``arcsin``, ``arccos``, ``arctan``, ``arctan2``,
``tanh``, ``sqrt``, ``exp``, ``log``, ``abs``; and the piecewise ``minimum``, ``maximum``,
``where`` and ``clip``. Arithmetic (``+ - * / **``) and comparisons work on both kinds
as they are. The solvers differentiate the CasADi form, so prefer smooth expressions: the
piecewise functions have kinks (``where`` evaluates both branches symbolically).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import casadi as ca
import numpy as np

_FLOAT_DTYPES = (np.dtype(np.float64), np.dtype(np.float32))


def is_symbolic(value: Any) -> bool:
    """True for CasADi types (``SX``, ``MX``, ``DM``), False for NumPy data."""
    return isinstance(value, (ca.SX, ca.MX, ca.DM))


def _any_symbolic(values: Sequence[Any]) -> bool:
    return any(is_symbolic(v) for v in values)


_CASADI_TYPES = (ca.SX, ca.MX, ca.DM)


def _unary(np_fun: Callable, ca_fun: Callable) -> Callable:
    def fun(a: Any) -> Any:
        return ca_fun(a) if isinstance(a, _CASADI_TYPES) else np_fun(a)

    fun.__name__ = np_fun.__name__
    fun.__doc__ = f"``{np_fun.__name__}`` of NumPy data or a CasADi expression."
    return fun


class _ArrayNamespace:
    """Element-wise math and component access that work on NumPy arrays and CasADi vectors.

    NumPy data carries its components on the *last* axis; CasADi data is a column vector.
    """

    sin = staticmethod(_unary(np.sin, ca.sin))
    cos = staticmethod(_unary(np.cos, ca.cos))
    tan = staticmethod(_unary(np.tan, ca.tan))
    arctan = staticmethod(_unary(np.arctan, ca.atan))
    arcsin = staticmethod(_unary(np.arcsin, ca.asin))
    arccos = staticmethod(_unary(np.arccos, ca.acos))
    tanh = staticmethod(_unary(np.tanh, ca.tanh))
    sqrt = staticmethod(_unary(np.sqrt, ca.sqrt))
    exp = staticmethod(_unary(np.exp, ca.exp))
    log = staticmethod(_unary(np.log, ca.log))
    abs = staticmethod(_unary(np.abs, ca.fabs))

    @staticmethod
    def arctan2(y: Any, x: Any) -> Any:
        """``arctan2(y, x)`` [rad]."""
        return ca.atan2(y, x) if _any_symbolic((y, x)) else np.arctan2(y, x)

    @staticmethod
    def minimum(a: Any, b: Any) -> Any:
        """The smaller of ``a`` and ``b``, element-wise (``fmin`` for CasADi). Not smooth
        where ``a == b``: a gradient-based solver may stall there."""
        return ca.fmin(a, b) if _any_symbolic((a, b)) else np.minimum(a, b)

    @staticmethod
    def maximum(a: Any, b: Any) -> Any:
        """The larger of ``a`` and ``b``, element-wise (``fmax`` for CasADi); e.g. a drag
        that acts only forwards, ``xp.maximum(v, 0.0)``. Not smooth where ``a == b``."""
        return ca.fmax(a, b) if _any_symbolic((a, b)) else np.maximum(a, b)

    @staticmethod
    def where(condition: Any, a: Any, b: Any) -> Any:
        """``a`` where ``condition`` holds, else ``b`` (``if_else`` for CasADi: both branches
        are evaluated, so each must be finite everywhere). The condition is a comparison
        of the same values, e.g. ``xp.where(v > 0.0, drag, 0.0)``; the result jumps where it
        switches, which solvers see as a kink."""
        if _any_symbolic((condition, a, b)):
            return ca.if_else(condition, a, b)
        return np.where(condition, a, b)

    @staticmethod
    def clip(a: Any, low: Any, high: Any) -> Any:
        """``a`` limited to ``[low, high]``, element-wise (``fmin(fmax(a, low), high)`` for
        CasADi), e.g. a saturated actuator. Flat outside the bounds: no gradient there."""
        if _any_symbolic((a, low, high)):
            return ca.fmin(ca.fmax(a, low), high)
        return np.clip(a, low, high)

    @staticmethod
    def unstack(x: Any) -> list[Any]:
        """The components of ``x``: ``x[..., i]`` (NumPy) or ``x[i]`` (CasADi).

        NumPy data stays in double or single precision (the particle transition evaluates
        the drift in single precision, :meth:`lfm_env.model.LatentForceModel.transition`);
        anything else becomes double.
        """
        if isinstance(x, _CASADI_TYPES):
            return [x[i] for i in range(x.shape[0])]
        if not isinstance(x, np.ndarray) or x.dtype not in _FLOAT_DTYPES:
            x = np.asarray(x, dtype=float)
        if x.ndim == 1:
            return list(x)
        # Components-first view: x.T[i] is x[..., i] without an ellipsis index per part.
        return list(np.moveaxis(x, -1, 0)) if x.ndim > 2 else list(x.T)

    @staticmethod
    def stack(parts: Sequence[Any]) -> Any:
        """Components back into one value: a CasADi column, or NumPy ``(..., len(parts))``.

        The NumPy result is a view of a component-major buffer (components first), so
        callers that work on component-major data (``(n, particles)``) read it back
        contiguously with ``.T``.
        """
        if _any_symbolic(parts):
            return ca.vertcat(*parts)
        shapes = {np.shape(p) for p in parts}
        shape = shapes.pop() if len(shapes) == 1 else np.broadcast_shapes(*shapes)
        out = np.empty((len(parts),) + shape)
        for i, part in enumerate(parts):
            out[i] = part
        return out.transpose(tuple(range(1, out.ndim)) + (0,))


#: The array namespace system definitions are written with (see the module docstring).
xp = _ArrayNamespace()


__all__ = ["is_symbolic", "xp"]
