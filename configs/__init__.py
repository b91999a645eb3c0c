"""The configs' presets (``paper``, ``quick``, ``quadrotor``, ...): one YAML file each.

This folder is shipped as the package ``lfm_env.presets`` (``package-dir`` in
``pyproject.toml``), so every function that takes a config finds a preset by its name from
any folder (``lfm-evaluate --config quick``, ``load_config("paper")``,
``gym.make("lfm_env/SineTrack-v0", config="paper")``); see
:func:`lfm_env.config.presets.config_path`.
"""
