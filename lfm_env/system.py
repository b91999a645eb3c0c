"""A controlled system with a latent force, defined once for NumPy and CasADi.

A :class:`ControlSystem` is the physics of one case study: named states and inputs with
units, the right-hand side ``dx/dt = f(x, u, w)`` with a latent force ``w``, hard input
bounds and named state constraints ``g(x) <= 0``. A :class:`QuadraticCost` is the
control objective. The environment (truth simulation and reward), the estimators, the
scenario problem and every solver read these two objects; nothing else writes the
dynamics, a constraint or the cost again.

The functions a system is made of are written once and work on both kinds of data. Write
them with the array namespace :data:`xp`::

    from lfm_env.system import xp

    def rhs(x, u, w):
        p, v = xp.unstack(x)          # components of the state
        (a,) = xp.unstack(u)
        (force,) = xp.unstack(w)
        return xp.stack([v, a + force])

* NumPy: ``x`` has shape ``(..., nx)``, ``u`` ``(..., nu)``, ``w`` ``(..., nw)``, broadcast
  against each other; the result has shape ``(..., nx)``.
* CasADi: ``x``, ``u`` and ``w`` are column vectors (``SX``/``MX``); the result is an
  ``(nx, 1)`` column.

Constraints ``g(x)`` follow the same rule with ``ng`` components (feasible where ``<= 0``).
"""

from __future__ import annotations

import re
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import casadi as ca
import numpy as np

_FLOAT_DTYPES = (np.dtype(np.float64), np.dtype(np.float32))

_UNIT = re.compile(r"^\s*(?P<name>[^\[]+?)\s*(\[(?P<unit>[^\]]*)\])?\s*$")


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


def split_unit(label: str) -> tuple[str, str]:
    """``("p_x", "m")`` from a label ``"p_x [m]"``; the unit is ``""`` when none is given."""
    m = _UNIT.match(label)
    if m is None:
        return label.strip(), ""
    return m.group("name"), m.group("unit") or ""


def _names(value: Any, field_name: str) -> tuple[str, ...]:
    if isinstance(value, str) or not isinstance(value, Sequence):
        raise ValueError(f"ControlSystem.{field_name}={value!r}: must be a sequence of strings")
    names = tuple(value)
    if not all(isinstance(n, str) and n.strip() for n in names):
        raise ValueError(f"ControlSystem.{field_name}={value!r}: must be non-empty strings")
    bare = [split_unit(n)[0] for n in names]
    if len(set(bare)) != len(bare):
        raise ValueError(f"ControlSystem.{field_name}={value!r}: names must be unique")
    return names


def _vector(value: Any, n: int, name: str) -> np.ndarray:
    arr = np.asarray(value, dtype=float).reshape(-1) if value is not None else None
    if arr is None or arr.shape != (n,):
        raise ValueError(f"{name}={value!r}: must be {n} numbers")
    arr = arr.copy()
    arr.flags.writeable = False
    return arr


