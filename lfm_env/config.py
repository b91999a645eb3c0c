"""Typed, validated configuration of the SineTrack world.

One frozen dataclass per component, defaults in one place (the dataclass), YAML as
plain data read with ``yaml.safe_load``. Unknown keys, wrong types, non-finite values
and out-of-range values are errors that name the key and the allowed range.

A config file has a top-level ``env:`` section (this module) and an ``agents:``
section (read by :mod:`controllers.config`).
"""

from __future__ import annotations

import dataclasses
import io
import math
import os
import reprlib
import types
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar

import numpy as np
import yaml

from lfm_env.worlds.sine_track.system import SineTrack

T = TypeVar("T")


class ConfigError(ValueError):
    """A configuration value is unknown, of the wrong type or out of range."""


_REPR = reprlib.Repr()
_REPR.maxlevel = 3  # nested lists shown this deep ...
_REPR.maxlist = _REPR.maxtuple = _REPR.maxdict = _REPR.maxset = 8  # ... this wide
_REPR.maxstring = _REPR.maxlong = _REPR.maxother = 100


def _show(value: Any, limit: int = 80) -> str:
    """A short ``repr(value)`` for an error message, cut to ``limit`` characters; never raises.

    Bounded in time and memory whatever the value: containers are shown at most 3 levels
    deep and 8 items wide (a YAML alias bomb expands to billions of items, whose full
    repr takes minutes and gigabytes); an integer beyond ``sys.get_int_max_str_digits()``
    has no repr (ValueError), and a megabyte-long string would drown the message.
    """
    try:
        text = _REPR.repr(value)
    except (ValueError, RecursionError):
        if isinstance(value, int):
            return f"<an integer of about {round(value.bit_length() * math.log10(2))} digits>"
        return f"<a {type(value).__name__}>"
    return text if len(text) <= limit else text[: limit - 3] + "..."


def _key(key: Any) -> str:
    """A mapping key as text for an error message, shortened like :func:`_show`."""
    text = key if isinstance(key, str) else _show(key)
    return text if len(text) <= 80 else text[:77] + "..."


# --------------------------------------------------------------------------- loading


def _check_unique_keys(root: yaml.Node | None) -> None:
    """Raise a YAML error for a key written twice in one mapping.

    YAML requires unique keys, but PyYAML keeps the last value silently, so a repeated
    key (a typo's twin) would pass unnoticed. Works on the composed node graph, which
    shares aliased nodes, so each node is visited once.
    """
    seen: set[int] = set()
    todo = [] if root is None else [root]
    while todo:
        node = todo.pop()
        if id(node) in seen:
            continue
        seen.add(id(node))
        if isinstance(node, yaml.MappingNode):
            keys: set[tuple[str, str]] = set()
            for key, value in node.value:
                if isinstance(key, yaml.ScalarNode) and key.tag != "tag:yaml.org,2002:merge":
                    if (key.tag, key.value) in keys:
                        raise yaml.constructor.ConstructorError(
                            "while reading a mapping",
                            node.start_mark,
                            f"found the key {_key(key.value)!r} twice",
                            key.start_mark,
                        )
                    keys.add((key.tag, key.value))
                todo += [key, value]
        elif isinstance(node, yaml.SequenceNode):
            todo += node.value


#: Limits of a config file: its size [bytes], the nesting depth of its lists and mappings,
#: and the number of values it expands to once its aliases are followed. Real configs are
#: a few kB, 3 levels deep and a few hundred values; the limits make the reading of any
#: file, however hostile, take well under a second and a few MB.
MAX_CONFIG_BYTES = 64_000
MAX_CONFIG_DEPTH = 50
MAX_CONFIG_VALUES = 10_000


