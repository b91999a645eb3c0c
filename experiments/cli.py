"""Command lines of the project: thin layers that parse arguments and call library functions.

Each command is a ``<name>_main(argv=None) -> int`` function registered as a console
script in ``pyproject.toml`` (``lfm-evaluate = "experiments.cli:evaluate_main"``) and
wrapped by a one-line script in ``scripts/``. Bad arguments exit with code 2 and a
one-line message (``argparse``'s ``parser.error``); so do operating-system errors (disk
full, a read-only or impossible output path) and running out of memory
(:func:`one_line_errors`). Ctrl-C prints one line and exits with code 130.
"""

from __future__ import annotations

import argparse
import functools
import os
import sys
import tempfile
from collections.abc import Callable, Sequence
from pathlib import Path

from experiments.interrupts import remember_interrupts

PRESETS_PACKAGE = "experiments.presets"  # the configs/ folder, shipped in the package
DEFAULT_PRESET = "paper"

_EVALUATE_EPILOG = """\
files written (DIR is --out):
  DIR/config.yaml                       the resolved config of every episode in DIR
  DIR/episodes/<agent>__seed<S>.npz     trajectory of one episode
  DIR/episodes/<agent>__seed<S>.json    its row of metrics (written last: marks it done)
  DIR/episodes.csv                      all rows, sorted by agent and seed

Rerunning the same command resumes an interrupted run: finished episodes are
skipped and episodes that raised an error are retried. A folder holds one config;
resuming with another config is refused. Exit code 0 when every episode ran, 1 when
some raised (they are in the table with their error), 2 on bad arguments.

Metrics (columns of episodes.csv): success, steps, time_to_goal [s], cost (sum of
the true stage cost), then per constraint group G of the world's system
<G>_violation_steps and max_<G>_excess [the group's unit] (sine track: track [m],
x [m], speed [m/s]; quadrotor: corridor [m], x [m]) and <G>_violation_steps_over_<T>
per tolerance T of the group (steps with the excess above T; sine track: track and x
0.01, 0.05 m, speed 0.05 m/s), failure (the env ended the
episode as a failure), latent_rmse [force unit] and latent_coverage (2-sigma band;
filter agents only), solve_time_median/p95/max [s], solver_failures,
fallback_steps, filter_resets, slack_total, wall_time [s], error.

examples:
  lfm-evaluate                                   paper config, seeds 0:20, 3 agents
  lfm-evaluate --config quick --seeds 0:5 --jobs 2      a preset, by name
  lfm-evaluate --config quadrotor --agents nominal,scenario,oracle
  lfm-evaluate --config my/config.yaml --seeds 0:5      a config file, by path
  lfm-evaluate --agents scenario,oracle --seeds 0:10,20:25 --out results/sweep
  lfm-evaluate --agents nominal,mypkg.agents:MyAgent   your own agent next to nominal
  lfm-evaluate --dask-workers 2                  local Dask cluster on 127.0.0.1
  lfm-evaluate --scheduler tcp://10.0.0.5:8786   existing Dask cluster (DIR shared)
"""


def os_error_text(exc: OSError) -> str:
    """One line for an operating-system error: its reason and the path it concerns."""
    reason = exc.strerror or str(exc) or type(exc).__name__
    paths = [str(p) for p in (exc.filename, exc.filename2) if p is not None]
    return " ".join(f"{reason}: {' -> '.join(paths)}".split()) if paths else reason


def one_line_errors(prog: str) -> Callable:
    """Decorate a ``main(argv) -> int``: an ``OSError`` or ``MemoryError`` escaping it is
    printed as one line ``<prog>: error: ...`` on stderr and gives exit code 2, and
    Ctrl-C (``KeyboardInterrupt``) one line ``<prog>: interrupted`` and exit code 130,
    instead of a traceback. ``main`` runs under
    :func:`experiments.interrupts.remember_interrupts` (SIGTERM ends it like Ctrl-C)."""

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
                    f"{prog}: error: out of memory; use smaller settings (see README, Limits)",
                    file=sys.stderr,
                )
                return 2
            except KeyboardInterrupt:
                print(f"\n{prog}: interrupted", file=sys.stderr)
                return 130

        return wrapped

    return decorate


