"""A whole config: reading it (presets by name, ``base:``, ``--set``, the top-level keys) and
its typed form, :class:`ExperimentConfig`.

A config file has a top-level ``env_id`` (the world), an ``env:`` section (the world's own,
read by :func:`lfm_env.worlds.registry.load_env_config`), an ``agents:`` section and an
``evaluation:`` section (:mod:`controllers.config.sections`). This module is where a whole
config is read, the same way for every caller:

* **a preset's name or a path** (:func:`lfm_env.config.presets.config_path`): a path that
  names an existing file wins; otherwise a name (``paper``, ``quick``, ``quadrotor``,
  ``matlab_reference``, with or without ``.yaml``) is one of the presets shipped in the
  package ``lfm_env.presets`` (the repository's ``configs/`` folder), found from any folder;
* **inheritance**: a file (or dict) with a top-level ``base:`` takes every value of its base
  (a preset's name, or a path relative to the file's folder) and overrides some: mappings
  are merged key by key, any other value (a list, a number, a text) replaces the base's. A
  base may have a base; a cycle is an error;
* **overrides** (:func:`apply_overrides`): ``KEY=VALUE`` texts (``lfm-evaluate --set``) with a
  dotted key (``agents.horizon=10``, ``env.latent_force.variance=2.0``, ``env_id=...``),
  each value read by its field's type (``1e-3`` is a number, ``[1, 2]`` a list, ``null``
  where allowed).

:func:`load_config` is the resolver: the commands and the public functions that take a
config (``make_agent``, ``evaluate``, ...) call it once, and everything below them takes the
:class:`ExperimentConfig` it returns. Unknown keys and values of the wrong type are one-line
errors naming the field.
"""

from __future__ import annotations

import copy
import dataclasses
import os
import re
import types
import typing
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from controllers.config.sections import (
    AgentConfig,
    EvaluationConfig,
    check_filter_memory,
    check_problem_memory,
)
from lfm_env.config import (
    ConfigError,
    WorldConfig,
    check_latent_step,
    config_path,
    from_dict,
    load_yaml,
    preset_names,
    show_value,
    to_dict,
)
from lfm_env.worlds.registry import (
    DEFAULT_ENV_ID,
    load_env_config,
    qualified_env_id,
    world_config_class,
)