def _check_size(root: yaml.Node | None) -> None:
    """Raise ``ConfigError`` when the node graph nests deeper than
    :data:`MAX_CONFIG_DEPTH` or expands (aliases followed) to more than
    :data:`MAX_CONFIG_VALUES` values; iterative, each shared node is counted once."""
    if root is None:
        return
    expanded: dict[int, int] = {}  # id(node) -> values it expands to
    todo: list[tuple[yaml.Node, int, bool]] = [(root, 1, False)]
    while todo:
        node, depth, children_done = todo.pop()
        if depth > MAX_CONFIG_DEPTH:
            raise ConfigError(
                f"nests lists or mappings deeper than {MAX_CONFIG_DEPTH} levels "
                f"(line {node.start_mark.line + 1})"
            )
        if isinstance(node, yaml.MappingNode):
            children = [n for pair in node.value for n in pair]
        elif isinstance(node, yaml.SequenceNode):
            children = list(node.value)
        else:
            expanded[id(node)] = 1
            continue
        if children_done:
            total = 1 + sum(expanded[id(c)] for c in children)
            if total > MAX_CONFIG_VALUES:
                raise ConfigError(
                    f"expands to more than {MAX_CONFIG_VALUES} values once its aliases are "
                    f"followed (line {node.start_mark.line + 1})"
                )
            expanded[id(node)] = total
        elif id(node) not in expanded:
            todo.append((node, depth, True))
            todo += [(c, depth + 1, False) for c in children if id(c) not in expanded]


def load_yaml(path: str | os.PathLike) -> dict:
    """Read a YAML file with the safe loader; the top level must be a mapping.

    A key given twice in one mapping is an error, as are bytes that are not UTF-8 or
    UTF-16 text, a file over :data:`MAX_CONFIG_BYTES`, nesting deeper than
    :data:`MAX_CONFIG_DEPTH` and more than :data:`MAX_CONFIG_VALUES` values once the
    aliases are followed (a "billion laughs" file).

    Raises:
        ConfigError: naming the file and the problem; an unreadable file too (``OSError``).
    """
    path = Path(path)
    try:
        if not path.is_file():
            problem = "is not a file" if path.exists() else "does not exist"
            raise ConfigError(f"config file {str(path)!r} {problem}")
        size = path.stat().st_size
        if size > MAX_CONFIG_BYTES:
            raise ConfigError(
                f"config file {str(path)!r} has {size} bytes: must be <= {MAX_CONFIG_BYTES}"
            )
        # Binary streams: PyYAML reads the encoding from the byte order mark.
        with path.open("rb") as fh:
            text = fh.read(MAX_CONFIG_BYTES + 1)
    except OSError as exc:
        raise ConfigError(f"config file {str(path)!r} cannot be read: {exc.strerror}") from None
    if len(text) > MAX_CONFIG_BYTES:  # grew since stat
        raise ConfigError(f"config file {str(path)!r}: must be <= {MAX_CONFIG_BYTES} bytes")
    try:
        # Bytes: PyYAML reads the encoding from the byte order mark. Parsed once; the
        # checks run on the node graph before any Python value is built from it.
        loader = yaml.SafeLoader(io.BytesIO(text))
        try:
            try:
                root = loader.get_single_node()
            except RecursionError:
                raise ConfigError(
                    f"nests lists or mappings deeper than {MAX_CONFIG_DEPTH} levels"
                ) from None
            _check_size(root)
            _check_unique_keys(root)
            data = None if root is None else loader.construct_document(root)
        finally:
            loader.dispose()
    except ConfigError as exc:
        raise ConfigError(f"config file {str(path)!r} {exc}") from None
    except (yaml.YAMLError, ValueError) as exc:  # ValueError: an int over 4300 digits
        raise ConfigError(f"config file {str(path)!r} is not valid YAML: {exc}") from exc
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise ConfigError(f"config file {str(path)!r}: top level must be a mapping of sections")
    return data


TOP_LEVEL_KEYS = ("env_id", "env", "agents")


def read_section(source: Any, section: str) -> dict | None:
    """The ``section`` mapping of a config given as a path, a dict or ``None``.

    A dict that holds top-level keys (``env_id``, ``env``, ``agents``) gives the named
    section; any other dict is taken as the section itself.
    """
    if source is None:
        return None
    if isinstance(source, (str, os.PathLike)):
        source = load_yaml(source)
    if not isinstance(source, dict):
        raise ConfigError(
            f"config must be a path, a dict or a dataclass, got {type(source).__name__}"
        )
    top = set(TOP_LEVEL_KEYS)
    unknown_top = {_key(k) for k in source} - top
    if {_key(k) for k in source} & top:
        if unknown_top:
            raise ConfigError(
                f"unknown top-level config section(s) {sorted(unknown_top)}; allowed: {sorted(top)}"
            )
        sec = source.get(section)
        if sec is None:
            return {}
        if not isinstance(sec, dict):
            raise ConfigError(f"config section {section!r} must be a mapping")
        return sec
    return source


