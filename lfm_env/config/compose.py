"""Where a config comes from, and configs that compose: presets by name, ``base:`` and settings.

Every function that takes a config (``load_env_config``, ``gym.make(..., config=...)``,
``controllers.config.load_config``, ``make_agent``, ``evaluate``, the commands' ``--config``)
resolves it here, the same way:

* **a preset's name or a path** (:func:`config_path`): a path that names an existing file
  wins; otherwise a name (``paper``, ``quick``, ``quadrotor``, ``matlab_reference``, with or
  without ``.yaml``) is one of the presets shipped in the package ``lfm_env.presets`` (the
  repository's ``configs/`` folder), found from any folder;
* **inheritance** (:func:`read_config`): a file (or dict) with a top-level ``base:`` takes
  every value of its base (a preset's name, or a path relative to the file's folder) and
  overrides some: mappings are merged key by key, any other value (a list, a number, a
  text) replaces the base's. A base may have a base; a cycle is an error;
* **settings** (:func:`apply_settings`): ``KEY=VALUE`` texts (``lfm-evaluate --set``) with a
  dotted key (``agents.horizon=10``, ``env.latent_force.variance=2.0``, ``env_id=...``),
  each value read by its field's type (``1e-3`` is a number, ``[1, 2]`` a list, ``null``
  where allowed).

Unknown keys and values of the wrong type stay one-line errors naming the field: the
result is plain data, read by :func:`~lfm_env.config.loading.from_dict` as any file is.
"""

from __future__ import annotations

import copy
import dataclasses
import os
import re
import types
import typing
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import yaml

from lfm_env.config.loading import (
    TOP_LEVEL_KEYS,
    ConfigError,
    load_yaml,
    show_value,
)

#: The package the presets ship in (the repository's ``configs/`` folder, mapped in
#: ``pyproject.toml``), read with ``importlib.resources``.
PRESETS_PACKAGE = "lfm_env.presets"
#: The preset a command uses when none is given.
DEFAULT_PRESET = "paper"
#: The top-level key naming the config a file inherits from.
BASE_KEY = "base"
#: Longest chain of ``base:`` files (a longer one is a mistake, not a plan).
MAX_BASE_DEPTH = 20


# --------------------------------------------------------------------------- presets


def presets_folder() -> Path:
    """The folder of the presets: the installed package's, else a checkout's ``configs/``.

    A wheel ships ``configs/`` as the package :data:`PRESETS_PACKAGE`; an editable install
    maps it there too. A source tree used without installing it (``PYTHONPATH=.``) has no
    such package, and its ``configs/`` folder beside ``lfm_env/`` is used instead.
    """
    from importlib import resources

    try:
        return Path(str(resources.files(PRESETS_PACKAGE)))
    except ModuleNotFoundError:
        return Path(__file__).resolve().parents[2] / "configs"


def preset_names() -> list[str]:
    """The names of the shipped presets (``paper``, ``quick``, ``quadrotor``, ...), sorted."""
    return sorted(p.stem for p in presets_folder().glob("*.yaml"))


def preset_path(name: str) -> Path | None:
    """The file of the preset ``name`` (with or without ``.yaml``), or ``None``."""
    stem = name[: -len(".yaml")] if name.endswith(".yaml") else name
    if "/" in stem or "\\" in stem or stem not in preset_names():
        return None
    return presets_folder() / f"{stem}.yaml"


def config_path(given: str | os.PathLike | None, folder: str | os.PathLike | None = None) -> Path:
    """The file a config is read from: a path to a YAML file, or a preset's name.

    A path that names an existing file wins (relative to ``folder`` when given, else to
    the working folder); otherwise ``given`` is looked up among the presets
    (:func:`preset_names`), from any folder.

    Args:
        given: a path or a preset's name; ``None`` for :data:`DEFAULT_PRESET`.
        folder: the folder a relative path is relative to (a ``base:``'s file's folder).

    Raises:
        ConfigError: naming ``given`` and the presets, if it is neither.
    """
    if given is None:
        given = DEFAULT_PRESET
    path = Path(given)
    located = path if folder is None or path.is_absolute() else Path(folder) / path
    if located.is_file():
        return located
    preset = preset_path(path.name) if path.parent == Path(".") else None
    if preset is not None:
        return preset
    problem = "is not a file" if located.exists() else "does not exist"
    raise ConfigError(
        f"config {str(given)[:200]!r}: {problem} and names no preset; presets: "
        f"{', '.join(preset_names())} (or a path to a YAML file)"
    )


