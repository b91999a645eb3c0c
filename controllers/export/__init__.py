"""The controller exported as a C project (``lfm-export``), and its checks from Python.

:func:`export_controller` writes the project (:mod:`controllers.export.project`; its C beside
this module in ``c/``), :func:`write_problem` a scenario problem for its ``example``, and
:class:`ExportedController` drives the built library through ctypes
(:mod:`controllers.export.binding`). See ``docs/export.md``.
"""

from controllers.export.binding import (
    ExportedController,
    build_shared,
    config_defines,
    external_dependencies,
    run_make,
)
from controllers.export.project import (
    EXPORTABLE_AGENTS,
    ExportResult,
    export_controller,
    read_plan,
    solver_options,
    write_problem,
)

__all__ = [
    "EXPORTABLE_AGENTS",
    "ExportResult",
    "ExportedController",
    "build_shared",
    "config_defines",
    "export_controller",
    "external_dependencies",
    "read_plan",
    "run_make",
    "solver_options",
    "write_problem",
]
