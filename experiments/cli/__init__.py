"""Command lines: thin ``<name>_main(argv=None) -> int`` layers (console scripts in
``pyproject.toml``) that parse arguments and call library functions. Bad arguments and
operating-system errors exit 2 with one line (:func:`~experiments.cli.common.one_line_errors`),
Ctrl-C exits 130.
"""

import argparse
from collections.abc import Callable

from experiments.cli.benchmark import benchmark_main, build_parser
from experiments.cli.calibrate import _calibrate_parser, calibrate_main
from experiments.cli.common import (
    DEFAULT_PRESET,
    PRESETS_PACKAGE,
    add_config_argument,
    check_writable,
    config_argument_path,
    config_file,
    one_line_errors,
    os_error_text,
    positive_int,
    preset_names,
    seeds_and_executor,
)
from experiments.cli.evaluate import _evaluate_parser, evaluate_main
from experiments.cli.export import _export_parser, export_main
from experiments.cli.render import (
    MAX_RENDER_SIDE,
    RENDER_MEMORY_BUDGET,
    _render_parser,
    render_main,
)
from experiments.cli.report import _report_parser, report_main
from experiments.cli.sweep import _sweep_parser, sweep_main
from experiments.cli.train import _train_parser, train_main

#: Each command's argument parser as its ``main()`` builds it, by command name (the docs'
#: tests parse the command lines they show with these).
COMMAND_PARSERS: dict[str, Callable[[], argparse.ArgumentParser]] = {
    "lfm-evaluate": _evaluate_parser,
    "lfm-report": _report_parser,
    "lfm-render": _render_parser,
    "lfm-sweep": _sweep_parser,
    "lfm-calibrate": _calibrate_parser,
    "lfm-train": _train_parser,
    "lfm-benchmark": build_parser,
    "lfm-export": _export_parser,
}

__all__ = [
    "COMMAND_PARSERS",
    "DEFAULT_PRESET",
    "MAX_RENDER_SIDE",
    "PRESETS_PACKAGE",
    "RENDER_MEMORY_BUDGET",
    "add_config_argument",
    "benchmark_main",
    "calibrate_main",
    "check_writable",
    "config_argument_path",
    "config_file",
    "evaluate_main",
    "export_main",
    "one_line_errors",
    "os_error_text",
    "positive_int",
    "preset_names",
    "render_main",
    "report_main",
    "seeds_and_executor",
    "sweep_main",
    "train_main",
]