# --------------------------------------------------------------------------- base: inheritance


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


def _with_base(data: dict, folder: Path | None, chain: tuple[str, ...]) -> dict:
    """``data`` merged onto its ``base:`` (recursively); ``data`` itself without one."""
    if BASE_KEY not in data:
        return data
    given = data[BASE_KEY]
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
    parent = _with_base(load_yaml(path), path.parent, chain + (key,))
    child = {k: v for k, v in data.items() if k != BASE_KEY}
    _check_top_level(parent, str(path))
    return merge(parent, child)


def _check_top_level(data: dict, where: str) -> None:
    """A whole file's keys must be top-level keys (a section alone cannot inherit)."""
    unknown = sorted(str(k) for k in data if k not in TOP_LEVEL_KEYS)
    if unknown:
        raise ConfigError(
            f"{where}: unknown top-level config section(s) {unknown}; allowed: "
            f"{sorted(TOP_LEVEL_KEYS)}"
        )


def read_config(source: Any = None, settings: Sequence[Any] = ()) -> Any:
    """The plain data of a config, its ``base:`` resolved and ``settings`` applied.

    Args:
        source: a preset's name or a path (:func:`config_path`), a dict (a whole file, or
            one section), or ``None`` (no file: the defaults). Anything else (a config
            dataclass) is returned as it is.
        settings: ``KEY=VALUE`` texts (or ``(key, text)`` pairs) for
            :func:`apply_settings`; they need a whole file (or ``None``).

    Returns:
        A dict (the whole file without ``base``, or the section given), ``None`` for
        ``None`` without settings, or ``source`` itself when it is not plain data.

    Raises:
        ConfigError: for a missing file or preset, a bad ``base:`` or a bad setting.
    """
    if isinstance(source, (str, os.PathLike)):
        path = config_path(source)
        data = _with_base(load_yaml(path), path.parent, (str(path.resolve()),))
    elif isinstance(source, dict):
        data = _with_base(dict(source), None, ()) if BASE_KEY in source else source
    elif source is None:
        data = None
    else:
        return source
    if settings:
        data = apply_settings({} if data is None else data, settings)
    return data


# --------------------------------------------------------------------------- settings


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
    if tp is int:
        return int(text) if re.fullmatch(r"[+-]?\d+", text) else text
    if tp is float:
        try:
            return float(text)
        except ValueError:
            return text
    if typing.get_origin(tp) is tuple:
        args = typing.get_args(tp)
        if text.startswith("[") and text.endswith("]"):
            inner = text[1:-1].strip()
            items = split_values(inner) if inner else []
        else:
            items = [text]
        if len(args) == 2 and args[1] is Ellipsis:
            return [parse_value(i, args[0]) for i in items]
        return [parse_value(i, a) for i, a in zip(items, args, strict=False)] + items[len(args) :]
    try:
        return yaml.safe_load(text)
    except yaml.YAMLError:
        return text


def split_setting(setting: Any) -> tuple[str, str]:
    """``"KEY=VALUE"`` (or a ``(key, value)`` pair) as ``(key, value text)``.

    Raises:
        ConfigError: for a text without ``=`` or with an empty key.
    """
    if isinstance(setting, tuple) and len(setting) == 2:
        key, text = str(setting[0]).strip(), str(setting[1])
    else:
        key, sep, text = str(setting).partition("=")
        key = key.strip()
        if not sep or not key:
            raise ConfigError(
                f"--set {str(setting)[:200]!r}: expected KEY=VALUE, e.g. agents.horizon=10 or "
                "env.latent_force.variance=2.0"
            )
    return key, text


