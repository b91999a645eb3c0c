"""The worlds, one record each: the Gymnasium id, the config section and the env.

A world is a Gymnasium env (a :class:`~lfm_env.env.LatentForceEnv`) with an ``env:`` config
section (a :class:`~lfm_env.config.WorldConfig` dataclass). :func:`register_world` records
both under the env's id and registers the id with Gymnasium, so that ``gym.make(env_id)``,
:func:`load_env_config` and the experiment layer all find the world through this one record.
The built-in worlds register here from :mod:`lfm_env`; a world of your own registers the same
way from your own module.

Classes may be given as ``"module:Class"`` strings, imported on first use (as Gymnasium's
entry points are), so that registering a world imports none of its code.
"""

from __future__ import annotations

import importlib
import os
from dataclasses import dataclass
from typing import Any

import gymnasium as gym
from gymnasium.envs.registration import WrapperSpec

from lfm_env.config.loading import (
    TOP_LEVEL_KEYS,
    ConfigError,
    from_dict,
    load_yaml,
    read_section,
    show_value,
)
from lfm_env.config.world import WorldConfig

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
    """

    env_id: str
    config: Any
    env: Any

    @property
    def config_class(self) -> type[WorldConfig]:
        """The config dataclass (imported on first use)."""
        return _load(self.config)

    @property
    def env_class(self) -> type:
        """The env class (imported on first use)."""
        return _load(self.env)


#: The registered worlds by env id, in registration order.
WORLDS: dict[str, WorldSpec] = {}


def register_world(env_id: str, config: Any, env: Any) -> WorldSpec:
    """Register a world under ``env_id``, with Gymnasium too (``gym.make(env_id)``).

    The Gymnasium registration truncates episodes after the config's ``max_steps``
    (:class:`lfm_env.wrappers.ConfigTimeLimit`), unless ``gym.make(env_id,
    max_episode_steps=K)`` asks for another length.

    Args:
        env_id: the id, ``"namespace/Name-vN"`` as Gymnasium's ids are.
        config: the ``env:`` section's dataclass (a :class:`WorldConfig`), or
            ``"module:Class"``.
        env: the env class, or ``"module:Class"``.

    Returns:
        The world's record, also in :data:`WORLDS`.

    Raises:
        ValueError: for an id that is not a non-empty string or that is registered already
            to other classes.
    """
    if not isinstance(env_id, str) or not env_id.strip():
        raise ValueError(f"register_world: env_id={env_id!r} must be a non-empty string")
    spec = WorldSpec(env_id, config, env)
    if env_id in WORLDS and WORLDS[env_id] != spec:
        raise ValueError(f"register_world: {env_id!r} is registered already as {WORLDS[env_id]}")
    WORLDS[env_id] = spec
    gym.register(
        id=env_id,
        entry_point=env,
        max_episode_steps=None,  # the config's max_steps, through ConfigTimeLimit
        additional_wrappers=(_CONFIG_TIME_LIMIT,),
    )
    return spec


def world_spec(env_id: Any) -> WorldSpec:
    """The record of the world ``env_id``; a ConfigError listing the known ids otherwise."""
    if not isinstance(env_id, str) or env_id not in WORLDS:
        raise ConfigError(f"env_id={show_value(env_id)}: must be one of {sorted(WORLDS)}")
    return WORLDS[env_id]


def world_config_class(env_id: Any) -> type[WorldConfig]:
    """The config class of the world whose env is ``env_id``."""
    return world_spec(env_id).config_class


def env_id_of(config: WorldConfig | type[WorldConfig]) -> str:
    """The env id of the world a config (or config class) belongs to.

    Raises:
        ConfigError: when no registered world has that config class.
    """
    cls = config if isinstance(config, type) else type(config)
    for spec in WORLDS.values():
        if spec.config_class is cls:
            return spec.env_id
    raise ConfigError(f"{cls.__name__} is the config of no registered world (register_world)")


def read_env_id(config: Any) -> Any:
    """The top-level ``env_id`` of a config (path or whole-file dict); ``None`` if absent."""
    if isinstance(config, (str, os.PathLike)):
        config = load_yaml(config)
    if isinstance(config, dict) and any(k in TOP_LEVEL_KEYS for k in config):
        read_section(config, "env")  # unknown top-level keys are an error
        return config.get("env_id")
    return None


def load_env_config(config: Any = None, env_id: str | None = None) -> WorldConfig:
    """A world config from a path, a dict (whole file or the ``env`` section), a world
    config, or ``None`` for the defaults.

    The world is the file's top-level ``env_id`` (default :data:`DEFAULT_ENV_ID`, the
    paper's case study), or ``env_id`` when given (an env reading its own config); the two
    must agree.

    Raises:
        ConfigError: for an unknown ``env_id``, a file of another world, or a bad field.
    """
    if isinstance(config, WorldConfig):
        own = env_id_of(config)
        if env_id is not None and own != env_id:
            raise ConfigError(f"a config of {own!r} given to {env_id!r}")
        return config
    if isinstance(config, (str, os.PathLike)):
        config = load_yaml(config)
    file_id = read_env_id(config)
    if env_id is not None and file_id is not None and file_id != env_id:
        raise ConfigError(
            f"env_id={show_value(file_id)}: the config is for another env than {env_id!r}"
        )
    chosen = env_id if env_id is not None else file_id
    cls = world_config_class(DEFAULT_ENV_ID if chosen is None else chosen)
    return from_dict(cls, read_section(config, "env"), prefix="env")


__all__ = [
    "DEFAULT_ENV_ID",
    "WORLDS",
    "WorldSpec",
    "env_id_of",
    "load_env_config",
    "read_env_id",
    "register_world",
    "world_config_class",
    "world_spec",
]
