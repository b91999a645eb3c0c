"""Names a package gives from its submodules on first use (PEP 562), so that importing the
package does not import them: the way out of an import cycle (a world's config imports the
shared config layer, whose package also gives the worlds' configs)."""

from __future__ import annotations

import importlib
from collections.abc import Callable, Mapping
from typing import Any


def lazy_attributes(package: str, where: Mapping[str, str]) -> Callable[[str], Any]:
    """A module ``__getattr__`` for ``package``: each name of ``where`` is imported from the
    module ``where[name]`` when it is first read; any other name is an AttributeError.

    Use: ``__getattr__ = lazy_attributes(__name__, {"Name": "package.module", ...})``.
    """

    def __getattr__(name: str) -> Any:
        if name in where:
            return getattr(importlib.import_module(where[name]), name)
        raise AttributeError(f"module {package!r} has no attribute {name!r}")

    return __getattr__


__all__ = ["lazy_attributes"]