@dataclass(frozen=True, eq=False)
class ControlSystem:
    """A nonlinear system ``dx/dt = f(x, u, w)`` driven by inputs ``u`` and a latent force ``w``.

    Args:
        name: short identifier, e.g. ``"sine_track"``.
        state_names: one label per state with its unit, e.g. ``("p_x [m]", "v [m/s]")``.
        input_names: one label per input with its unit.
        rhs: ``f(x, u, w)``, written once for NumPy and CasADi (see :mod:`lfm_env.system`).
        input_lower: hard lower input bounds, in the inputs' units.
        input_upper: hard upper input bounds.
        constraints: ``g(x)`` with ``len(constraint_names)`` components, feasible where
            ``<= 0``, in the constraints' units; ``None`` for none.
        constraint_names: one label per constraint, with its unit (``"track_left [m]"``).
        force_names: one label per latent-force component entering ``f``, with its unit.
        mirror_inputs: inputs whose sign flip mirrors a manoeuvre (the bicycle's steering).
            A hint for the solvers' extra starts on non-convex problems; empty for none.
        fallback_law: optional state feedback ``law(x, dt) -> u`` applied instead of
            ``fallback_input`` (clipped into the bounds), e.g. braking to a standstill.
        fallback_input: the input applied when a solve fails and no plan is left (e.g.
            full braking); by default the input closest to zero inside the bounds.
        constraint_groups: names for groups of constraints that metrics report together
            (``{"track": (0, 1)}``: the excess over the track band, either side); by
            default each constraint is its own group, named by its label.
        violation_tolerances: for each group, the excesses [group unit] beyond which a
            violation counts in the tolerance-aware metrics (``{"track": (0.01, 0.05)}``:
            steps more than 1 cm and 5 cm outside the band); groups not named get none.

    The NumPy right-hand side is batched over leading axes, so one call moves thousands
    of particles; the CasADi one is built once into :meth:`casadi_rhs` and friends.
    """

    name: str
    state_names: tuple[str, ...]
    input_names: tuple[str, ...]
    rhs: Callable[[Any, Any, Any], Any]
    input_lower: Any
    input_upper: Any
    constraints: Callable[[Any], Any] | None = None
    constraint_names: tuple[str, ...] = ()
    force_names: tuple[str, ...] = ("w",)
    mirror_inputs: tuple[int, ...] = ()
    fallback_input: Any = None
    fallback_law: Callable[[Any, float], Any] | None = None
    constraint_groups: Any = None
    violation_tolerances: Any = None
    _cache: dict = field(default_factory=dict, init=False, repr=False)

    def __post_init__(self) -> None:
        if not isinstance(self.name, str) or not self.name:
            raise ValueError(f"ControlSystem.name={self.name!r}: must be a non-empty string")
        for name in ("state_names", "input_names", "force_names"):
            object.__setattr__(self, name, _names(getattr(self, name), name))
        if self.constraints is None and self.constraint_names:
            raise ValueError("ControlSystem.constraint_names given without constraints")
        names = () if self.constraints is None else self.constraint_names
        object.__setattr__(self, "constraint_names", _names(names, "constraint_names"))
        if self.fallback_law is not None and not callable(self.fallback_law):
            raise ValueError("ControlSystem.fallback_law must be callable: law(x, dt) -> u")
        if not callable(self.rhs):
            raise ValueError("ControlSystem.rhs must be callable: f(x, u, w) -> dx/dt")
        nu = len(self.input_names)
        lo = _vector(self.input_lower, nu, "ControlSystem.input_lower")
        hi = _vector(self.input_upper, nu, "ControlSystem.input_upper")
        if not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi)) and np.all(lo < hi)):
            raise ValueError(
                f"ControlSystem input bounds {lo.tolist()} .. {hi.tolist()}: must be finite "
                "with input_lower < input_upper"
            )
        object.__setattr__(self, "input_lower", lo)
        object.__setattr__(self, "input_upper", hi)
        mirror = tuple(int(i) for i in self.mirror_inputs)
        if not all(0 <= i < nu for i in mirror):
            raise ValueError(f"ControlSystem.mirror_inputs={mirror}: indices in [0, {nu})")
        object.__setattr__(self, "mirror_inputs", mirror)
        fallback = np.clip(np.zeros(nu), lo, hi) if self.fallback_input is None else None
        if fallback is None:
            fallback = _vector(self.fallback_input, nu, "ControlSystem.fallback_input")
            if np.any(fallback < lo) or np.any(fallback > hi):
                raise ValueError("ControlSystem.fallback_input must lie inside the input bounds")
        fallback.flags.writeable = False
        object.__setattr__(self, "fallback_input", fallback)
        groups = self.constraint_groups
        if groups is None:
            groups = {label: (j,) for j, label in enumerate(self.constraint_labels)}
        try:
            groups = {str(k): tuple(int(j) for j in v) for k, v in dict(groups).items()}
        except (TypeError, ValueError):
            raise ValueError(
                f"ControlSystem.constraint_groups={self.constraint_groups!r}: must map names "
                "to tuples of constraint indices"
            ) from None
        if not all(v and all(0 <= j < self.ng for j in v) for v in groups.values()):
            raise ValueError(
                f"ControlSystem.constraint_groups={groups}: indices must be in [0, {self.ng})"
            )
        object.__setattr__(self, "constraint_groups", groups)
        tolerances = {} if self.violation_tolerances is None else self.violation_tolerances
        try:
            tolerances = {str(k): tuple(float(t) for t in v) for k, v in dict(tolerances).items()}
        except (TypeError, ValueError):
            raise ValueError(
                f"ControlSystem.violation_tolerances={self.violation_tolerances!r}: must map "
                "group names to tuples of excesses > 0"
            ) from None
        unknown = sorted(set(tolerances) - set(groups))
        bad = [t for v in tolerances.values() for t in v if not (np.isfinite(t) and t > 0.0)]
        if unknown or bad:
            raise ValueError(
                f"ControlSystem.violation_tolerances={tolerances}: keys must be constraint "
                f"groups {sorted(groups)} and values finite excesses > 0"
            )
        object.__setattr__(self, "violation_tolerances", tolerances)
        self._check_shapes()

    def _check_shapes(self) -> None:
        """Evaluate ``f`` and ``g`` once on NumPy batches and CasADi symbols."""
        nx, nu, nw, ng = self.nx, self.nu, self.nw, self.ng
        x, u, w = np.zeros((3, nx)), np.zeros((3, nu)), np.zeros((3, nw))
        dx = np.asarray(self.rhs(x, u, w))
        if dx.shape != (3, nx):
            raise ValueError(
                f"ControlSystem.rhs on a batch of 3 states returned shape {dx.shape}; "
                f"expected (3, nx) = {(3, nx)}"
            )
        fx = self.casadi_rhs()
        if fx.size_out(0) != (nx, 1):
            raise ValueError(f"ControlSystem.rhs on CasADi returned {fx.size_out(0)}; ({nx}, 1)")
        if self.constraints is not None:
            g = np.asarray(self.constraints(x))
            if g.shape != (3, ng):
                raise ValueError(
                    f"ControlSystem.constraints on a batch of 3 states returned shape {g.shape}; "
                    f"expected (3, len(constraint_names)) = {(3, ng)}"
                )
            if self.casadi_constraints().size_out(0) != (ng, 1):
                raise ValueError("ControlSystem.constraints on CasADi: expected an (ng, 1) column")

    # ------------------------------------------------------------------ dimensions

    @property
    def nx(self) -> int:
        """Number of physical states."""
        return len(self.state_names)

    @property
    def nu(self) -> int:
        """Number of inputs."""
        return len(self.input_names)

    @property
    def nw(self) -> int:
        """Number of latent-force components."""
        return len(self.force_names)

    @property
    def ng(self) -> int:
        """Number of state constraints."""
        return len(self.constraint_names)

    @property
    def state_labels(self) -> tuple[str, ...]:
        """State names without their units."""
        return tuple(split_unit(n)[0] for n in self.state_names)

    @property
    def constraint_labels(self) -> tuple[str, ...]:
        """Constraint names without their units."""
        return tuple(split_unit(n)[0] for n in self.constraint_names)

    # ------------------------------------------------------------------ NumPy

    def euler_step(self, x: Any, u: Any, w: Any, dt: float) -> Any:
        """One explicit Euler step ``x + dt f(x, u, w)`` (NumPy batched, or CasADi)."""
        return x + dt * self.rhs(x, u, w)

    def constraint_values(self, x: Any) -> Any:
        """``g(x)`` ``(..., ng)`` (NumPy) or an ``(ng, 1)`` column (CasADi)."""
        if self.constraints is None:
            if is_symbolic(x):
                return ca.DM.zeros(0, 1)
            return np.zeros(np.shape(x)[:-1] + (0,))
        return self.constraints(x)

    def constraint_excess(self, x: Any) -> np.ndarray:
        """How far each constraint is exceeded, ``max(g(x), 0)`` ``(..., ng)`` (0 inside)."""
        return np.maximum(np.asarray(self.constraint_values(np.asarray(x, dtype=float))), 0.0)

    def group_excess(self, x: Any) -> dict[str, Any]:
        """Largest excess [constraint unit] within each of :attr:`constraint_groups`."""
        excess = self.constraint_excess(x)
        return {k: np.max(excess[..., list(v)], axis=-1) for k, v in self.constraint_groups.items()}

    def fallback(self, x: Any, dt: float) -> np.ndarray:
        """The input to apply when no plan is left, at (estimated) state ``x`` ``(nx,)``."""
        if self.fallback_law is None:
            return np.array(self.fallback_input, dtype=float)
        u = np.asarray(self.fallback_law(np.asarray(x, dtype=float), dt), dtype=float)
        u = u.reshape(self.nu)
        return self.clip_input(u) if np.all(np.isfinite(u)) else np.array(self.fallback_input)

    def clip_input(self, u: Any) -> np.ndarray:
        """``u`` clipped into the input bounds."""
        return np.clip(u, self.input_lower, self.input_upper)

    # ------------------------------------------------------------------ CasADi

    def _symbols(self) -> tuple[ca.SX, ca.SX, ca.SX]:
        return ca.SX.sym("x", self.nx), ca.SX.sym("u", self.nu), ca.SX.sym("w", self.nw)

    def casadi_rhs(self) -> ca.Function:
        """``f(x, u, w)`` as a CasADi function (built once)."""
        if "rhs" not in self._cache:
            x, u, w = self._symbols()
            dx = ca.vec(ca.SX(self.rhs(x, u, w)))
            self._cache["rhs"] = ca.Function("f", [x, u, w], [dx], ["x", "u", "w"], ["dx"])
        return self._cache["rhs"]

    def casadi_step(self, dt: float) -> ca.Function:
        """One Euler step ``x+ = x + dt f(x, u, w)`` as a CasADi function (cached per ``dt``)."""
        key = ("step", float(dt))
        if key not in self._cache:
            x, u, w = self._symbols()
            x_next = x + float(dt) * self.casadi_rhs()(x, u, w)
            self._cache[key] = ca.Function(
                "euler_step", [x, u, w], [x_next], ["x", "u", "w"], ["x_next"]
            )
        return self._cache[key]

    def casadi_constraints(self) -> ca.Function:
        """``g(x)`` as a CasADi function (an empty output when there are no constraints)."""
        if "g" not in self._cache:
            x = ca.SX.sym("x", self.nx)
            g = ca.vec(ca.SX(self.constraint_values(x)))
            self._cache["g"] = ca.Function("g", [x], [g], ["x"], ["g"])
        return self._cache["g"]

    def constraint_jacobian(self, x: Any) -> np.ndarray:
        """``dg/dx`` ``(ng, nx)`` at one state ``(nx,)``, from the CasADi expression."""
        if "dg" not in self._cache:
            xs = ca.SX.sym("x", self.nx)
            g = self.casadi_constraints()(xs)
            self._cache["dg"] = ca.Function("dg", [xs], [ca.jacobian(g, xs)], ["x"], ["dg"])
        return np.asarray(self._cache["dg"](np.asarray(x, dtype=float)).full(), dtype=float)

    def __getstate__(self) -> dict[str, Any]:
        # CasADi functions are rebuilt on demand after unpickling (e.g. in a worker).
        state = self.__dict__.copy()
        state["_cache"] = {}
        return state

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__dict__.update(state)