def _is_float_text(text: str) -> bool:
    """Whether Python reads ``text`` (a short one) as a finite float, e.g. ``"1.0e6"``."""
    if len(text) > 100:
        return False
    try:
        return math.isfinite(float(text))
    except ValueError:
        return False


def _convert(value: Any, tp: Any, key: str) -> Any:
    """Convert a plain YAML value to the annotated type ``tp``, or raise naming ``key``."""
    origin = typing.get_origin(tp)
    args = typing.get_args(tp)
    if origin in (typing.Union, types.UnionType):
        if value is None and type(None) in args:
            return None
        inner = [a for a in args if a is not type(None)]
        return _convert(value, inner[0], key)
    if dataclasses.is_dataclass(tp):
        if isinstance(value, tp):
            return value
        if not isinstance(value, dict):
            raise ConfigError(f"{key}: expected a mapping, got {_show(value)}")
        return from_dict(tp, value, prefix=key)
    if tp is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{key}={_show(value)}: expected true or false")
        return value
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
            raise ConfigError(f"{key}={_show(value)}: expected an integer")
        return int(value)
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
            hint = ""
            if isinstance(value, str):
                hint = " (write floats with a dot, e.g. 1.0e-3)"
                if _is_float_text(value):
                    hint = (
                        f" (PyYAML, a YAML 1.1 reader, takes {_show(value)} for text: write"
                        " floats with a dot and a signed exponent, e.g. 1.0e+6 or 1.0e-3)"
                    )
            raise ConfigError(f"{key}={_show(value)}: expected a number{hint}")
        try:
            value = float(value)
        except OverflowError:
            raise ConfigError(f"{key}={_show(value)}: too large for a float") from None
        if not math.isfinite(value):
            raise ConfigError(f"{key}={_show(value)}: must be finite")
        return value
    if tp is str:
        if not isinstance(value, str):
            raise ConfigError(f"{key}={_show(value)}: expected a string")
        return value
    if origin is tuple:
        if isinstance(value, np.ndarray):
            value = value.tolist()
        if len(args) == 2 and args[1] is Ellipsis and isinstance(value, (int, float)):
            value = [value]  # a variable-length vector may be given as one number
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"{key}={_show(value)}: expected a list")
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_convert(v, args[0], f"{key}[{i}]") for i, v in enumerate(value))
        if len(value) != len(args):
            raise ConfigError(f"{key}={_show(list(value))}: expected a list of {len(args)} values")
        return tuple(
            _convert(v, a, f"{key}[{i}]") for i, (v, a) in enumerate(zip(value, args, strict=True))
        )
    raise TypeError(f"unsupported config type {tp!r} for {key}")  # a bug, not user input


def from_dict(cls: type[T], data: dict | None, prefix: str = "") -> T:
    """Build the frozen dataclass ``cls`` from a plain mapping, validating every key.

    Args:
        cls: the dataclass to build.
        data: mapping of field names to plain values; missing fields keep their defaults.
        prefix: dotted path of the section, used in error messages (e.g. ``"env"``).

    Raises:
        ConfigError: for unknown keys, wrong types, non-finite or out-of-range values.
    """
    data = {} if data is None else data
    if not isinstance(data, dict):
        raise ConfigError(f"{prefix or cls.__name__}: expected a mapping, got {_show(data)}")
    hints = typing.get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls) if f.init}
    unknown = sorted(_key(k) for k in data if k not in names)
    if unknown:
        where = f"{prefix}." if prefix else ""
        raise ConfigError(
            f"unknown config key(s) {[where + k for k in unknown]}; allowed keys: {sorted(names)}"
        )
    kwargs = {}
    for name, value in data.items():
        key = f"{prefix}.{name}" if prefix else name
        kwargs[name] = _convert(value, hints[name], key)
    try:
        return cls(**kwargs)
    except ConfigError as exc:
        if prefix and not str(exc).startswith(prefix):
            raise ConfigError(f"{prefix}.{exc}") from None
        raise


