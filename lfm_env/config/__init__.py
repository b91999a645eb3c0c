"""Typed, validated configuration of the world: the YAML reader and the ``env:`` section.

One frozen dataclass per component, defaults in one place (the dataclass), YAML as plain
data. Unknown keys, wrong types, non-finite and out-of-range values are errors that name
the key and the allowed range. This layer reads a world's ``env:`` section (each world's
``config.py``; the world is chosen by a config's ``env_id``:
:func:`lfm_env.worlds.registry.load_env_config`) and knows no other section: a whole config
file (``env_id``, ``env``, ``agents``, ``evaluation``, ``base:``, ``--set``) is read by
:func:`controllers.config.load_config`.

* :mod:`lfm_env.config.loading`: the YAML reader with its limits, and typed conversion;
* :mod:`lfm_env.config.world`: the latent force's section and the :class:`WorldConfig` mixin;
* :mod:`lfm_env.config.presets`: the presets shipped with the package, found by name.
"""

from __future__ import annotations

from lfm_env.config.loading import (
    MAX_CONFIG_BYTES,
    MAX_CONFIG_DEPTH,
    MAX_CONFIG_VALUES,
    ConfigError,
    FieldChecker,
    from_dict,
    load_yaml,
    show_value,
    to_dict,
    to_dict_fields,
)
from lfm_env.config.presets import PRESETS_PACKAGE, config_path, preset_names, presets_folder
from lfm_env.config.world import (
    DISCRETIZATIONS,
    KERNELS,
    MATERN_NUS,
    MAX_STEPS,
    STARTS,
    LatentForceConfig,
    WorldConfig,
    check_latent_step,
)

__all__ = [
    "DISCRETIZATIONS",
    "KERNELS",
    "MATERN_NUS",
    "MAX_CONFIG_BYTES",
    "MAX_CONFIG_DEPTH",
    "MAX_CONFIG_VALUES",
    "MAX_STEPS",
    "PRESETS_PACKAGE",
    "STARTS",
    "ConfigError",
    "FieldChecker",
    "LatentForceConfig",
    "WorldConfig",
    "check_latent_step",
    "config_path",
    "from_dict",
    "load_yaml",
    "preset_names",
    "presets_folder",
    "show_value",
    "to_dict",
    "to_dict_fields",
]