def _weight(value: Any, n: int, name: str) -> np.ndarray:
    """A PSD weight matrix from a diagonal (``n`` numbers) or a full ``(n, n)`` matrix."""
    arr = np.asarray(value, dtype=float)
    if arr.shape == (n,):
        arr = np.diag(arr)
    if arr.shape != (n, n) or not np.all(np.isfinite(arr)):
        raise ValueError(
            f"QuadraticCost.{name}: must be {n} finite numbers or an ({n}, {n}) matrix"
        )
    if not np.allclose(arr, arr.T, rtol=0.0, atol=1e-12 * (1.0 + np.abs(arr).max())):
        raise ValueError(f"QuadraticCost.{name}: must be symmetric")
    if np.linalg.eigvalsh(arr)[0] < -1e-12 * (1.0 + np.abs(arr).max()):
        raise ValueError(f"QuadraticCost.{name}: must be positive semi-definite")
    arr = arr.copy()
    arr.flags.writeable = False
    return arr


@dataclass(frozen=True, eq=False)
class QuadraticCost:
    """Stage cost ``(x - x_g)' Q (x - x_g) + u' R u`` and terminal ``(x - x_g)' Qf (x - x_g)``.

    Args:
        Q: state weights, a diagonal (``nx`` numbers) or an ``(nx, nx)`` PSD matrix, in
            1/(state unit)^2.
        R: input weights, a diagonal or an ``(nu, nu)`` PSD matrix.
        Qf: terminal state weights; ``None`` for ``Q``.
        x_goal: the goal state ``(nx,)`` in the states' units; ``None`` for zeros.
    """

    Q: Any
    R: Any
    Qf: Any = None
    x_goal: Any = None

    def __post_init__(self) -> None:
        q = np.asarray(self.Q, dtype=float)
        nx = q.shape[0] if q.ndim >= 1 else -1
        nu = np.asarray(self.R, dtype=float).shape[0] if np.ndim(self.R) >= 1 else -1
        if nx < 1 or nu < 1:
            raise ValueError("QuadraticCost: Q and R must be vectors or square matrices")
        object.__setattr__(self, "Q", _weight(self.Q, nx, "Q"))
        object.__setattr__(self, "R", _weight(self.R, nu, "R"))
        object.__setattr__(self, "Qf", _weight(self.Q if self.Qf is None else self.Qf, nx, "Qf"))
        goal = np.zeros(nx) if self.x_goal is None else self.x_goal
        object.__setattr__(self, "x_goal", _vector(goal, nx, "QuadraticCost.x_goal"))
        if not np.all(np.isfinite(self.x_goal)):
            raise ValueError("QuadraticCost.x_goal must be finite")

    @property
    def nx(self) -> int:
        return int(self.Q.shape[0])

    @property
    def nu(self) -> int:
        return int(self.R.shape[0])

    @property
    def diagonal(self) -> bool:
        """True when ``Q``, ``R`` and ``Qf`` are diagonal (solvers take a cheaper path)."""
        return all(
            np.count_nonzero(m - np.diag(np.diag(m))) == 0 for m in (self.Q, self.R, self.Qf)
        )

    def check_system(self, system: ControlSystem) -> None:
        """Raise ``ValueError`` unless the dimensions fit ``system``."""
        if (self.nx, self.nu) != (system.nx, system.nu):
            raise ValueError(
                f"QuadraticCost has nx={self.nx}, nu={self.nu}; system {system.name!r} has "
                f"nx={system.nx} states {system.state_labels} and nu={system.nu} inputs"
            )

    def _form(self, M: np.ndarray, e: Any) -> Any:
        if is_symbolic(e):
            return ca.bilin(ca.DM(M), e, e)
        e = np.asarray(e, dtype=float)
        if np.count_nonzero(M - np.diag(np.diag(M))) == 0:
            d = np.diag(M)
            return e @ (d * e) if e.ndim == 1 else np.einsum("...i,i,...i->...", e, d, e)
        return np.einsum("...i,ij,...j->...", e, M, e)

    def state_cost(self, x: Any) -> Any:
        """``(x - x_g)' Q (x - x_g)`` (NumPy ``(...)`` or a CasADi scalar)."""
        return self._form(self.Q, x - (ca.DM(self.x_goal) if is_symbolic(x) else self.x_goal))

    def terminal_cost(self, x: Any) -> Any:
        """``(x - x_g)' Qf (x - x_g)``."""
        return self._form(self.Qf, x - (ca.DM(self.x_goal) if is_symbolic(x) else self.x_goal))

    def input_cost(self, u: Any) -> Any:
        """``u' R u``."""
        return self._form(self.R, u)

    def stage_cost(self, x: Any, u: Any) -> Any:
        """``(x - x_g)' Q (x - x_g) + u' R u``: minus the env's reward."""
        return self.state_cost(x) + self.input_cost(u)


__all__ = ["ControlSystem", "QuadraticCost", "is_symbolic", "split_unit", "xp"]
