"""The worlds, one record each: the Gymnasium id, the config section and the env.

A world is a Gymnasium env (a :class:`~lfm_env.env.LatentForceEnv`) with an ``env:`` config
section (a :class:`~lfm_env.config.WorldConfig` dataclass). :func:`register_world` records
both under the env's id and registers the id with Gymnasium, so that ``gym.make(env_id)``,
:func:`load_env_config` and the experiment layer all find the world through this one record.
The built-in worlds register here from :mod:`lfm_env`; a world of your own registers the same
way from your own module.

Classes may be given as ``"module:Class"`` strings, imported on first use (as Gymnasium's
entry points are), so that registering a world imports none of its code.

**A world from your own module.** A config names a world registered outside the package
with Gymnasium's ``module:EnvId`` convention, ``env_id: mypkg.worlds:Mine/Unicycle-v0``:
the module is imported first (as ``gym.make`` does), which registers the world. The record
keeps the module that registered it (:attr:`WorldSpec.module`), so that a resolved config
(a results folder's ``config.yaml``) names it the same way and any process, a worker or a
later ``lfm-report``, finds the world again (:func:`qualified_env_id`).
"""

from __future__ import annotations

import dataclasses
import importlib
import os
import sys
from dataclasses import dataclass, replace
from typing import Any

import gymnasium as gym
from gymnasium.envs.registration import WrapperSpec

from lfm_env.config.loading import (
    ConfigError,
    annotation_problem,
    from_dict,
    load_yaml,
    show_value,
)
from lfm_env.config.presets import config_path
from lfm_env.validation import one_line
from lfm_env.working_folder import import_named

#: The world a config means when it names none: the paper's case study.
DEFAULT_ENV_ID = "lfm_env/SineTrack-v0"

# The registrations' outermost wrapper: the episode's length from the config's max_steps.
_CONFIG_TIME_LIMIT = WrapperSpec(
    name="ConfigTimeLimit", entry_point="lfm_env.wrappers:ConfigTimeLimit", kwargs={}
)


def _load(target: Any) -> Any:
    """A class given as itself or as ``"module:Class"`` (imported now)."""
    if not isinstance(target, str):
        return target
    module, _, name = target.partition(":")
    return getattr(importlib.import_module(module), name)


@dataclass(frozen=True)
class WorldSpec:
    """What the project knows of one world.

    Attributes:
        env_id: the Gymnasium id of its env, e.g. ``"lfm_env/SineTrack-v0"``.
        config: its ``env:`` section, a :class:`~lfm_env.config.WorldConfig` dataclass (or
            ``"module:Class"``).
        env: its env class, built as ``env(config=..., render_mode=...)`` (or
            ``"module:Class"``, Gymnasium's entry point).
        module: the module whose import registers the world (``None`` for the built-in
            worlds, which ``import lfm_env`` registers, and for a script's own): configs
            name the world ``module:env_id`` (:func:`qualified_env_id`).
    """

    env_id: str
    config: Any
    env: Any
    module: str | None = None

    @property
    def config_class(self) -> type:
        """The config dataclass (imported on first use, and then checked as
        :func:`register_world` checks a class)."""
        cls = _load(self.config)
        if isinstance(self.config, str):
            _check_config_class(cls, self.env_id)
        return cls

    @property
    def env_class(self) -> type:
        """The env class (imported on first use)."""
        return _load(self.env)


#: The registered worlds by env id, in registration order.
WORLDS: dict[str, WorldSpec] = {}


def _caller_module(depth: int = 2) -> str | None:
    """The importable module of the code that called the caller (``None`` for a script)."""
    try:
        name = sys._getframe(depth).f_globals.get("__name__")
    except ValueError:  # no such frame
        return None
    return None if name in (None, "__main__", "__mp_main__") else str(name)