def to_dict(obj: Any) -> dict:
    """Plain (YAML-ready) mapping of a config dataclass, tuples as lists."""

    def plain(v: Any) -> Any:
        if dataclasses.is_dataclass(v):
            return {f.name: plain(getattr(v, f.name)) for f in dataclasses.fields(v) if f.init}
        if isinstance(v, tuple):
            return [plain(x) for x in v]
        return v

    return plain(obj)


class _Checker:
    """Collects range checks of one dataclass and raises with the field's name."""

    def __init__(self, obj: Any) -> None:
        self.obj = obj

    def __call__(self, name: str, ok: bool, allowed: str) -> None:
        if not ok:
            raise ConfigError(f"{name}={_show(getattr(self.obj, name))}: must be {allowed}")

    def positive(self, *names: str) -> None:
        for n in names:
            self(n, getattr(self.obj, n) > 0, "> 0")

    def non_negative(self, *names: str) -> None:
        for n in names:
            v = getattr(self.obj, n)
            ok = all(x >= 0 for x in v) if isinstance(v, tuple) else v >= 0
            self(n, ok, ">= 0" if not isinstance(v, tuple) else "all >= 0")


# --------------------------------------------------------------------------- sections

#: Longest episode [steps]: 100000 steps are hours of solves, and the recorded trajectory
#: (a few arrays of this length) stays within megabytes.
MAX_STEPS = 100_000

MATERN_NUS = (0.5, 1.5, 2.5, 3.5)
DISCRETIZATIONS = ("exact", "euler_maruyama")
KERNELS = ("matern", "squared_exponential", "periodic")
STARTS = ("stationary", "zero")


@dataclass(frozen=True)
class DisturbanceConfig:
    """The latent force: a stationary GP in time, in state-space form.

    ``kernel`` picks the covariance: ``matern`` (exact in state space; the paper's),
    ``squared_exponential`` (Taylor approximation of order ``order``) or ``periodic``
    (``sigma^2 exp(-2 sin^2(pi tau / period) / lengthscale^2)``, cosine series with
    ``harmonics`` terms; its lengthscale is dimensionless).
    """

    kernel: str = "matern"  # one of KERNELS
    nu: float = 2.5  # Matern smoothness, a half-integer in MATERN_NUS
    variance: float = 4.0  # sigma^2 [(m/s^2)^2]
    lengthscale: float = 4.0  # [s] (dimensionless for the periodic kernel)
    order: int = 6  # Taylor order of the squared-exponential approximation, 1..12
    period: float = 10.0  # [s] of the periodic kernel
    harmonics: int = 6  # cosine-series terms of the periodic kernel
    discretization: str = "exact"  # "exact" (expm) or "euler_maruyama" (the published code)
    start: str = "stationary"  # "stationary" (z0 ~ N(0, Pinf)) or "zero" (the published code)

    def __post_init__(self) -> None:
        c = _Checker(self)
        c("kernel", self.kernel in KERNELS, f"one of {KERNELS}")
        c("nu", self.nu in MATERN_NUS, f"one of {list(MATERN_NUS)}")
        c.positive("variance", "lengthscale", "period")
        # Shorter lengthscales overflow lambda^(2 nu + 1) in the state-space model.
        c("lengthscale", self.lengthscale >= 1.0e-6, ">= 1.0e-6 s")
        c("order", 1 <= self.order <= 12, "an integer in [1, 12]")
        c("harmonics", 1 <= self.harmonics <= 100, "an integer in [1, 100]")
        c("discretization", self.discretization in DISCRETIZATIONS, f"one of {DISCRETIZATIONS}")
        c("start", self.start in STARTS, f"one of {STARTS}")
        if self.kernel != "matern":
            try:  # the approximations know their own limits (e.g. too few harmonics)
                self.make_kernel()
            except ValueError as exc:
                raise ConfigError(f"kernel={self.kernel!r}: {exc}") from None

    def make_kernel(self):
        """The state-space kernel (:mod:`lfm_env.gp`) these settings describe."""
        from lfm_env import gp

        if self.kernel == "squared_exponential":
            return gp.squared_exponential(self.variance, self.lengthscale, order=self.order)
        if self.kernel == "periodic":
            return gp.periodic(
                self.variance, self.lengthscale, self.period, harmonics=self.harmonics
            )
        return gp.matern(self.nu, self.variance, self.lengthscale)