def check_writable(path: str | os.PathLike, what: str) -> str | None:
    """Why the file ``path`` cannot be written (one line naming ``what``), else ``None``.

    Creates the missing parent folders and a temporary file beside ``path`` (removed at
    once), so an unwritable, read-only or impossible path is found before any work.
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


def _positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not an integer") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"{text!r} must be >= 1")
    return value


def _presets_folder() -> Path:
    """The folder of the presets: the installed package's, else a checkout's ``configs/``.

    A wheel ships ``configs/`` as the package ``experiments.presets``; an editable install
    maps it there too. A source tree used without installing it (``PYTHONPATH=.``) has
    no such package, and its ``configs/`` folder beside ``experiments/`` is used instead.
    """
    from importlib import resources

    try:
        return Path(str(resources.files(PRESETS_PACKAGE)))
    except ModuleNotFoundError:
        return Path(__file__).resolve().parent.parent / "configs"


def preset_names() -> list[str]:
    """The names of the shipped presets (``paper``, ``quick``, ``quadrotor``, ...), sorted."""
    return sorted(p.stem for p in _presets_folder().glob("*.yaml"))


def config_file(given: str | os.PathLike | None) -> Path:
    """The config file of a ``--config`` value: a path to a YAML file, or a preset's name.

    Every command with ``--config`` resolves it here. A path that names an existing file
    wins; otherwise ``given`` is looked up among the presets shipped in the package
    (``paper``, ``quick``, ``quadrotor``, with or without ``.yaml``), from any folder.

    Args:
        given: the option's value; ``None`` for the default preset (``paper``).

    Raises:
        ValueError: naming ``given`` and the preset names, if it is neither.
    """
    if given is None:
        given = DEFAULT_PRESET
    path = Path(given)
    if path.is_file():
        return path
    name = path.name[: -len(".yaml")] if path.name.endswith(".yaml") else path.name
    if path.parent == Path(".") and name in preset_names():
        return _presets_folder() / f"{name}.yaml"
    raise ValueError(
        f"--config {str(given)[:200]}: no such file and no preset of that name; presets: "
        f"{', '.join(preset_names())} (or a path to a YAML file)"
    )


def _add_config_argument(parser: argparse.ArgumentParser) -> None:
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


def _config_path(parser: argparse.ArgumentParser, given: str | None) -> Path:
    """The config file of ``--config`` (:func:`config_file`); exits 2 if there is none."""
    try:
        return config_file(given)
    except ValueError as exc:
        parser.error(str(exc))


def _evaluate_parser() -> argparse.ArgumentParser:
    from controllers.agents import AGENT_LABELS

    agents_help = "; ".join(f"{k} = {v}" for k, v in AGENT_LABELS.items())
    parser = argparse.ArgumentParser(
        prog="lfm-evaluate",
        description=(
            "Run MPC agents on the world of the config (its env_id, e.g. lfm_env/SineTrack-v0\n"
            "for configs/paper.yaml) over env seeds and save one row of metrics and one\n"
            "trajectory per episode. For one env seed every agent faces the same hidden\n"
            "disturbance and noise (paired design)."
        ),
        epilog=_EVALUATE_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    _add_config_argument(parser)
    parser.add_argument(
        "--agents",
        default="nominal,pf,scenario",
        metavar="A,B,...",
        help=(
            "comma-separated agents (default: nominal,pf,scenario): registered names, or "
            "your own agent as module:attribute, a factory called with the resolved config "
            "(or an agent class taking it) returning an object with reset(seed=None) and "
            "act(obs) (README, 'Your own agent'; the module is looked up from the current "
            f"folder too). {agents_help}"
        ),
    )
    parser.add_argument(
        "--seeds",
        default="0:20",
        metavar="SEEDS",
        help=(
            "env seeds: a range start:end (end exclusive), single seeds and lists, "
            "e.g. 0:20, 3, 1,5,9, 0:10,20:25 (default: 0:20)"
        ),
    )
    parser.add_argument(
        "--jobs",
        type=_positive_int,
        default=1,
        metavar="N",
        help="local worker processes (default: 1, serial)",
    )
    parser.add_argument(
        "--scheduler",
        metavar="ADDRESS",
        default=None,
        help="run on an existing Dask cluster, e.g. tcp://127.0.0.1:8786 (DIR must be shared)",
    )
    parser.add_argument(
        "--dask-workers",
        type=_positive_int,
        default=None,
        metavar="N",
        help="start a local Dask cluster of N single-threaded workers on 127.0.0.1",
    )
    parser.add_argument(
        "--out",
        metavar="DIR",
        default=None,
        help="results folder (default: results/<config file stem>, e.g. results/paper)",
    )
    parser.add_argument(
        "--no-report",
        action="store_true",
        help="do not write the report after the run (default: experiments.report.write_report)",
    )
    parser.add_argument(
        "--quiet", action="store_true", help="no progress bar and no per-agent summary"
    )
    return parser


def _print_summary(rows: list[dict]) -> None:
    """One line per agent: episodes, successes, failures, errors."""
    agents = list(dict.fromkeys(r["agent"] for r in rows))
    width = max((len(a) for a in agents), default=0)
    for agent in agents:
        mine = [r for r in rows if r["agent"] == agent]
        ok = [r for r in mine if r["error"] == ""]
        print(
            f"  {agent:>{width}}: {len(mine)} episodes, "
            f"{sum(r['success'] for r in ok)} reached the goal, "
            f"{sum(r['failure'] for r in ok)} left the safety box, "
            f"{len(mine) - len(ok)} raised an error"
        )


def _seeds_and_executor(parser: argparse.ArgumentParser, args: argparse.Namespace) -> list[int]:
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


@one_line_errors("lfm-evaluate")
def evaluate_main(argv: Sequence[str] | None = None) -> int:
    """``lfm-evaluate``: evaluate agents over seeds and write the results (see ``--help``).

    Returns:
        The exit code: 0 if every episode ran, 1 if some raised an error.
    """
    from experiments.evaluation import evaluate

    parser = _evaluate_parser()
    args = parser.parse_args(argv)

    config_path = _config_path(parser, args.config)
    seeds = _seeds_and_executor(parser, args)
    agents = [a.strip() for a in args.agents.split(",")]
    if any(":" in a for a in agents) and os.getcwd() not in sys.path:
        # As `python -m` does: `module:attribute` agents import from the current folder.
        sys.path.insert(0, os.getcwd())
    out = (
        Path(args.out)
        if args.out
        else Path("results") / (config_path.stem if config_path is not None else "defaults")
    )

    try:
        rows = evaluate(
            agents,
            seeds,
            config=config_path,
            out=out,
            jobs=args.jobs,
            scheduler=args.scheduler,
            dask_workers=args.dask_workers,
            progress=not args.quiet,
        )
    except (ValueError, ConnectionError) as exc:  # raised before any episode runs
        parser.error(" ".join(str(exc).split()))
    except KeyboardInterrupt:
        print(f"\ninterrupted; finished episodes are in {out}; rerun to resume", file=sys.stderr)
        return 130

    n_errors = sum(r["error"] != "" for r in rows)
    if not args.quiet:
        _print_summary(rows)
    print(f"results: {out / 'episodes.csv'} ({len(rows)} episodes, {n_errors} with errors)")
    if n_errors:
        print(f"rerun the same command to retry the {n_errors} episodes that raised an error")

    if not args.no_report:
        try:
            from experiments.report import write_report
        except ImportError as exc:
            print(f"report: skipped, experiments.report is not available ({exc})")
        else:
            try:
                where = write_report(out)
            except Exception as exc:  # the results are safe; only the report failed
                print(f"report: failed ({type(exc).__name__}: {exc}); results are kept")
                return 1
            print(f"report: {where if where is not None else out}")
    return 1 if n_errors else 0


# --------------------------------------------------------------------------- lfm-report

_REPORT_EPILOG = """\
files written (DIR is the results folder):
  DIR/report.md, DIR/report.html   the same report; report.md links the figures,
                                   report.html embeds them all (it can be sent alone)
  DIR/figures/*.png                figures of one episode (with the plan's scenario fan
                                   at four steps), across-seed plots
  DIR/figures/episode.gif          the episode replayed from its saved true states, with
                                   the estimate and the scenario fan below the scene
  DIR/figures/estimator_calibration.png   coverage and RMSE of the filtering agents
  DIR/figures/sweep.png            the risk sweep's Pareto picture (with --sweep, or
                                   when DIR holds a sweep.md of lfm-sweep)

Reads DIR/episodes.csv, DIR/episodes/*.npz and DIR/config.yaml; runs no episode.
The figures and the metric units come from the system of the world in config.yaml,
so a results folder of any world (configs/paper.yaml, configs/quadrotor.yaml, ...)
is reported the same way.
Exit code 0 on success, 2 when DIR is missing, empty or the seed has no trajectory.

examples:
  lfm-report results/paper
  lfm-report results/quick --seed 3 --no-gif
  lfm-report results/paper --sweep results/sweep
  lfm-report results/paper --baseline pf         paired differences against pf
"""


def _report_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="lfm-report",
        description=(
            "Write report.md and report.html for a results folder of lfm-evaluate: per-agent\n"
            "means with 95% bootstrap intervals (constraint metrics per group of the world's\n"
            "system), paired differences against a baseline agent, one episode's figures\n"
            "drawn from the system (path in the plane of the first two states with the\n"
            "feasible region, latent force, inputs with bounds, other states, constraint\n"
            "excess), across-seed plots, a GIF of the episode and, for the sine track, a\n"
            "'paper vs measured' table. The oracle agent is an upper bound (it reads the\n"
            "hidden truth) and is labelled so."
        ),
        epilog=_REPORT_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("results_dir", metavar="DIR", help="results folder of lfm-evaluate")
    parser.add_argument(
        "--seed",
        type=int,
        default=None,
        metavar="S",
        help=(
            "env seed of the episode figures and GIF (default: the smallest seed whose "
            "scenario episode ran without error for at least one step)"
        ),
    )
    parser.add_argument("--no-gif", action="store_true", help="do not write figures/episode.gif")
    parser.add_argument(
        "--baseline",
        metavar="NAME",
        default=None,
        help=(
            "the agent the paired differences compare every other agent with (default: "
            "scenario if DIR holds it, else the first agent)"
        ),
    )
    parser.add_argument(
        "--sweep",
        metavar="SWEEPDIR",
        default=None,
        help=(
            "include the table and Pareto figure of an lfm-sweep folder (default: DIR's own "
            "sweep when DIR holds a sweep.md)"
        ),
    )
    return parser


@one_line_errors("lfm-report")
def report_main(argv: Sequence[str] | None = None) -> int:
    """``lfm-report``: write the report of a results folder (see ``--help``).

    Returns:
        The exit code: 0 when the report was written.
    """
    from experiments.report import write_report

    parser = _report_parser()
    args = parser.parse_args(argv)
    try:
        path = write_report(
            args.results_dir,
            figure_seed=args.seed,
            gif=not args.no_gif,
            sweep_dir=args.sweep,
            baseline=args.baseline,
        )
    except (FileNotFoundError, ValueError) as exc:
        parser.error(" ".join(str(exc).split()))
    print(f"report: {path} and {path.with_suffix('.html')}")
    return 0


# --------------------------------------------------------------------------- lfm-sweep

_SWEEP_EPILOG = """\
files written (DIR is --out):
  DIR/sweep.json                  what is swept: agent, key, values, baseline, seeds
  DIR/baseline/                   the baseline agent on the base config (lfm-evaluate folder)
  DIR/<KEY>=<VALUE>/              the agent with KEY set to VALUE, one folder per value
  DIR/sweep.md                    the table: per value its mean and the paired difference
                                  to the baseline with a 95% bootstrap interval
  DIR/sweep.png                   the Pareto picture: violation steps beyond the first
                                  tolerance against time to goal, paired to the baseline

--set takes a dotted key of the agents section and comma-separated values, read by
the key's own type (a list key takes one value or [a,b,...]; null where allowed):
agents.backoff, agents.n_scenarios, agents.estimator, agents.n_particles,
agents.robust.backoff, ... Rerunning the same command resumes an interrupted sweep
(finished episodes are kept). lfm-report RESULTS --sweep DIR puts the table and the
figure into a report. Exit code 0 when every episode ran, 1 when some raised, 2 on
bad arguments.

examples:
  lfm-sweep --config configs/paper.yaml --agent robust --set agents.robust.backoff=0,1,2,3 \\
            --baseline pf --seeds 0:100 --jobs 2 --out results/sweep
  lfm-sweep --config configs/quick.yaml --agent scenario --set agents.backoff=0,2 --seeds 0:5
  lfm-sweep --agent robust --set agents.robust.estimator=bootstrap,rbpf,ukf --seeds 0:20
"""


def _sweep_parser() -> argparse.ArgumentParser:
    from controllers.agents import AGENT_LABELS

    agents_help = "; ".join(f"{k} = {v}" for k, v in AGENT_LABELS.items())
    parser = argparse.ArgumentParser(
        prog="lfm-sweep",
        description=(
            "The risk trade-off: run one agent with one setting swept over values, and a\n"
            "baseline agent once, on the same env seeds (same hidden disturbance and noise),\n"
            "then compare each value with the baseline: violation steps beyond each tolerance,\n"
            "zero-violation episodes and time to goal, with paired bootstrap intervals."
        ),
        epilog=_SWEEP_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    _add_config_argument(parser)
    parser.add_argument(
        "--agent", default="robust", help=f"the agent swept (default: robust). {agents_help}"
    )
    parser.add_argument(
        "--set",
        dest="setting",
        required=True,
        metavar="KEY=V1,V2,...",
        help="the swept setting, e.g. agents.robust.backoff=0,1,2,3",
    )
    parser.add_argument(
        "--baseline", default="pf", help="the agent every value is compared with (default: pf)"
    )
    parser.add_argument(
        "--seeds",
        default="0:20",
        metavar="SEEDS",
        help="env seeds, e.g. 0:100, 3, 1,5,9 (end exclusive; default: 0:20)",
    )
    parser.add_argument(
        "--jobs",
        type=_positive_int,
        default=1,
        metavar="N",
        help="local worker processes per evaluation (default: 1, serial)",
    )
    parser.add_argument(
        "--scheduler",
        metavar="ADDRESS",
        default=None,
        help="run on an existing Dask cluster, e.g. tcp://127.0.0.1:8786 (DIR must be shared)",
    )
    parser.add_argument(
        "--dask-workers",
        type=_positive_int,
        default=None,
        metavar="N",
        help="start a local Dask cluster of N single-threaded workers on 127.0.0.1",
    )
    parser.add_argument(
        "--out",
        metavar="DIR",
        default="results/sweep",
        help="sweep folder (default: results/sweep)",
    )
    parser.add_argument("--quiet", action="store_true", help="no progress bars")
    return parser


@one_line_errors("lfm-sweep")
def sweep_main(argv: Sequence[str] | None = None) -> int:
    """``lfm-sweep``: sweep one agent setting against a baseline (see ``--help``).

    Returns:
        The exit code: 0 if every episode ran, 1 if some raised an error.
    """
    from experiments.sweep import run_sweep, sweep_errors

    parser = _sweep_parser()
    args = parser.parse_args(argv)
    config_path = _config_path(parser, args.config)
    seeds = _seeds_and_executor(parser, args)
    out = Path(args.out)
    try:
        summary = run_sweep(
            args.agent.strip(),
            args.setting,
            seeds,
            config=config_path,
            out=out,
            baseline=args.baseline.strip(),
            jobs=args.jobs,
            scheduler=args.scheduler,
            dask_workers=args.dask_workers,
            progress=not args.quiet,
        )
    except (ValueError, ConnectionError) as exc:  # raised before any episode runs
        parser.error(" ".join(str(exc).split()))
    except KeyboardInterrupt:
        print(f"\ninterrupted; finished episodes are in {out}; rerun to resume", file=sys.stderr)
        return 130
    n_errors = sweep_errors(summary)
    print(f"sweep: {out / 'sweep.md'} and {out / 'sweep.png'} ({len(summary.values)} values)")
    if n_errors:
        print(f"{n_errors} episodes raised an error; rerun the same command to retry them")
    return 1 if n_errors else 0


# --------------------------------------------------------------------------- lfm-render

_RENDER_EPILOG = """\
Runs ONE episode (the same one lfm-evaluate runs for this agent, config and seed: the
agent's own seed is derived the same way) on the config's world and draws every step
with that world's own renderer (render_mode="rgb_array", no display needed). A .gif
gets one frame per step plus the start (1/dt frames per second); a .png gets one frame.
To look at a saved episode without re-running it, use lfm-report (figures/episode.gif).

examples:
  lfm-render --agent scenario --seed 0 --out scenario.gif
  lfm-render --config configs/quick.yaml --agent pf --seed 3 --steps 40 --out pf.png
  lfm-render --config configs/quadrotor.yaml --agent scenario --out quadrotor.gif
"""


def _render_parser() -> argparse.ArgumentParser:
    from controllers.agents import AGENT_LABELS

    agents_help = "; ".join(f"{k} = {v}" for k, v in AGENT_LABELS.items())
    parser = argparse.ArgumentParser(
        prog="lfm-render",
        description="Run one episode of an agent on the config's world and render it.",
        epilog=_RENDER_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    _add_config_argument(parser)
    parser.add_argument(
        "--agent", default="scenario", help=f"agent (default: scenario). {agents_help}"
    )
    parser.add_argument("--seed", type=int, default=0, metavar="S", help="env seed (default: 0)")
    parser.add_argument(
        "--out", required=True, metavar="FILE", help="output file, .gif (animation) or .png"
    )
    parser.add_argument(
        "--steps",
        type=_positive_int,
        default=None,
        metavar="N",
        help="stop after N steps (default: run until the episode ends)",
    )
    parser.add_argument(
        "--frame",
        choices=("last", "first"),
        default="last",
        help="which frame a .png gets (default: last)",
    )
    parser.add_argument(
        "--size",
        default="480x240",
        metavar="WxH",
        help="frame size in pixels, for worlds whose renderer takes one (default: 480x240)",
    )
    return parser


def _render_episode(
    config: object, agent_name: str, seed: int, max_steps: int | None, size: tuple[int, int]
) -> tuple[list, float]:
    """Frames ``(H, W, 3)`` of one episode rendered step by step, and ``dt`` [s]."""
    from controllers.agents import make_agent
    from experiments.evaluation import agent_seed, resolve_config
    from experiments.plots import annotate_frame, make_render_env

    cfg = resolve_config(config, [agent_name])
    # The same drawing options as the report's replay (experiments.plots.replay_frames).
    env = make_render_env(cfg, screen_size=size)  # each world's own view
    try:
        agent = make_agent(agent_name, cfg, env=env if agent_name == "oracle" else None)
        dt = env.unwrapped.model.dt
        obs, info = env.reset(seed=seed)
        agent.reset(seed=agent_seed(seed, agent_name))
        frames, k = [], 0

        def grab() -> None:
            text = f"{agent_name} | seed {seed} | t = {k * dt:.1f} s"
            frames.append(annotate_frame(env.render(), text))

        grab()
        done = False
        while not done and (max_steps is None or k < max_steps):
            obs, _, terminated, truncated, info = env.step(agent.act(obs))
            k += 1
            done = terminated or truncated
            grab()
    finally:
        env.close()
    return frames, dt


#: Largest frame side of lfm-render [px], and the memory budget of all its frames [bytes]
#: (the frames of a whole episode are kept until the GIF is written).
MAX_RENDER_SIDE = 4096
RENDER_MEMORY_BUDGET = 2 * 1024**3


@one_line_errors("lfm-render")
def render_main(argv: Sequence[str] | None = None) -> int:
    """``lfm-render``: run one episode and write it as a GIF or PNG (see ``--help``).

    Returns:
        The exit code: 0 when the file was written.
    """
    from controllers.agents import AGENTS
    from experiments.plots import write_gif

    parser = _render_parser()
    args = parser.parse_args(argv)
    out = Path(args.out)
    if out.suffix.lower() not in (".gif", ".png"):
        parser.error(f"--out {args.out}: must end in .gif or .png")
    if args.agent not in AGENTS:
        parser.error(f"--agent {args.agent}: choose one of {', '.join(AGENTS)}")
    if args.seed < 0:
        parser.error(f"--seed {args.seed}: must be >= 0")
    try:
        width, height = (int(v) for v in args.size.lower().split("x"))
        if not (16 <= width <= MAX_RENDER_SIDE and 16 <= height <= MAX_RENDER_SIDE):
            raise ValueError
    except ValueError:
        parser.error(
            f"--size {args.size[:40]}: expected WxH in pixels, each >= 16 and <= {MAX_RENDER_SIDE},"
            " e.g. 480x240"
        )
    config = _config_path(parser, args.config)
    try:
        from experiments.evaluation import resolve_config

        max_steps = resolve_config(config, [args.agent]).env.max_steps
    except ValueError as exc:  # a bad config: the loaders name the key
        parser.error(" ".join(str(exc).split()))
    n_frames = 1 + (max_steps if args.steps is None else min(args.steps, max_steps))
    need = 3 * width * height * n_frames
    if need > RENDER_MEMORY_BUDGET:
        parser.error(
            f"--size {width}x{height}: {n_frames} frames would need {need / 1024**3:.3g} GB,"
            f" over the budget of {RENDER_MEMORY_BUDGET / 1024**3:.3g} GB; use a smaller"
            " --size or fewer --steps"
        )
    problem = check_writable(out, "--out")
    if problem is not None:
        parser.error(problem)

    try:
        frames, dt = _render_episode(config, args.agent, args.seed, args.steps, (width, height))
    except ValueError as exc:  # a bad config: the loaders name the key
        parser.error(" ".join(str(exc).split()))
    if out.suffix.lower() == ".gif":
        write_gif(frames, out, fps=1.0 / dt)
    else:
        import imageio.v3 as iio

        iio.imwrite(out, frames[-1] if args.frame == "last" else frames[0])
    print(f"{out}: {len(frames)} frame(s), {len(frames) - 1} step(s) of {args.agent}")
    return 0
