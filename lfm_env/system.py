"""A controlled system with a latent force, defined once for NumPy and CasADi.

A :class:`ControlSystem` is the physics of one case study: named states and inputs with
units, the right-hand side ``dx/dt = f(x, u, w)`` with a latent force ``w``, hard input
bounds and named state constraints ``g(x) <= 0``. A :class:`~lfm_env.cost.QuadraticCost`
is the control objective. The environment (truth simulation and reward), the estimators, the
scenario problem and every solver read these two objects; nothing else writes the
dynamics, a constraint or the cost again.

The functions a system is made of are written once and work on both kinds of data. Write
them with the array namespace :data:`lfm_env.xp.xp`; the module
:mod:`lfm_env.xp` shows a right-hand side written so, and the shapes it gets and returns on
NumPy batches and on CasADi columns. Constraints ``g(x)`` follow the same rule with ``ng``
components (feasible where ``<= 0``).
"""

from __future__ import annotations

import re
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import casadi as ca
import numpy as np

from lfm_env.validation import frozen_vector
from lfm_env.xp import is_symbolic

_UNIT = re.compile(r"^\s*(?P<name>[^\[]+?)\s*(\[(?P<unit>[^\]]*)\])?\s*$")


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


def _tuples_by_name(
    value: Any, convert: Callable[[Any], Any], field_name: str, allowed: str
) -> dict[str, tuple]:
    """``{str(name): tuple(convert(item) ...)}`` of a mapping, or a ValueError naming the field
    ``ControlSystem.<field_name>`` and what it must map (``allowed``)."""
    try:
        return {str(k): tuple(convert(j) for j in v) for k, v in dict(value).items()}
    except (TypeError, ValueError):
        raise ValueError(f"ControlSystem.{field_name}={value!r}: must map {allowed}") from None


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
        self._set_names()
        if self.fallback_law is not None and not callable(self.fallback_law):
            raise ValueError("ControlSystem.fallback_law must be callable: law(x, dt) -> u")
        if not callable(self.rhs):
            raise ValueError("ControlSystem.rhs must be callable: f(x, u, w) -> dx/dt")
        self._set_inputs()
        self._set_groups()
        self._check_shapes()

    def _set_names(self) -> None:
        """The states', inputs', forces' and constraints' names, checked."""
        if not isinstance(self.name, str) or not self.name:
            raise ValueError(f"ControlSystem.name={self.name!r}: must be a non-empty string")
        for name in ("state_names", "input_names", "force_names"):
            object.__setattr__(self, name, _names(getattr(self, name), name))
        if self.constraints is None and self.constraint_names:
            raise ValueError("ControlSystem.constraint_names given without constraints")
        names = () if self.constraints is None else self.constraint_names
        object.__setattr__(self, "constraint_names", _names(names, "constraint_names"))

    def _set_inputs(self) -> None:
        """The input bounds, the mirrored inputs and the fallback input, checked."""
        nu = len(self.input_names)
        lo = frozen_vector(self.input_lower, nu, "ControlSystem.input_lower")
        hi = frozen_vector(self.input_upper, nu, "ControlSystem.input_upper")
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
            fallback = frozen_vector(self.fallback_input, nu, "ControlSystem.fallback_input")
            if np.any(fallback < lo) or np.any(fallback > hi):
                raise ValueError("ControlSystem.fallback_input must lie inside the input bounds")
        fallback.flags.writeable = False
        object.__setattr__(self, "fallback_input", fallback)

    def _set_groups(self) -> None:
        """The constraint groups and their violation tolerances, checked."""
        groups = self.constraint_groups
        if groups is None:
            groups = {label: (j,) for j, label in enumerate(self.constraint_labels)}
        groups = _tuples_by_name(
            groups, int, "constraint_groups", "names to tuples of constraint indices"
        )
        if not all(v and all(0 <= j < self.ng for j in v) for v in groups.values()):
            raise ValueError(
                f"ControlSystem.constraint_groups={groups}: indices must be in [0, {self.ng})"
            )
        object.__setattr__(self, "constraint_groups", groups)
        tolerances = {} if self.violation_tolerances is None else self.violation_tolerances
        tolerances = _tuples_by_name(
            tolerances, float, "violation_tolerances", "group names to tuples of excesses > 0"
        )
        unknown = sorted(set(tolerances) - set(groups))
        bad = [t for v in tolerances.values() for t in v if not (np.isfinite(t) and t > 0.0)]
        if unknown or bad:
            raise ValueError(
                f"ControlSystem.violation_tolerances={tolerances}: keys must be constraint "
                f"groups {sorted(groups)} and values finite excesses > 0"
            )
        object.__setattr__(self, "violation_tolerances", tolerances)

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


__all__ = ["ControlSystem", "split_unit"]