@dataclass(frozen=True)
class ExperimentConfig:
    """A whole config (``env_id``, ``env`` and ``agents``), resolved and validated once.

    ``env`` is the world's config (the paper's sine track by default, or another world's,
    chosen by the file's top-level ``env_id``: :mod:`lfm_env.worlds.registry`). The builders
    below are what every agent, solver benchmark and worker process uses, so a config file is
    read and checked in one place; the object pickles, so workers get it instead of a path or a
    dict to parse again.
    """

    env: WorldConfig = field(default_factory=lambda: load_env_config(None))  # default world
    agents: AgentConfig = field(default_factory=AgentConfig)
    # How an evaluation runs (not part of to_dict, nor of equality: see EvaluationConfig).
    evaluation: EvaluationConfig = field(default_factory=EvaluationConfig, compare=False)

    @property
    def env_id(self) -> str:
        """The Gymnasium id of the world's env (``gym.make(cfg.env_id, config=cfg.env)``):
        ``module:EnvId`` for a world registered by a module of one's own, so that any
        process (a worker, a later report) imports the module and finds the world."""
        return qualified_env_id(self.env.ENV_ID)

    def to_dict(self) -> dict:
        """Plain, YAML-ready data that :func:`load_config` reads back to an equal config
        (``env_id``, ``env`` and ``agents``; the ``evaluation`` run settings are left out)."""
        data = {"env_id": self.env_id, **to_dict(self)}
        data.pop("evaluation", None)
        return data

    def __post_init__(self) -> None:
        object.__setattr__(self, "agents", _with_world_cost(self.env, self.agents))
        check_latent_step(self.env)
        if self.agents.latent_force is not None:
            check_latent_step(self.env, self.agents.latent_force, where="agents.latent_force")
        self.make_cost()  # the cost's own checks of its weights and goal
        system = self.make_system()
        self.agents.check_scenario_count(system.nu)
        model = self.make_model()
        a = self.agents
        # Memory up front, for the largest problem and each filter any agent builds.
        r = a.robust
        robust_ns = 1 if r.forecast == "mean" else (r.n_scenarios or self.scenario_count())
        check_problem_memory(model, a.horizon, max(self.scenario_count(), robust_ns))
        check_filter_memory(model, a.n_particles, a.estimator)
        check_filter_memory(model, r.n_particles, r.estimator, "agents.robust.n_particles")
        groups = list(system.constraint_groups)
        for name, k in (
            ("backoff", self.agents.backoff),
            ("robust.backoff", self.agents.robust.backoff),
        ):
            if len(k) not in (1, len(groups)):
                raise ConfigError(
                    f"agents.{name}={list(k)}: must be one number or {len(groups)}, one per "
                    f"constraint group {groups} of the {system.name} system"
                )

    def make_system(self):
        """The controlled system (:class:`~lfm_env.system.ControlSystem`) of the env section."""
        return self.env.make_system()

    def make_model(self):
        """The agents' model: the env's system with the agents' belief about the force.

        ``agents.latent_force`` when set (e.g. learned by ``lfm-calibrate``), otherwise the
        env's own latent force, known a priori as in the paper.
        """
        return self.env.make_model(self.agents.latent_force)

    def make_cost(self):
        """The agents' :class:`~lfm_env.cost.QuadraticCost` (``Q``, ``R``, ``Qf``, goal)."""
        from lfm_env.cost import QuadraticCost

        a = self.agents
        return QuadraticCost(Q=a.Q, R=a.R, Qf=a.Qf, x_goal=self.env.state_from_config(a.goal_state))

    @property
    def measurement_std(self) -> np.ndarray:
        """Std of the full-state measurement noise, in SI units (the filter's likelihood)."""
        return self.env.measurement_std_rad

    def scenario_count(self) -> int:
        """The scenario count ``Ns`` of the scenario agents (explicit or Campi-Garatti)."""
        return self.agents.scenario_count(self.make_system().nu)

    def make_problem(
        self,
        n_scenarios: int | None = None,
        horizon: int | None = None,
        prediction: str | None = None,
    ):
        """The scenario problem of the agents' model and cost.

        Args:
            n_scenarios: ``Ns``; ``None`` for :meth:`scenario_count`.
            horizon: ``N``; ``None`` for ``agents.horizon``.
            prediction: ``"open_loop"`` or ``"feedback"``; ``None`` for ``agents.prediction``.
        """
        from controllers.problem import ScenarioProblem

        return ScenarioProblem(
            self.make_model(),
            self.make_cost(),
            horizon=self.agents.horizon if horizon is None else int(horizon),
            n_scenarios=self.scenario_count() if n_scenarios is None else int(n_scenarios),
            slack_penalty=self.agents.slack_penalty,
            prediction=self.agents.prediction if prediction is None else prediction,
        )


def _with_world_cost(env: WorldConfig, agents: AgentConfig) -> AgentConfig:
    """``agents`` with its cost resolved: ``Q``, ``R``, ``goal_state`` not given are the world's
    own (``env.Q``, ...), ``Qf`` not given is ``Q``; every vector as long as the world's.

    Raises:
        ConfigError: naming the ``agents`` field and the world's dimension (and its ``env``
            field), for a vector of another length.
    """
    system = env.make_system()
    nx, nu = len(system.state_names), len(system.input_names)
    world = {"Q": env.Q, "R": env.R, "goal_state": env.goal_state}
    values = {k: w if getattr(agents, k) is None else getattr(agents, k) for k, w in world.items()}
    values["Qf"] = values["Q"] if agents.Qf is None else agents.Qf
    for name, n, what, names in (
        ("Q", nx, "states", system.state_names),
        ("Qf", nx, "states", system.state_names),
        ("goal_state", nx, "states", system.state_names),
        ("R", nu, "inputs", system.input_names),
    ):
        value = values[name]
        if len(value) != n:
            own = "Q" if name == "Qf" else name
            raise ConfigError(
                f"agents.{name}={list(value)}: has {len(value)} values, but the world "
                f"{env.ENV_ID!r} (system {system.name!r}) has {n} {what} {list(names)}, as its "
                f"env.{own}={list(world[own])}; give {n} values, or leave agents.{name} out for "
                "the world's own"
            )
    if all(getattr(agents, k) == v for k, v in values.items()):
        return agents
    return dataclasses.replace(agents, **values)


# --------------------------------------------------------------------------- reading a file