class WorldConfig:
    """What every world's ``env`` section gives the rest of the project (a mixin).

    A world config is a frozen dataclass with at least the fields ``dt`` [s],
    ``initial_state``, ``goal_state``, ``Q``, ``R``, ``measurement_noise_std``,
    ``process_noise_diffusion`` (vectors over the state in config units),
    ``max_steps`` and ``disturbance``; it names its env (:attr:`ENV_ID`), the states it
    gives in degrees (:attr:`ANGLE_STATES`, converted to radians here) and builds its
    system (:meth:`make_system`). Everything else (the model, the cost, the SI vectors) is
    derived here the same way for every world.
    """

    ENV_ID: str = ""  # the Gymnasium id of the world's env
    ANGLE_STATES: tuple[int, ...] = ()  # state indices given in degrees (deg/s) in configs

    def make_system(self):  # pragma: no cover - every world defines it
        raise NotImplementedError

    def state_from_config(self, values: Any) -> np.ndarray:
        """A state vector given in config units (angles in degrees) in SI units [rad]."""
        out = np.array(tuple(values), dtype=float)
        for i in self.ANGLE_STATES:
            out[i] = math.radians(out[i])
        return out

    @property
    def initial_state_rad(self) -> np.ndarray:
        """Start state in SI units."""
        return self.state_from_config(self.initial_state)

    @property
    def goal_state_rad(self) -> np.ndarray:
        """Goal state of the cost in SI units."""
        return self.state_from_config(self.goal_state)

    @property
    def measurement_std_rad(self) -> np.ndarray:
        """Std of the full-state measurement noise in SI units."""
        return self.state_from_config(self.measurement_noise_std)

    @property
    def process_noise_std_rad(self) -> np.ndarray:
        """Per-step process noise std on the physical states in SI units."""
        return self.state_from_config(self.process_noise_diffusion) * math.sqrt(self.dt)

    def make_model(self, disturbance: DisturbanceConfig | None = None, system: Any = None):
        """The latent-force model of this world, or of another belief about its force.

        Args:
            disturbance: the GP to model; ``None`` for this config's (the hidden truth's).
            system: the system to stack it on; ``None`` builds :meth:`make_system`.
        """
        from lfm_env.model import LatentForceModel

        d = self.disturbance if disturbance is None else disturbance
        return LatentForceModel(
            self.make_system() if system is None else system,
            kernel=d.make_kernel(),
            dt=self.dt,
            process_noise_std=self.process_noise_std_rad,
            discretization=d.discretization,
        )

    def make_cost(self):
        """The reward's cost: ``Q``, ``R`` on the goal state (no separate terminal weight)."""
        from lfm_env.system import QuadraticCost

        return QuadraticCost(Q=self.Q, R=self.R, x_goal=self.goal_state_rad)

    def replace(self, **changes: Any):
        """A copy with some fields changed (validated like any config)."""
        cls = type(self)
        return from_dict(cls, {**to_dict(self), **to_dict_fields(changes)}, prefix="env")


@dataclass(frozen=True)
class EnvConfig(WorldConfig):
    """The SineTrack world: vehicle, track, noise, disturbance, goal and episode limits.

    Vectors over the state ``[p_x, p_y, v, psi]`` give the heading in **degrees** for
    readability; the env converts to radians.
    """

    ENV_ID = "lfm_env/SineTrack-v0"
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
    disturbance: DisturbanceConfig = field(default_factory=DisturbanceConfig)

    def __post_init__(self) -> None:
        c = _Checker(self)
        c.positive("dt", "vehicle_length", "track_half_width", "accel_max", "goal_radius")
        c.positive("max_steps", "safety_margin")
        c("max_steps", self.max_steps <= MAX_STEPS, f"an integer in [1, {MAX_STEPS}]")
        c.non_negative("track_amplitude", "track_pulsation", "Q", "R")
        c.non_negative("measurement_noise_std", "process_noise_diffusion")
        c("x_max", self.x_max > self.x_min, f"> x_min={self.x_min}")
        c("speed_max", self.speed_max > self.speed_min, f"> speed_min={self.speed_min}")
        c("steer_max_deg", 0 < self.steer_max_deg < 90, "in (0, 90) deg")
        c("dt", self.dt <= 10.0, "<= 10 s")
        track = self.track
        gx, gy = self.goal
        c("goal", self.x_min <= gx <= self.x_max, f"inside x bounds [{self.x_min}, {self.x_max}]")
        c(
            "goal",
            float(track.track_excess(gx, gy)) == 0.0,
            f"on the track (|y - centre_y(x)| <= {self.track_half_width} m)",
        )
        x0, y0 = self.initial_state[:2]
        c(
            "initial_state",
            self.x_min <= x0 <= self.x_max and float(track.track_excess(x0, y0)) == 0.0,
            "a position inside the track and the x bounds",
        )

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
        """The bicycle on this track (:func:`lfm_env.worlds.sine_track.system.sine_track_system`)."""
        from lfm_env.worlds.sine_track.system import sine_track_system

        return sine_track_system(
            track=self.track,
            vehicle_length=self.vehicle_length,
            speed_min=self.speed_min,
            speed_max=self.speed_max,
            accel_max=self.accel_max,
            steer_max=self.steer_max,
        )