def register_world(env_id: str, config: Any, env: Any, module: str | None = None) -> WorldSpec:
    """Register a world under ``env_id``, with Gymnasium too (``gym.make(env_id)``).

    The Gymnasium registration truncates episodes after the config's ``max_steps``
    (:class:`lfm_env.wrappers.ConfigTimeLimit`), unless ``gym.make(env_id,
    max_episode_steps=K)`` asks for another length. Call it at the top level of your own
    module; a config then names the world ``module:env_id`` (see the module docstring).

    Args:
        env_id: the id, ``"namespace/Name-vN"`` as Gymnasium's ids are (no ``:``).
        config: the ``env:`` section's dataclass (a :class:`WorldConfig`), or
            ``"module:Class"``.
        env: the env class, or ``"module:Class"``.
        module: the module whose import registers the world; by default the module that
            calls this function (none for a script run as ``__main__``, and none inside
            ``lfm_env``, which registers the built-in worlds on import).

    Returns:
        The world's record, also in :data:`WORLDS`.

    Raises:
        ValueError: for an id that is not a non-empty string, holds a ``:``, or is
            registered already to other classes; for a config class with a field that a
            config file cannot be read into (named ``Class.field``, e.g. one annotated with a
            bare ``tuple``: write ``tuple[float, ...]``).
    """
    if not isinstance(env_id, str) or not env_id.strip():
        raise ValueError(f"register_world: env_id={env_id!r} must be a non-empty string")
    if ":" in env_id:
        raise ValueError(
            f"register_world: env_id={env_id!r} must not hold ':' (configs write "
            "'module:env_id' to name the module that registers it)"
        )
    if module is None:
        module = _caller_module()
    if module is not None and (module == "lfm_env" or module.startswith("lfm_env.")):
        module = None  # the built-in worlds: import lfm_env registers them
    if not isinstance(config, str):
        _check_config_class(config, env_id)
    spec = WorldSpec(env_id, config, env, module)
    known = WORLDS.get(env_id)
    if known is not None and replace(known, module=None) != replace(spec, module=None):
        raise ValueError(f"register_world: {env_id!r} is registered already as {known}")
    if known is not None and spec.module is None:
        spec = known  # registered again (e.g. by a script): keep the module that did it first
    WORLDS[env_id] = spec
    gym.register(
        id=env_id,
        entry_point=env,
        max_episode_steps=None,  # the config's max_steps, through ConfigTimeLimit
        additional_wrappers=(_CONFIG_TIME_LIMIT,),
    )
    return spec


def _check_config_class(cls: Any, env_id: str) -> None:
    """Refuse a world's config class that a config file cannot be read into, naming the
    field (a bare ``tuple`` would run its episodes and then fail every reader of the folder's
    ``config.yaml``)."""
    if cls in _CHECKED:
        return
    if not (isinstance(cls, type) and dataclasses.is_dataclass(cls)):
        raise ValueError(
            f"register_world({env_id!r}): config={cls!r} must be a WorldConfig dataclass "
            "(or 'module:Class')"
        )
    problem = annotation_problem(cls)
    if problem is not None:
        raise ValueError(f"register_world({env_id!r}): {problem}")
    _CHECKED.add(cls)


_CHECKED: set[type] = set()  # config classes checked already


def import_world_module(module: str, env_id: str = "") -> None:
    """Import the module that registers a world (the ``module`` of ``module:EnvId``).

    As ``gym.make`` does, the module is imported as Python finds it; a module that Python
    does not find is looked for in the working folder too, by its name and last
    (:func:`lfm_env.working_folder.import_named`), so a ``mine.py`` beside the config works
    from a console script while a ``random.py`` there never shadows the real one.

    Raises:
        ConfigError: naming the env id and the module, when it cannot be imported.
    """
    what = f"env_id={show_value(f'{module}:{env_id}' if env_id else module)}"
    try:
        import_named(module)  # (the working folder too, last, and that module alone)
    except ConfigError:
        raise
    except Exception as exc:
        raise ConfigError(
            f"{what}: cannot import the module {module!r} ({one_line(exc)})"
        ) from None


def split_env_id(env_id: str) -> tuple[str | None, str]:
    """``"mypkg.worlds:Mine/Unicycle-v0"`` -> ``("mypkg.worlds", "Mine/Unicycle-v0")``;
    an id without a module -> ``(None, env_id)``."""
    module, sep, name = env_id.partition(":")
    return (module.strip(), name.strip()) if sep else (None, env_id)


def world_spec(env_id: Any) -> WorldSpec:
    """The record of the world ``env_id`` (``EnvId`` or ``module:EnvId``, the module imported
    first); a ConfigError listing the known ids otherwise."""
    if not isinstance(env_id, str):
        raise ConfigError(f"env_id={show_value(env_id)}: must be one of {sorted(WORLDS)}")
    module, name = split_env_id(env_id)
    if module:
        import_world_module(module, name)
        if name in WORLDS and WORLDS[name].module is None:
            # Registered by a script or directly: remember how this config named it.
            WORLDS[name] = replace(WORLDS[name], module=module)
    if name not in WORLDS:
        hint = (
            f" (importing {module!r} registered no world of that id)"
            if module
            else " (a world of your own: env_id: your.module:Name-v0 imports it first)"
        )
        raise ConfigError(f"env_id={show_value(env_id)}: must be one of {sorted(WORLDS)}{hint}")
    return WORLDS[name]


def qualified_env_id(env_id: str) -> str:
    """The id a config writes for a world: ``module:EnvId`` when a module of one's own
    registers it (:attr:`WorldSpec.module`), the plain id otherwise (the built-in worlds).

    Both ``gym.make`` and :func:`world_spec` take it, in any process."""
    module, name = split_env_id(env_id)
    spec = WORLDS.get(name)
    module = spec.module if spec is not None and spec.module else module
    return f"{module}:{name}" if module else name


