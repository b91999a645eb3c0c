"""Typed, validated configuration: the YAML reader and the sections every world shares.

One frozen dataclass per component, defaults in one place (the dataclass), YAML as plain
data. Unknown keys, wrong types, non-finite and out-of-range values are errors that name
the key and the allowed range. A config file has a top-level ``env_id`` (the world), an
``env:`` section (the world's config: ``lfm_env/worlds/<world>/config.py``) and an
``agents:`` section (:mod:`controllers.config`).

* :mod:`lfm_env.config.loading`: the YAML reader with its limits, and typed conversion;
* :mod:`lfm_env.config.world`: the latent force's section and the :class:`WorldConfig` mixin;
* :mod:`lfm_env.config.compose`: where a config comes from (a preset's name or a path, one
  resolver for every function that takes a config), ``base:`` inheritance and ``KEY=VALUE``
  settings;
* :mod:`lfm_env.worlds.registry`: which world a config means (:func:`load_env_config`).

The worlds' configs and the registry's functions are importable from here too (on first
use, since they import this package).
"""

from __future__ import annotations

from lfm_env.config.compose import (
    DEFAULT_PRESET,
    PRESETS_PACKAGE,
    apply_settings,
    config_path,
    merge,
    preset_names,
    presets_folder,
    read_config,
)
from lfm_env.config.loading import (
    MAX_CONFIG_BYTES,
    MAX_CONFIG_DEPTH,
    MAX_CONFIG_VALUES,
    TOP_LEVEL_KEYS,
    ConfigError,
    FieldChecker,
    from_dict,
    load_yaml,
    read_section,
    show_value,
    to_dict,
    to_dict_fields,
)
from lfm_env.config.world import (
    DISCRETIZATIONS,
    KERNELS,
    MATERN_NUS,
    MAX_STEPS,
    STARTS,
    DisturbanceConfig,
    LatentForceConfig,
    WorldConfig,
    check_latent_step,
)
from lfm_env.lazy import lazy_attributes

_ELSEWHERE = {
    "SineTrackConfig": "lfm_env.worlds.sine_track.config",
    "EnvConfig": "lfm_env.worlds.sine_track.config",
    "QuadrotorLatentForceConfig": "lfm_env.worlds.quadrotor.config",
    "GustConfig": "lfm_env.worlds.quadrotor.config",
    "QuadrotorGustConfig": "lfm_env.worlds.quadrotor.config",
    "DEFAULT_ENV_ID": "lfm_env.worlds.registry",
    "WORLDS": "lfm_env.worlds.registry",
    "load_env_config": "lfm_env.worlds.registry",
    "read_env_id": "lfm_env.worlds.registry",
    "world_config_class": "lfm_env.worlds.registry",
}


__getattr__ = lazy_attributes(__name__, _ELSEWHERE)


__all__ = [
    "DEFAULT_PRESET",
    "DISCRETIZATIONS",
    "KERNELS",
    "MATERN_NUS",
    "MAX_CONFIG_BYTES",
    "MAX_CONFIG_DEPTH",
    "MAX_CONFIG_VALUES",
    "MAX_STEPS",
    "PRESETS_PACKAGE",
    "STARTS",
    "TOP_LEVEL_KEYS",
    "ConfigError",
    "DisturbanceConfig",
    "LatentForceConfig",
    "FieldChecker",
    "WorldConfig",
    "apply_settings",
    "check_latent_step",
    "config_path",
    "from_dict",
    "load_yaml",
    "merge",
    "preset_names",
    "presets_folder",
    "read_config",
    "read_section",
    "show_value",
    "to_dict",
    "to_dict_fields",
    *_ELSEWHERE,
]