def to_dict_fields(changes: dict) -> dict:
    """Plain values of a partial mapping of config fields (dataclasses become dicts)."""
    return {k: (to_dict(v) if dataclasses.is_dataclass(v) else v) for k, v in changes.items()}


def check_latent_step(
    config: EnvConfig,
    disturbance: DisturbanceConfig | None = None,
    where: str = "env.disturbance",
) -> EnvConfig:
    """Refuse a latent-force model whose Euler-Maruyama step diverges; returns ``config``.

    The Euler step ``z+ = (I + F dt) z`` of a Matern model has the single eigenvalue
    ``1 - lambda dt`` with ``lambda = sqrt(2 nu) / lengthscale``: it is stable only for
    ``lambda dt < 2``, i.e. ``lengthscale > sqrt(2 nu) dt / 2``; beyond, the simulated
    force grows without bound (1e19 m/s^2 within 30 s). The exact discretisation is
    stable for every lengthscale. The env and the agents call this before simulating;
    :func:`load_env_config` does not, so such a config can still be read.

    Args:
        config: the world; its ``dt`` and, by default, its disturbance.
        disturbance: another model of the force at the same ``dt`` (the agents' belief).
        where: the config section of that model, for the message.

    Raises:
        ConfigError: naming ``<where>.lengthscale`` and its lower bound.
    """
    d = config.disturbance if disturbance is None else disturbance
    if d.discretization == "euler_maruyama" and d.kernel == "matern":
        bound = math.sqrt(2.0 * d.nu) * config.dt / 2.0
        if not d.lengthscale > bound:
            raise ConfigError(
                f"{where}.lengthscale={_show(d.lengthscale)}: must be > sqrt(2 nu) dt / 2"
                f" = {bound:.6g} s with discretization 'euler_maruyama' (its step diverges"
                " otherwise); use discretization 'exact' or a smaller dt"
            )
    elif d.discretization == "euler_maruyama":
        F = np.asarray(d.make_kernel().F)
        radius = float(np.max(np.abs(np.linalg.eigvals(np.eye(len(F)) + F * config.dt))))
        if radius >= 1.0:
            raise ConfigError(
                f"{where}.discretization='euler_maruyama': its step diverges for the "
                f"{d.kernel} kernel at dt={config.dt} (spectral radius {radius:.4g} >= 1); "
                "use discretization 'exact'"
            )
    return config


@dataclass(frozen=True)
class GustConfig(DisturbanceConfig):
    """The quadrotor's gust: a :class:`DisturbanceConfig` whose defaults are the gust's.

    Matern 3/2 (a gust spectrum is a low-order filtered noise), std 2.5 m/s^2 on the
    horizontal acceleration: 60% of the horizontal authority of a vehicle tilted to the
    0.4 rad bound (``g tan(0.4) = 4.1 m/s^2``), so one gust in ten exceeds it for a while.
    Lengthscale 2.5 s: predictable over the MPC's 1 s horizon once estimated (at 1 s the
    open-loop spread of the position, times the tunnel's slope, exceeded the tunnel's
    height and every scenario plan hovered at a crest). A partial ``disturbance:``
    section keeps these defaults for the keys it omits.
    """

    nu: float = 1.5  # Matern smoothness
    variance: float = 6.25  # sigma^2 [(m/s^2)^2], std 2.5 m/s^2
    lengthscale: float = 2.5  # [s]