def world_config_class(env_id: Any) -> type:
    """The config class of the world whose env is ``env_id``."""
    return world_spec(env_id).config_class


def env_id_of(config: Any) -> str:
    """The env id of the world a config (or config class) belongs to.

    Raises:
        ConfigError: when no registered world has that config class.
    """
    cls = config if isinstance(config, type) else type(config)
    for spec in WORLDS.values():
        if spec.config_class is cls:
            return spec.env_id
    raise ConfigError(f"{cls.__name__} is the config of no registered world (register_world)")


#: The keys of a whole config this layer reads: the world (``env_id``) and its section
#: (``env``). The rest of a whole config is read above this layer
#: (:func:`controllers.config.load_config`).
WORLD_KEYS = ("env_id", "env")


def _env_file(given: str | os.PathLike) -> dict:
    """The ``env_id`` and ``env`` of a config file (a preset's name or a path)."""
    data = load_yaml(config_path(given))
    if "base" in data:
        raise ConfigError(
            f"config {str(given)[:200]!r} inherits (base: {show_value(data['base'])}): a world "
            "reads one file's env section; read the whole file with "
            "controllers.config.load_config and pass its env (config=cfg.env)"
        )
    return {k: data[k] for k in WORLD_KEYS if k in data}


def _env_section(config: Any) -> tuple[Any, dict]:
    """``(env_id or None, the env section)`` of a config given as a file, a dict (a whole
    config: its ``env_id`` and ``env``; else the section itself), an object with an ``env``
    attribute (an experiment's config), or ``None``."""
    if config is None:
        return None, {}
    if isinstance(config, (str, os.PathLike)):
        config = _env_file(config)
    elif not isinstance(config, dict):
        raise ConfigError(
            f"config must be a world config, a dict, a preset's name or a path, got "
            f"{type(config).__name__}"
        )
    if "base" in config:
        raise ConfigError(
            "a config with base: is read whole by controllers.config.load_config; pass its "
            "env (config=cfg.env)"
        )
    if not any(k in config for k in WORLD_KEYS):
        return None, config  # the env section itself
    section = config.get("env")
    if section is None:
        section = {}
    if not isinstance(section, dict):
        raise ConfigError(f"config section 'env' must be a mapping, got {show_value(section)}")
    return config.get("env_id"), section


def _world_of(file_id: Any, env_id: str | None) -> str:
    """The plain id of the world a config means: the file's ``env_id`` (its module
    imported), else ``env_id``, else :data:`DEFAULT_ENV_ID`; the two must agree."""
    if file_id is not None:
        file_id = world_spec(file_id).env_id  # its module imported; the plain id
    if env_id is not None:
        env_id = split_env_id(env_id)[1]
    if env_id is not None and file_id is not None and file_id != env_id:
        raise ConfigError(
            f"env_id={show_value(file_id)}: the config is for another env than {env_id!r}"
        )
    chosen = env_id if env_id is not None else file_id
    return DEFAULT_ENV_ID if chosen is None else chosen


def load_env_config(config: Any = None, env_id: str | None = None) -> Any:
    """A world's config (its ``env:`` section, a :class:`~lfm_env.config.WorldConfig`) from
    a world config, a dict of its fields, a whole config (a dict, a preset's name or a path
    such as ``"quadrotor"`` or ``"my/config.yaml"``: its ``env_id`` and ``env`` are read, the
    other sections left to the layers above), an object with an ``env`` attribute, or
    ``None`` for the world's defaults.

    The world is the config's top-level ``env_id`` (default :data:`DEFAULT_ENV_ID`, the
    paper's case study; ``module:EnvId`` imports the module first), or ``env_id`` when given
    (an env reading its own config); the two must agree. A file that inherits from another
    (``base:``) is read whole by :func:`controllers.config.load_config`, not here.

    Raises:
        ConfigError: for an unknown ``env_id``, a config of another world, or a bad field.
    """
    own = getattr(config, "env", None)
    if own is not None and not isinstance(config, dict) and dataclasses.is_dataclass(own):
        config = own  # an experiment's config: its world
    if dataclasses.is_dataclass(config) and not isinstance(config, type):
        world = env_id_of(config)
        if env_id is not None and world != split_env_id(env_id)[1]:
            raise ConfigError(f"a config of {world!r} given to {env_id!r}")
        return config
    file_id, section = _env_section(config)
    cls = world_config_class(_world_of(file_id, env_id))
    return from_dict(cls, section, prefix="env")


__all__ = [
    "DEFAULT_ENV_ID",
    "WORLDS",
    "WorldSpec",
    "env_id_of",
    "import_world_module",
    "load_env_config",
    "qualified_env_id",
    "register_world",
    "split_env_id",
    "world_config_class",
    "world_spec",
]