#: The top level of a config file: the world (``env_id``, ``env``), the agents' settings
#: (``agents``) and how an evaluation runs (``evaluation``); ``base:`` names a config it
#: inherits from.
TOP_LEVEL_KEYS = ("env_id", "env", "agents", "evaluation")
#: The dataclass of each section other than ``env`` (whose class is the config's world's).
SECTIONS: dict[str, type] = {"agents": AgentConfig, "evaluation": EvaluationConfig}
#: The preset a command uses when none is given.
DEFAULT_PRESET = "paper"
#: The top-level key naming the config a file inherits from.
BASE_KEY = "base"
#: Longest chain of ``base:`` files (a longer one is a mistake, not a plan).
MAX_BASE_DEPTH = 20


def merge(base: Mapping, override: Mapping) -> dict:
    """``base`` updated by ``override``: mappings merged key by key (recursively), any other
    value of ``override`` (a list, a number, a text, ``null``) replacing the base's."""
    out = copy.deepcopy(dict(base))
    for key, value in override.items():
        if isinstance(value, Mapping) and isinstance(out.get(key), Mapping):
            out[key] = merge(out[key], value)
        else:
            out[key] = copy.deepcopy(value)
    return out


def _base_file(given: Any, folder: Path | None, chain: tuple[str, ...]) -> Path:
    """The file a ``base:`` names (a preset's name, or a path relative to ``folder``)."""
    where = f" (in {chain[-1]})" if chain else ""
    if not isinstance(given, str) or not given.strip():
        raise ConfigError(
            f"base={show_value(given)}{where}: must be a preset's name "
            f"({', '.join(preset_names())}) or a path to a YAML file"
        )
    try:
        path = config_path(given, folder)
    except ConfigError as exc:
        raise ConfigError(f"base: {exc}{where}") from None
    key = str(path.resolve())
    if key in chain:
        raise ConfigError(f"base: {given!r} inherits from itself: {' -> '.join(chain + (key,))}")
    if len(chain) >= MAX_BASE_DEPTH:
        raise ConfigError(f"base: more than {MAX_BASE_DEPTH} configs inherit one from another")
    return path


def _with_base(data: dict, folder: Path | None, chain: tuple[str, ...]) -> dict:
    """``data`` merged onto its ``base:`` (recursively); ``data`` itself without one."""
    if BASE_KEY not in data:
        return data
    path = _base_file(data[BASE_KEY], folder, chain)
    parent = _with_base(load_yaml(path), path.parent, chain + (str(path.resolve()),))
    child = {k: v for k, v in data.items() if k != BASE_KEY}
    _check_top_level(parent, str(path))
    return merge(parent, child)


def _check_top_level(data: dict, where: str) -> None:
    """A whole config's keys must be top-level keys (:data:`TOP_LEVEL_KEYS`)."""
    unknown = sorted(show_value(k) if not isinstance(k, str) else k for k in data)
    unknown = [k for k in unknown if k not in TOP_LEVEL_KEYS]
    if unknown:
        raise ConfigError(
            f"{where}unknown top-level config section(s) {unknown}; allowed: "
            f"{sorted(TOP_LEVEL_KEYS)}"
        )
    for name in ("env", *SECTIONS):
        if data.get(name) is not None and not isinstance(data[name], dict):
            raise ConfigError(f"config section {name!r} must be a mapping")


def read_document(source: Any = None, overrides: Sequence[Any] = ()) -> dict:
    """The plain data of a whole config, its ``base:`` resolved and ``overrides`` applied.

    Args:
        source: a preset's name or a path (:func:`~lfm_env.config.presets.config_path`), a
            dict (a whole config), or ``None`` (no file: the defaults).
        overrides: ``KEY=VALUE`` texts (or ``(key, text)`` pairs) for :func:`apply_overrides`.

    Raises:
        ConfigError: for a missing file or preset, a bad ``base:``, an unknown top-level
            key or a bad override.
    """
    if isinstance(source, (str, os.PathLike)):
        path = config_path(source)
        data = _with_base(load_yaml(path), path.parent, (str(path.resolve()),))
        _check_top_level(data, f"{path}: ")
    elif isinstance(source, dict):
        data = _with_base(dict(source), None, ())
        _check_top_level(data, "")
    elif source is None:
        data = {}
    else:
        raise ConfigError(
            "config must be a preset's name, a path, a dict or an ExperimentConfig, got "
            f"{type(source).__name__}"
        )
    return apply_overrides(data, overrides) if overrides else data


