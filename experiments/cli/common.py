"""What the command lines share: one-line errors, writable outputs, the configs by name or path,
the seeds and executor options."""

from __future__ import annotations

import argparse
import functools
import os
import sys
import tempfile
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from controllers.config import DEFAULT_PRESET
from experiments.evaluation.interrupts import remember_interrupts
from lfm_env.config import ConfigError
from lfm_env.config.presets import PRESETS_PACKAGE, config_path, preset_names


def os_error_text(exc: OSError) -> str:
    """One line for an operating-system error: its reason and the path it concerns."""
    reason = exc.strerror or str(exc) or type(exc).__name__
    paths = [str(p) for p in (exc.filename, exc.filename2) if p is not None]
    return " ".join(f"{reason}: {' -> '.join(paths)}".split()) if paths else reason


def one_line_errors(prog: str) -> Callable:
    """Decorate a ``main(argv) -> int``: an escaping ``OSError`` or ``MemoryError`` prints
    ``<prog>: error: ...`` and exits 2, Ctrl-C prints ``<prog>: interrupted`` and exits 130;
    ``main`` runs under :func:`~experiments.evaluation.interrupts.remember_interrupts`.
    """

    def decorate(main: Callable[..., int]) -> Callable[..., int]:
        @functools.wraps(main)
        def wrapped(argv: Sequence[str] | None = None) -> int:
            try:
                with remember_interrupts():  # a Ctrl-C a library swallows still stops
                    return main(argv)
            except OSError as exc:
                print(f"{prog}: error: {os_error_text(exc)}", file=sys.stderr)
                return 2
            except MemoryError:
                print(
                    f"{prog}: error: out of memory; use smaller settings "
                    "(see docs/configuration.md, Limits)",
                    file=sys.stderr,
                )
                return 2
            except KeyboardInterrupt:
                print(f"\n{prog}: interrupted", file=sys.stderr)
                return 130

        return wrapped

    return decorate


def check_writable(path: str | os.PathLike, what: str) -> str | None:
    """Why the file ``path`` cannot be written (one line naming ``what``), else ``None``; creates
    its parent folders and tries a temporary file beside it.
    """
    target = Path(path)
    if target.is_dir():
        return f"{what} {path}: is a folder, expected a file name"
    try:
        target.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=target.parent, prefix=f".{target.name}.", suffix=".tmp")
        os.close(fd)
        os.unlink(tmp)
    except OSError as exc:
        return f"{what} {path}: cannot be written ({os_error_text(exc)})"
    return None


def positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not an integer") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"{text!r} must be >= 1")
    return value


def config_file(given: str | os.PathLike | None) -> Path:
    """The config file of a ``--config`` value: an existing YAML path, else a preset's name
    (``None``: ``paper``), as :func:`lfm_env.config.presets.config_path`.

    Raises:
        ValueError: naming ``given`` and the preset names, if it is neither.
    """
    try:
        return config_path(DEFAULT_PRESET if given is None else given)
    except ConfigError:
        raise ValueError(
            f"--config {str(given)[:200]}: no such file and no preset of that name; presets: "
            f"{', '.join(preset_names())} (or a path to a YAML file)"
        ) from None


def add_config_argument(parser: argparse.ArgumentParser) -> None:
    """The ``--config`` option shared by the commands that run episodes."""
    parser.add_argument(
        "--config",
        metavar="NAME|YAML",
        default=None,
        help=(
            "a preset's name (" + ", ".join(preset_names()) + ") or a config file with "
            f"env_id, env and agents sections; env_id picks the world (default: "
            f"{DEFAULT_PRESET})"
        ),
    )


def config_argument_path(parser: argparse.ArgumentParser, given: str | None) -> Path:
    """The config file of ``--config`` (:func:`config_file`); exits 2 if there is none."""
    try:
        return config_file(given)
    except ValueError as exc:
        parser.error(str(exc))


#: The help texts' note on the fast solver's compiled C library and where it is cached.
CACHE_NOTE = (
    "The fast solver compiles a C library once per system (about 1.5 s, with the system C "
    "compiler $CC, else cc or gcc) and caches it under $LFM_CACHE_DIR (default "
    "~/.cache/lfm-scenario-mpc); delete that folder to rebuild. Without a compiler it runs "
    "its NumPy backend, slower."
)


def add_set_argument(parser: argparse.ArgumentParser) -> None:
    """``--set KEY=VALUE`` (repeatable): a field of the config, set on top of ``--config``."""
    parser.add_argument(
        "--set",
        dest="overrides",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help=(
            "set one field of the config, e.g. --set agents.horizon=10 --set "
            "env.latent_force.variance=2.0 (repeatable; a dotted key from the top: env_id, "
            "env.<field>, agents.<field>; the value read by the field's type, lists as "
            "[a,b], null where allowed)"
        ),
    )