#: The dataclass of a section other than ``env`` (whose class is the config's world's):
#: ``controllers.config`` registers ``agents`` -> ``AgentConfig`` here (this layer cannot
#: import it). A section without a registered type takes its values as YAML reads them.
SECTION_TYPES: dict[str, type] = {}


def _world_class(data: dict) -> type:
    from lfm_env.worlds.registry import DEFAULT_ENV_ID, world_config_class

    env_id = data.get("env_id")
    return world_config_class(DEFAULT_ENV_ID if env_id is None else env_id)


def _set_one(data: dict, key: str, text: str) -> None:
    """Set the dotted ``key`` of ``data`` (a whole file) to ``text`` read by its field's type."""
    parts = key.split(".")
    top = parts[0]
    if top not in TOP_LEVEL_KEYS or not all(parts):
        raise ConfigError(
            f"--set {key}: the key must start with one of {sorted(TOP_LEVEL_KEYS)[::-1]} "
            "(e.g. agents.horizon, env.latent_force.variance, env_id)"
        )
    if top == "env_id":
        if len(parts) > 1:
            raise ConfigError(f"--set {key}: env_id is a value, not a section")
        data["env_id"] = text.strip()
        return
    if len(parts) == 1:
        raise ConfigError(f"--set {key}: {key} is a section; set one of its keys ({key}.KEY=...)")
    cls = _world_class(data) if top == "env" else SECTION_TYPES.get(top)
    node = data.setdefault(top, {})
    if not isinstance(node, dict):
        raise ConfigError(f"--set {key}: the config's {top} section is not a mapping")
    for depth, name in enumerate(parts[1:], start=1):
        where = ".".join(parts[:depth])
        tp = None
        if cls is not None:
            fields = field_types(cls)
            if name not in fields:
                raise ConfigError(
                    f"--set {key}: {where} has no key {name!r}; its keys are {sorted(fields)}"
                )
            tp, _ = optional_type(fields[name])
        if depth == len(parts) - 1:
            if tp is not None and dataclasses.is_dataclass(tp):
                raise ConfigError(
                    f"--set {key}: {key} is a section; set one of its keys "
                    f"{sorted(field_types(tp))}"
                )
            node[name] = parse_value(text, fields[name]) if tp is not None else _yaml(text)
            return
        if tp is not None and not dataclasses.is_dataclass(tp):
            raise ConfigError(f"--set {key}: {where}.{name} is a value, not a section")
        if not isinstance(node.get(name), dict):
            node[name] = {}
        node, cls = node[name], tp


def _yaml(text: str) -> Any:
    try:
        return yaml.safe_load(text)
    except yaml.YAMLError:
        return text


def apply_settings(data: Mapping, settings: Sequence[Any]) -> dict:
    """A copy of ``data`` (a whole config) with each ``KEY=VALUE`` of ``settings`` set.

    ``KEY`` is dotted from the top level: ``env_id``, ``env.<field>[.<field>]`` (the
    fields of the config's world, after an ``env_id`` setting), ``agents.<field>...``.
    Each value is read by its field's type (:func:`parse_value`); later settings win.

    Raises:
        ConfigError: naming the key, for a malformed setting, an unknown key, or a section
            given where a value is expected (the values themselves are checked when the
            config is built, naming the field).
    """
    out = copy.deepcopy(dict(data))
    if out and not any(k in TOP_LEVEL_KEYS for k in out):
        raise ConfigError("--set needs a whole config (env_id, env, agents), not one section")
    pairs = [split_setting(s) for s in settings]
    # env_id first: the env section's keys are the fields of the world it names.
    for key, text in sorted(pairs, key=lambda p: p[0] != "env_id"):
        _set_one(out, key, text)
    return out


__all__ = [
    "BASE_KEY",
    "DEFAULT_PRESET",
    "PRESETS_PACKAGE",
    "SECTION_TYPES",
    "apply_settings",
    "config_path",
    "field_types",
    "merge",
    "optional_type",
    "parse_value",
    "preset_names",
    "preset_path",
    "presets_folder",
    "read_config",
    "split_setting",
    "split_values",
]
