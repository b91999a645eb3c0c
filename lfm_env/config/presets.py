"""The presets: the config files shipped with the package, found by name from any folder.

The presets are the repository's ``configs/`` folder, installed as the package
``lfm_env.presets`` (mapped in ``pyproject.toml``) and read with ``importlib.resources``.
:func:`config_path` turns a preset's name or a path into the file to read: a path that names
an existing file wins; otherwise a name (``paper``, ``quick``, ``quadrotor``,
``matlab_reference``, with or without ``.yaml``) is looked up among the presets. This module
only finds files; what a whole file means (its sections, ``base:``, ``--set``) is read by
:func:`controllers.config.load_config`, and a world reads its own ``env:`` section
(:func:`lfm_env.worlds.registry.load_env_config`).
"""

from __future__ import annotations

import os
from pathlib import Path

from lfm_env.config.loading import ConfigError

#: The package the presets ship in (the repository's ``configs/`` folder, mapped in
#: ``pyproject.toml``), read with ``importlib.resources``.
PRESETS_PACKAGE = "lfm_env.presets"


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


def config_path(given: str | os.PathLike, folder: str | os.PathLike | None = None) -> Path:
    """The file a config is read from: a path to a YAML file, or a preset's name.

    A path that names an existing file wins (relative to ``folder`` when given, else to
    the working folder); otherwise ``given`` is looked up among the presets
    (:func:`preset_names`), from any folder.

    Args:
        given: a path or a preset's name.
        folder: the folder a relative path is relative to (a ``base:``'s file's folder).

    Raises:
        ConfigError: naming ``given`` and the presets, if it is neither.
    """
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


__all__ = ["PRESETS_PACKAGE", "config_path", "preset_names", "preset_path", "presets_folder"]
