"""``lfm-export``: write the controller of a config and agent as a self-contained C project
(:func:`controllers.export.export_controller`)."""

from __future__ import annotations

import argparse
from collections.abc import Sequence

from experiments.cli.common import config_file, one_line_errors, preset_names


def _export_parser() -> argparse.ArgumentParser:
    from controllers.export import EXPORTABLE_AGENTS

    parser = argparse.ArgumentParser(
        prog="lfm-export",
        description=(
            "Write an agent's controller as a C project a robot can run without Python: the "
            "system's generated library with the compiled fast SQP, the agent's estimator "
            "(the UKF) and scenarios, a documented API (lfm_controller.h), example.c and a "
            "Makefile. `make -C DIR` builds DIR/example and liblfm_controller.a with a plain C "
            "compiler (libc and libm only); `DIR/example PROBLEM.txt` prints the plan of a "
            "scenario problem (controllers.export.write_problem writes one). See docs/export.md."
        ),
        epilog="example: lfm-export --config paper --agent robust --out build/robust",
    )
    parser.add_argument(
        "--config",
        metavar="NAME|YAML",
        default="paper",
        help=f"a preset's name ({', '.join(preset_names())}) or a config file (default: paper)",
    )
    parser.add_argument(
        "--agent",
        required=True,
        choices=EXPORTABLE_AGENTS,
        help="the agent to export (its step needs the UKF estimator, or none: nominal; "
        "with another estimator only its solve is exported)",
    )
    parser.add_argument("--out", required=True, metavar="DIR", help="the project folder")
    parser.add_argument(
        "--force", action="store_true", help="overwrite the files of an existing export in DIR"
    )
    return parser


@one_line_errors("lfm-export")
def export_main(argv: Sequence[str] | None = None) -> int:
    """``lfm-export``: write the C project; prints what it wrote and how to build it."""
    from controllers.export import export_controller

    parser = _export_parser()
    args = parser.parse_args(argv)
    try:
        path = config_file(args.config)
        result = export_controller(
            str(path), args.agent, args.out, overwrite=args.force, config_name=path.stem
        )
    except ValueError as exc:
        parser.error(" ".join(str(exc).split()))
    d = result.dimensions
    print(
        f"lfm-export: {result.agent} on {result.system} ({path.stem}): N = {d['N']}, "
        f"Ns = {d['Ns']}, {d['nx']} states, {d['nu']} inputs -> {result.out}"
    )
    print(f"  files: {', '.join(result.files)}")
    step = "the whole step" if result.step_available else "the solve only (lfm_controller_solve)"
    print(f"  exported: {step}")
    for note in result.notes:
        print(f"  note: {note}")
    print(f"  build: make -C {result.out}    then: {result.out}/example PROBLEM.txt")
    return 0
