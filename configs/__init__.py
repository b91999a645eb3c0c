"""The configs' presets (``paper``, ``quick``, ``quadrotor``, ...): one YAML file each.

This folder is shipped as the package ``experiments.presets`` (``package-dir`` in
``pyproject.toml``), so an installed command finds a preset by its name from any folder
(``lfm-evaluate --config quick``); see :func:`experiments.cli.config_file`.
"""