def load_config(config: Any = None, overrides: Sequence[Any] = ()) -> ExperimentConfig:
    """The resolver: an :class:`ExperimentConfig` from a preset's name (``"paper"``,
    ``"quick"``, ...), a YAML path, a dict (a whole config: ``env_id``, ``env``, ``agents``,
    ``evaluation``), an ``ExperimentConfig`` (returned as it is without overrides), or
    ``None`` (the defaults: the paper's values).

    A file (or dict) may inherit from another with ``base:``, and ``overrides`` (``KEY=VALUE``
    texts, as ``lfm-evaluate --set``) override single fields. The commands and the public
    functions that take a config call this once; everything below takes the result.

    Raises:
        ConfigError: naming the first bad field (``env.dt``, ``agents.Q``, ...).
    """
    if isinstance(config, ExperimentConfig):
        if not overrides:
            return config
        evaluation = config.evaluation  # (not in to_dict: a run setting)
        data = read_document(config.to_dict(), overrides)
        return _experiment(data, evaluation)
    return _experiment(read_document(config, overrides))


def _experiment(data: dict, evaluation: EvaluationConfig | None = None) -> ExperimentConfig:
    """The typed config of a whole config's plain data (:func:`read_document`)."""
    if evaluation is None:
        evaluation = from_dict(EvaluationConfig, data.get("evaluation"), prefix="evaluation")
    world = {"env_id": data.get("env_id"), "env": data.get("env")}  # the world's part
    return ExperimentConfig(
        env=load_env_config(world),
        agents=from_dict(AgentConfig, data.get("agents"), prefix="agents"),
        evaluation=evaluation,
    )


# --------------------------------------------------------------------------- overrides (--set)


def split_values(text: str) -> list[str]:
    """Comma-separated values, commas inside brackets kept: ``"0,[1,2]"`` -> ``["0", "[1,2]"]``."""
    values, depth, current = [], 0, []
    for ch in text:
        depth += {"[": 1, "]": -1}.get(ch, 0)
        if ch == "," and depth == 0:
            values.append("".join(current).strip())
            current = []
        else:
            current.append(ch)
    values.append("".join(current).strip())
    return values


def field_types(obj: Any) -> dict[str, Any]:
    """The annotated types of a config dataclass's (or instance's) init fields."""
    cls = obj if isinstance(obj, type) else type(obj)
    hints = typing.get_type_hints(cls)
    return {f.name: hints[f.name] for f in dataclasses.fields(cls) if f.init}


def optional_type(tp: Any) -> tuple[Any, bool]:
    """``(inner type, whether None is allowed)`` of ``X | None``; other types unchanged."""
    if typing.get_origin(tp) in (typing.Union, types.UnionType):
        inner = [a for a in typing.get_args(tp) if a is not type(None)]
        return inner[0], len(inner) < len(typing.get_args(tp))
    return tp, False


def _yaml(text: str) -> Any:
    try:
        return yaml.safe_load(text)
    except yaml.YAMLError:
        return text


def _parse_number(text: str, tp: type) -> Any:
    if tp is int:
        return int(text) if re.fullmatch(r"[+-]?\d+", text) else text
    try:
        return float(text)
    except ValueError:
        return text


def _parse_list(text: str, args: tuple) -> list:
    if text.startswith("[") and text.endswith("]"):
        inner = text[1:-1].strip()
        items = split_values(inner) if inner else []
    else:
        items = [text]
    if len(args) == 2 and args[1] is Ellipsis:
        return [parse_value(i, args[0]) for i in items]
    return [parse_value(i, a) for i, a in zip(items, args, strict=False)] + items[len(args) :]


def parse_value(text: str, tp: Any) -> Any:
    """A value given on the command line, read as the config field's type ``tp`` reads it.

    Strings stay as written; numbers are read as numbers (``1e-3`` too); a list field
    takes ``[a, b]`` or one value, which becomes a list of one; ``null`` (or ``none``,
    ``~``) is ``None`` where the field allows it. What does not parse is passed on as
    text, so the config's own check names the key.
    """
    tp, nullable = optional_type(tp)
    if nullable and text.strip().lower() in ("null", "none", "~"):
        return None
    text = text.strip()
    if tp is str:
        return text
    if tp in (int, float):
        return _parse_number(text, tp)
    if typing.get_origin(tp) is tuple:
        return _parse_list(text, typing.get_args(tp))
    return _yaml(text)


