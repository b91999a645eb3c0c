"""Modules that a config or a command line names, found in the working folder too: by name,
and last.

A config names a world ``env_id: mine:Mine/World-v0`` and ``lfm-evaluate --agents
mymod:MyAgent`` an agent; the module (``mine``, ``mymod``) may be a file beside the config,
in the working folder, which a console script does not search. :func:`import_named` imports
it as Python finds it and, if Python finds no module of that name anywhere, from the working
folder: that one name, and only after every other place (the standard library and the
installed packages first), so a ``random.py`` or ``signal.py`` in the folder never shadows
the real module, and nothing else is imported from the folder.

Worker processes (a process pool, Dask) are given the same names with :func:`state` and
:func:`install`, so they find the named modules, and only those, where the parent did.
"""

from __future__ import annotations

import importlib
import importlib.abc
import importlib.machinery
import os
import sys
from types import ModuleType
from typing import Any

# The working folders and the top-level module names found in each, by import_named.
_NAMED: dict[str, set[str]] = {}


class _NamedModuleFinder(importlib.abc.MetaPathFinder):
    """Finds the top-level modules named by :func:`import_named` in their folder; on
    ``sys.meta_path`` after Python's own finders, so it is asked only for names that no
    other place holds."""

    def find_spec(self, fullname: str, path: Any = None, target: Any = None) -> Any:
        if path is not None or "." in fullname:
            return None  # (submodules are found through their package's __path__)
        for folder, names in _NAMED.items():
            if fullname in names:
                spec = importlib.machinery.PathFinder.find_spec(fullname, [folder])
                if spec is not None:
                    return spec
        return None


_FINDER = _NamedModuleFinder()


def _install_finder() -> None:
    if _FINDER not in sys.meta_path:
        sys.meta_path.append(_FINDER)


def import_named(module: str, folder: str | os.PathLike | None = None) -> ModuleType:
    """Import ``module`` as Python finds it or, when Python finds no module of its top-level
    name, from ``folder`` (default: the working folder), last (module docstring).

    Raises:
        ModuleNotFoundError: when neither holds it (as ``importlib.import_module``); any
            error of the module's own code propagates.
    """
    try:
        return importlib.import_module(module)
    except ModuleNotFoundError as exc:
        top = module.partition(".")[0]
        where = os.path.abspath(os.getcwd() if folder is None else folder)
        if exc.name not in (module, top) or top in _NAMED.get(where, ()):
            raise
        if importlib.machinery.PathFinder.find_spec(top, [where]) is None:
            raise
        _NAMED.setdefault(where, set()).add(top)
        _install_finder()
        return importlib.import_module(module)


def state() -> tuple[tuple[str, tuple[str, ...]], ...]:
    """The names :func:`import_named` found in working folders, as plain data for workers."""
    return tuple((folder, tuple(sorted(names))) for folder, names in sorted(_NAMED.items()))


def install(named: tuple[tuple[str, tuple[str, ...]], ...]) -> None:
    """In a worker process: find the modules of :func:`state` where the parent found them,
    and remove the working folder that a ``python -c`` start puts first on ``sys.path``
    (``""``), so that nothing else is imported from it."""
    sys.path[:] = [p for p in sys.path if p]
    for folder, names in named:
        _NAMED.setdefault(folder, set()).update(names)
    if _NAMED:
        _install_finder()


__all__ = ["import_named", "install", "state"]