def config_argument(
    parser: argparse.ArgumentParser, args: argparse.Namespace, agents: Sequence[str] = ()
) -> tuple[Path, object]:
    """The ``--config`` file and the config it gives with the ``--set`` overrides applied
    (an :class:`~controllers.config.ExperimentConfig`, checked for ``agents``); exits 2
    with one line naming the field otherwise."""
    from experiments.evaluation import resolve_config

    path = config_argument_path(parser, args.config)
    try:
        from controllers.config import load_config

        config = resolve_config(load_config(path, getattr(args, "overrides", ())), agents)
    except ValueError as exc:  # ConfigError: the loaders name the key
        parser.error(" ".join(str(exc).split()))
    return path, config


def add_executor_arguments(parser: argparse.ArgumentParser, jobs_help: str) -> None:
    """``--jobs``, ``--scheduler`` and ``--dask-workers``: where the episodes run (checked
    together by :func:`seeds_and_executor`)."""
    parser.add_argument("--jobs", type=positive_int, default=1, metavar="N", help=jobs_help)
    parser.add_argument(
        "--scheduler",
        metavar="ADDRESS",
        default=None,
        help="run on an existing Dask cluster, e.g. tcp://127.0.0.1:8786 (DIR must be shared)",
    )
    parser.add_argument(
        "--dask-workers",
        type=positive_int,
        default=None,
        metavar="N",
        help="start a local Dask cluster of N single-threaded workers on 127.0.0.1",
    )


def run_episodes(
    parser: argparse.ArgumentParser,
    args: argparse.Namespace,
    out: Path,
    run: Callable[..., Any],
    *run_args: Any,
    **run_kwargs: Any,
) -> Any:
    """``run(*run_args, out=out, <the executor options>, progress=not args.quiet, **run_kwargs)``
    for ``lfm-evaluate`` and ``lfm-sweep``: a ``ValueError`` or ``ConnectionError`` (raised
    before any episode runs) exits 2 through ``parser.error``; Ctrl-C prints where the
    finished episodes are and gives ``None`` (the command then returns 130)."""
    try:
        return run(
            *run_args,
            out=out,
            jobs=args.jobs,
            scheduler=args.scheduler,
            dask_workers=args.dask_workers,
            progress=not args.quiet,
            **run_kwargs,
        )
    except (ValueError, ConnectionError) as exc:  # raised before any episode runs
        parser.error(" ".join(str(exc).split()))
    except KeyboardInterrupt:
        print(f"\ninterrupted; finished episodes are in {out}; rerun to resume", file=sys.stderr)
        return None


def non_negative_seconds(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number of seconds") from None
    if not (value >= 0.0 and value != float("inf")):
        raise argparse.ArgumentTypeError(f"{text!r} must be a finite number of seconds >= 0")
    return value


def add_episode_timeout_argument(parser: argparse.ArgumentParser) -> None:
    """``--episode-timeout SECONDS``: the wall-clock limit of one episode."""
    parser.add_argument(
        "--episode-timeout",
        type=non_negative_seconds,
        default=None,
        metavar="SECONDS",
        help=(
            "wall-clock limit of one episode: one that runs longer ends as an error row "
            "naming the limit, in every executor; 0 for none (default: the config's "
            "evaluation.episode_timeout, 600 s unless set)"
        ),
    )


def registered_agents_help() -> str:
    """``name = label`` of every registered agent, for the agent options' help texts."""
    from controllers.agents import AGENT_REGISTRY

    return "; ".join(f"{s.name} = {s.label}" for s in AGENT_REGISTRY.values())


def seeds_and_executor(parser: argparse.ArgumentParser, args: argparse.Namespace) -> list[int]:
    """The parsed ``--seeds``, after checking that the executor options fit together
    (exits 2 through ``parser.error`` naming the option otherwise)."""
    from experiments.evaluation import parse_seeds

    try:
        seeds = parse_seeds(args.seeds)
    except ValueError as exc:
        parser.error(f"--seeds: {exc}")
    if args.scheduler is not None and args.dask_workers is not None:
        parser.error("--scheduler and --dask-workers exclude each other")
    if args.jobs > 1 and (args.scheduler is not None or args.dask_workers is not None):
        parser.error("--jobs runs local processes; do not combine it with Dask options")
    return seeds


__all__ = [
    "CACHE_NOTE",
    "DEFAULT_PRESET",
    "PRESETS_PACKAGE",
    "add_config_argument",
    "add_episode_timeout_argument",
    "add_executor_arguments",
    "add_set_argument",
    "check_writable",
    "config_argument",
    "config_argument_path",
    "config_file",
    "one_line_errors",
    "os_error_text",
    "non_negative_seconds",
    "positive_int",
    "preset_names",
    "registered_agents_help",
    "run_episodes",
    "seeds_and_executor",
]