@dataclass(frozen=True)
class QuadrotorGustConfig(WorldConfig):
    """The QuadrotorGust world: vehicle, attitude loop, tunnel, noise, gust, goal, limits.

    Vectors over the state ``[p_x, p_z, theta, v_x, v_z, omega]`` give the pitch in
    **degrees** and the pitch rate in **deg/s** for readability; the env converts to
    radians. The input bounds and ``R`` are in the inputs' units ``[N, rad]``.
    """

    ENV_ID = "lfm_env/QuadrotorGust-v0"
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
    disturbance: GustConfig = field(default_factory=GustConfig)

    def __post_init__(self) -> None:
        from lfm_env.worlds.quadrotor.system import attitude_euler_radius, attitude_frequency_bound

        c = _Checker(self)
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
        corridor = self.corridor
        inside = f"inside the tunnel (|p_z - centre_z(p_x)| <= {self.corridor_half_height} m)"
        gx, gz = self.goal
        c("goal", self.x_min <= gx <= self.x_max, f"inside x bounds [{self.x_min}, {self.x_max}]")
        c("goal", float(corridor.corridor_excess(gx, gz)) == 0.0, inside)
        x0, z0 = self.initial_state[:2]
        c(
            "initial_state",
            self.x_min <= x0 <= self.x_max and float(corridor.corridor_excess(x0, z0)) == 0.0,
            "a position inside the tunnel and the x bounds",
        )

    @property
    def corridor(self):
        """The tunnel geometry as a :class:`~lfm_env.worlds.quadrotor.system.Corridor`."""
        from lfm_env.worlds.quadrotor.system import Corridor

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
        from lfm_env.worlds.quadrotor.system import quadrotor_gust_system

        return quadrotor_gust_system(
            corridor=self.corridor,
            mass=self.mass,
            gravity=self.gravity,
            thrust_max=self.thrust_max,
            pitch_max=self.pitch_max,
            attitude_frequency=self.attitude_frequency,
            attitude_damping=self.attitude_damping,
        )


#: The worlds, by the Gymnasium id of their env: the name of their config class here.
WORLDS: dict[str, str] = {
    "lfm_env/SineTrack-v0": "EnvConfig",
    "lfm_env/QuadrotorGust-v0": "QuadrotorGustConfig",
}
DEFAULT_ENV_ID = "lfm_env/SineTrack-v0"


def world_config_class(env_id: Any) -> type:
    """The config class of the world whose env is ``env_id`` (a key of :data:`WORLDS`)."""
    if not isinstance(env_id, str) or env_id not in WORLDS:
        raise ConfigError(f"env_id={_show(env_id)}: must be one of {sorted(WORLDS)}")
    return globals()[WORLDS[env_id]]


def read_env_id(config: Any) -> Any:
    """The top-level ``env_id`` of a config (path or whole-file dict); ``None`` if absent."""
    if isinstance(config, (str, os.PathLike)):
        config = load_yaml(config)
    if isinstance(config, dict) and {_key(k) for k in config} & set(TOP_LEVEL_KEYS):
        read_section(config, "env")  # unknown top-level keys are an error
        return config.get("env_id")
    return None


def load_env_config(config: Any = None, env_id: str | None = None) -> WorldConfig:
    """A world config from a path, a dict (whole file or the ``env`` section), a world
    config, or ``None`` for the defaults.

    The world is the file's top-level ``env_id`` (default ``lfm_env/SineTrack-v0``, the
    paper's case study), or ``env_id`` when given (an env reading its own config); the two
    must agree.

    Raises:
        ConfigError: for an unknown ``env_id``, a file of another world, or a bad field.
    """
    if isinstance(config, WorldConfig):
        if env_id is not None and config.ENV_ID != env_id:
            raise ConfigError(f"a config of {config.ENV_ID!r} given to {env_id!r}")
        return config
    if isinstance(config, (str, os.PathLike)):
        config = load_yaml(config)
    file_id = read_env_id(config)
    if env_id is not None and file_id is not None and file_id != env_id:
        raise ConfigError(f"env_id={_show(file_id)}: the config is for another env than {env_id!r}")
    chosen = env_id if env_id is not None else file_id
    cls = world_config_class(DEFAULT_ENV_ID if chosen is None else chosen)
    return from_dict(cls, read_section(config, "env"), prefix="env")