def split_override(override: Any) -> tuple[str, str]:
    """``"KEY=VALUE"`` (or a ``(key, value)`` pair) as ``(key, value text)``.

    Raises:
        ConfigError: for a text without ``=`` or with an empty key.
    """
    if isinstance(override, tuple) and len(override) == 2:
        key, text = str(override[0]).strip(), str(override[1])
    else:
        key, sep, text = str(override).partition("=")
        key = key.strip()
        if not sep or not key:
            raise ConfigError(
                f"--set {str(override)[:200]!r}: expected KEY=VALUE, e.g. agents.horizon=10 or "
                "env.latent_force.variance=2.0"
            )
    return key, text


def _section_class(data: dict, top: str) -> type:
    """The dataclass of the section ``top`` of the config ``data``."""
    if top == "env":
        env_id = data.get("env_id")
        return world_config_class(DEFAULT_ENV_ID if env_id is None else env_id)
    return SECTIONS[top]


def _check_override_key(key: str, parts: list[str]) -> None:
    """An override's key starts with a top-level key, and names a value of a section."""
    top = parts[0]
    if top not in TOP_LEVEL_KEYS or not all(parts):
        raise ConfigError(
            f"--set {key}: the key must start with one of {sorted(TOP_LEVEL_KEYS)[::-1]} "
            "(e.g. agents.horizon, env.latent_force.variance, env_id)"
        )
    if top == "env_id" and len(parts) > 1:
        raise ConfigError(f"--set {key}: env_id is a value, not a section")
    if top != "env_id" and len(parts) == 1:
        raise ConfigError(f"--set {key}: {key} is a section; set one of its keys ({key}.KEY=...)")


def _field_type(key: str, parts: list[str], depth: int, cls: type) -> Any:
    """The type of the field ``parts[depth]`` of the section class ``cls``."""
    fields = field_types(cls)
    name = parts[depth]
    if name not in fields:
        where = ".".join(parts[:depth])
        raise ConfigError(
            f"--set {key}: {where} has no key {name!r}; its keys are {sorted(fields)}"
        )
    return fields[name]


def _set_one(data: dict, key: str, text: str) -> None:
    """Set the dotted ``key`` of ``data`` (a whole config) to ``text`` read by its field's type."""
    parts = key.split(".")
    _check_override_key(key, parts)
    if parts[0] == "env_id":
        data["env_id"] = text.strip()
        return
    cls = _section_class(data, parts[0])
    node = data.setdefault(parts[0], {})
    if not isinstance(node, dict):
        raise ConfigError(f"--set {key}: the config's {parts[0]} section is not a mapping")
    for depth in range(1, len(parts) - 1):
        tp, _ = optional_type(_field_type(key, parts, depth, cls))
        if not dataclasses.is_dataclass(tp):
            raise ConfigError(
                f"--set {key}: {'.'.join(parts[: depth + 1])} is a value, not a section"
            )
        if not isinstance(node.get(parts[depth]), dict):
            node[parts[depth]] = {}
        node, cls = node[parts[depth]], tp
    field = _field_type(key, parts, len(parts) - 1, cls)
    if dataclasses.is_dataclass(optional_type(field)[0]):
        raise ConfigError(
            f"--set {key}: {key} is a section; set one of its keys "
            f"{sorted(field_types(optional_type(field)[0]))}"
        )
    node[parts[-1]] = parse_value(text, field)


def apply_overrides(data: Mapping, overrides: Sequence[Any]) -> dict:
    """A copy of ``data`` (a whole config) with each ``KEY=VALUE`` of ``overrides`` set.

    ``KEY`` is dotted from the top level: ``env_id``, ``env.<field>[.<field>]`` (the
    fields of the config's world, after an ``env_id`` override), ``agents.<field>...``,
    ``evaluation.<field>``. Each value is read by its field's type (:func:`parse_value`);
    later overrides win.

    Raises:
        ConfigError: naming the key, for a malformed override, an unknown key, or a section
            given where a value is expected (the values themselves are checked when the
            config is built, naming the field).
    """
    out = copy.deepcopy(dict(data))
    pairs = [split_override(s) for s in overrides]
    # env_id first: the env section's keys are the fields of the world it names.
    for key, text in sorted(pairs, key=lambda p: p[0] != "env_id"):
        _set_one(out, key, text)
    return out


__all__ = [
    "DEFAULT_PRESET",
    "TOP_LEVEL_KEYS",
    "ExperimentConfig",
    "apply_overrides",
    "load_config",
    "merge",
    "parse_value",
    "read_document",
]
