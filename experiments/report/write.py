"""A report of a saved results folder (never re-running an episode): ``report.md`` and a
self-contained ``report.html`` with the metrics that do not reward failing, per-agent and
paired tables with bootstrap CIs, the estimators' coverage, the chance constraint against
its design, a risk sweep's table, one episode's figures, across-seed plots, a GIF and, for
the sine track, "paper vs measured". Everything world-specific comes from the system.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from pathlib import Path

import numpy as np

from controllers.agents.registry import AGENT_REGISTRY
from experiments import plots
from experiments.evaluation.columns import tolerance_columns
from experiments.evaluation.storage import folder_in_use, warn, warnings_once
from experiments.report.chance import chance_section
from experiments.report.document import GIF_EMBED_LIMIT, Document, embedded_image
from experiments.report.figures import check_figure_seed, figures_section
from experiments.report.format import agent_label, fmt, fmt_estimate, long_label
from experiments.report.results import Results, load_results, load_trajectory, read_episodes_csv
from experiments.report.stats import (
    BOOTSTRAP_RESAMPLES,
    BOOTSTRAP_SEED,
    REFERENCE_AGENT,
    TWO_SIGMA_COVERAGE,
    Estimate,
    EstimatorCoverage,
    Metric,
    PairedDifference,
    _beyond,
    _key,
    bootstrap_ci,
    estimator_coverage,
    few_seeds_caveat,
    group_metrics,
    paired_differences,
    paired_metrics,
    paired_rows_difference,
    pooled_ratio_ci,
    summarize,
    summary_metrics,
    tolerance_metrics,
    zero_violation_metrics,
)
from experiments.report.survival import headline_counts, headline_section
from experiments.report.sweep_section import check_sweep_config, load_report_sweep, sweep_section
from lfm_env.system import split_unit

PAPER_ENV_ID = "lfm_env/SineTrack-v0"  # the paper's world: "paper vs measured" only there
#: The default baseline of the paired tables: the first of these the results hold (the
#: agent with the fewest violations we measured, then the paper's), else the first agent.
DEFAULT_BASELINES = ("robust", REFERENCE_AGENT)
#: "In plain words" names at most this many agents, one sentence each.
PLAIN_WORDS_AGENTS = 9
PAPER_SPEED_EXCESS = 0.35  # [m/s] largest speed excess over the bound reported in the paper


def _seeds(n: int) -> str:
    return f"{n} seed" if n == 1 else f"{n} seeds"


def _quantiles(values: Iterable[float], qs: Sequence[float]) -> list[float]:
    x = np.asarray(list(values), dtype=float)
    x = x[np.isfinite(x)]
    if len(x) == 0:
        return [math.nan] * len(qs)
    return [float(v) for v in np.quantile(x, qs)]


def _used_settings(results: Results) -> set[str]:
    """The agents-section settings some agent of the results reads (the registered agents'
    :attr:`~controllers.agents.registry.AgentSpec.uses`; a user's own agent names none)."""
    return {u for a in results.agents if a in AGENT_REGISTRY for u in AGENT_REGISTRY[a].uses}


_PARTICLE_FILTERS = ("bootstrap", "rbpf")  # estimators whose size is a particle count


def _settings_text(results: Results) -> str:
    """The run's settings that its agents use: ``dt`` and ``max_steps`` always, the MPC's
    horizon, scenario and particle counts and solver only when an agent present reads them."""
    cfg = results.config
    settings = results.agent_settings
    used = _used_settings(results)
    parts = [f"dt = {cfg.dt:g} s", f"max_steps = {cfg.max_steps}"]
    for key in ("horizon", "n_scenarios", "n_particles", "solver"):
        if key == "n_particles" and settings.get("estimator", "bootstrap") not in _PARTICLE_FILTERS:
            continue  # the UKF has no particles
        if key in used and key in settings:
            parts.append(f"{key} = {settings[key]}")
    if "prediction" in used and settings.get("prediction", "open_loop") != "open_loop":
        parts.append(f"prediction = {settings['prediction']}")  # (docs/feedback.md)
    robust = settings.get("robust")
    if "robust" in used and isinstance(robust, dict):
        est = robust.get("estimator", "ukf")
        text = f"robust: estimator {est}, forecast {robust.get('forecast', 'mean')}"
        if est in _PARTICLE_FILTERS:
            text += f", {robust.get('n_particles')} particles"
        parts.append(text)
    return ", ".join(parts)


def _cost_text(results: Results) -> str:
    """The MPC agents' cost as resolved (config.yaml's agents section), and whether it is the
    world's own."""
    a, env = results.agent_settings, results.config
    if not all(a.get(k) is not None for k in ("Q", "Qf", "R", "goal_state")):
        return "The agents' cost: the world's own (config.yaml names none)."
    values = {k: tuple(a[k]) for k in ("Q", "Qf", "R", "goal_state")}
    own = values == {"Q": env.Q, "Qf": env.Q, "R": env.R, "goal_state": env.goal_state}
    shown = ", ".join(f"`{k}` {list(v)}" for k, v in values.items())
    origin = "the world's own" if own else "set in the config's agents section"
    return f"The MPC agents' cost: {shown} ({origin}; the reward is the world's)."


def _model_section(doc: Document, results: Results) -> None:
    """The hidden force's kernel beside the agents' belief (learned or given), when some
    agent models the force; the hidden force alone otherwise."""
    true = results.config.latent_force
    belief = results.agent_settings.get("latent_force")
    doc.heading("Latent force: hidden truth and the agents' model")
    fields = ("kernel", "nu", "variance", "lengthscale", "discretization")
    unit = plots.force_unit(results.system)
    variance = f"variance {true.variance:g}" + (f" ({unit})^2" if unit else "")
    scale = f"lengthscale {true.lengthscale:g}" + ("" if true.kernel == "periodic" else " s")
    modelling = [a for a in results.agents if a in AGENT_REGISTRY
                 and "latent_force" in AGENT_REGISTRY[a].uses]  # fmt: skip
    if not modelling:
        doc.paragraph(
            f"The hidden force: {true.kernel} kernel, {variance}, {scale}. No agent here models "
            "it (none estimates or forecasts the force), so the agents' belief about its "
            "hyperparameters plays no part."
        )
        return
    who = ", ".join(f"`{a}`" for a in modelling)
    if not belief:
        doc.paragraph(
            f"The agents that model the force ({who}) know the hidden force's hyperparameters "
            f"a priori, as in the paper: {true.kernel} kernel, {variance}, {scale}."
        )
        return
    doc.paragraph(
        f"The agents that model the force ({who}) use their own hyperparameters "
        "(`agents.latent_force`, e.g. learned by `lfm-calibrate`), not the env's hidden ones:"
    )
    rows = []
    for f in fields:
        b = belief.get(f, "")
        rows.append([f, str(getattr(true, f)), fmt(b) if isinstance(b, float) else str(b)])
    doc.table(["hyperparameter", "hidden truth (env)", "agents' model"], rows)


def _summary_section(doc: Document, results: Results, stats: dict) -> None:
    agents = results.agents
    n_ok = {a: len(results.rows_of(a)) for a in agents}
    doc.heading("Results per agent")
    doc.paragraph(
        f"Mean over episodes with a 95% BCa bootstrap interval (bias-corrected and "
        f"accelerated, `scipy.stats.bootstrap`, {BOOTSTRAP_RESAMPLES} resamples, fixed seed "
        f"{BOOTSTRAP_SEED}; the percentile interval where BCa is undefined, a zero-width one "
        "where every value is equal), in brackets. "
        "Episodes that ended with an error are counted in the last row and listed below, "
        "but left out of the statistics; `(n=k)` marks a metric defined on fewer episodes "
        "(e.g. time to goal only where the goal was reached). The oracle is "
        "certainty-equivalent MPC that reads the hidden true state and future latent force: "
        "no controller one could build, and no upper bound either. Violation steps `> t` "
        "count only the steps whose excess over the "
        "group's bounds is above the tolerance t (a millimetre over a bound is not a crash); "
        "zero-violation episodes are the fraction of episodes with no such step."
        + _caveat(min(n_ok.values(), default=0))
    )
    header = ["metric"] + [agent_label(a) for a in agents]
    rows = []
    for m in _reported(results, summary_metrics(results.system)):
        rows.append([m.title] + [fmt_estimate(stats[a][_key(m)], n_ok[a]) for a in agents])
    rows.append(["episodes (error-free)"] + [str(n_ok[a]) for a in agents])
    rows.append(
        ["episodes with errors"]
        + [str(len(results.rows_of(a, include_errors=True)) - n_ok[a]) for a in agents]
    )
    doc.table(header, rows)


def _errors_section(doc: Document, results: Results) -> None:
    errors = results.error_rows
    if not errors:  # (the per-agent table says 0 in its last row)
        return
    doc.heading("Episodes with errors")
    doc.paragraph(
        f"{len(errors)} episode(s) ended with an error; they are left out of the statistics."
    )
    doc.table(
        ["agent", "seed", "error"],
        [[agent_label(r["agent"]), str(r["seed"]), r["error"][:300]] for r in errors],
    )


def _damaged_section(doc: Document, results: Results) -> None:
    """The episode files that did not load, left out of the figures (the table's rows of
    those episodes are kept: the statistics read ``episodes.csv``)."""
    if not results.damaged:
        return
    doc.heading("Damaged episode files")
    doc.paragraph(
        f"{len(results.damaged)} episode file(s) did not load and are left out of the figures "
        "and of the pooled solve times (their rows in episodes.csv are kept); rerunning the "
        "evaluation into this folder runs those episodes again."
    )
    doc.table(
        ["file", "why"], [[path.name, why[-300:]] for path, why in sorted(results.damaged.items())]
    )


def _reported(results: Results, metrics: Sequence[Metric]) -> list[Metric]:
    """``metrics`` without the tolerance-aware ones that no error-free episode holds (an
    older table whose episodes have no saved trajectory to count them from)."""
    tolerance = {c for _, _, c in tolerance_columns(results.system)}
    return [
        m
        for m in metrics
        if m.column not in tolerance
        or any(np.isfinite(r.get(m.column, math.nan)) for r in results.rows if not r["error"])
    ]


def choose_baseline(results: Results, baseline: str | None = None) -> str:
    """The report's one baseline for every paired table: ``baseline``, else the first of
    :data:`DEFAULT_BASELINES` present, else the first agent.

    Raises:
        ValueError: naming ``baseline`` and the results' agents, if it is not among them.
    """
    if baseline is None:
        held = [a for a in DEFAULT_BASELINES if a in results.agents]
        return held[0] if held else results.agents[0]
    if baseline not in results.agents:
        raise ValueError(
            f"baseline {baseline!r} is not an agent of {results.directory}; choose one of "
            + ", ".join(results.agents)
        )
    return baseline


def _paired_section(doc: Document, results: Results, baseline: str) -> list[PairedDifference]:
    """Every paired metric of every other agent against ``baseline``; nothing when the
    results hold one agent."""
    others = [a for a in results.agents if a != baseline]
    if not others:
        return []
    doc.heading(f"Paired differences against {agent_label(baseline)}")
    metrics = _reported(results, paired_metrics(results.system))
    found = {
        (a, m.column): paired_differences(results, m, a, baseline) for a in others for m in metrics
    }
    paired_seeds = max((len(d.seeds) for d in found.values()), default=0)
    doc.paragraph(
        f"Difference `agent - {baseline}` on the same env seeds (same latent force and "
        "noise), mean with a 95% paired BCa bootstrap interval over seeds (the two episodes "
        f"of a seed resampled together). Negative: the agent's value is lower than "
        f"{baseline}'s. Only seeds where both episodes are error-free "
        "and the metric is defined count. The baseline, the same in every paired table of "
        "this report, is chosen with `--baseline NAME` (`lfm-report`, `lfm-evaluate`)."
        + _caveat(paired_seeds)
    )
    rows = []
    for m in metrics:
        cells = []
        for agent in others:
            d = found[(agent, m.column)]
            n = len(d.seeds)
            cells.append(fmt_estimate(d.estimate) + (f" ({_seeds(n)})" if n else ""))
        rows.append([m.title, *cells])
    doc.table(["metric"] + [agent_label(a) for a in others], rows)
    doc.paragraph("In plain words:")
    doc.bullets(_plain_words(results, found, others, metrics, baseline))
    return list(found.values())


def _plain_words(
    results: Results,
    found: dict[tuple[str, str], PairedDifference],
    others: Sequence[str],
    metrics: Sequence[Metric],
    baseline: str,
) -> list[str]:
    """One sentence per agent (at most :data:`PLAIN_WORDS_AGENTS`): on how many seeds the
    baseline does better in the first group's headline count and in time to goal; the
    rest is in the table."""
    columns = [m.column for m in metrics]
    head = headline_counts(results.system)
    first = head[0].column if head and head[0].column in columns else "cost"
    chosen = [m for m in metrics if m.column in (first, "time_to_goal")]
    out = []
    for agent in others[:PLAIN_WORDS_AGENTS]:
        parts = []
        for m in chosen:
            d = found[(agent, m.column)]
            if d.seeds:
                parts.append(
                    f"{m.fewer} on {d.reference_lower} of {_seeds(len(d.seeds))} (the opposite "
                    f"on {d.agent_lower}, equal on {d.ties})"
                )
        if parts:
            out.append(f"`{baseline}` has " + ", and ".join(parts) + f" than `{agent}`.")
        else:
            out.append(f"`{baseline}` and `{agent}` have no error-free seed in common.")
    if len(others) > PLAIN_WORDS_AGENTS:
        out.append("The other agents are compared in the table above.")
    return out


def _paper_vs_measured_section(doc: Document, results: Results, solve_times: np.ndarray) -> None:
    """The paper's reported results beside the measured distribution (sine track only)."""
    agent = REFERENCE_AGENT
    rows = results.rows_of(agent)
    if not rows:  # the paper's agent not run (or every episode of it raised)
        return
    doc.heading("Paper vs measured")
    n = len(rows)
    dt = results.config.dt
    track_steps = np.array([r.get("track_violation_steps", math.nan) for r in rows])
    zero_track = int(np.sum(track_steps == 0))
    speed = np.array([r.get("max_speed_excess", math.nan) for r in rows])
    med, p05, p95 = _quantiles(speed, (0.5, 0.05, 0.95))
    within = int(np.sum(speed <= PAPER_SPEED_EXCESS))
    if len(solve_times):
        st_med, st_p95 = np.quantile(solve_times, [0.5, 0.95])
        over = float(np.mean(solve_times > dt))
        st_source = f"{len(solve_times)} solves pooled over {n} episodes"
    else:  # no saved arrays: fall back to the per-episode statistics of the table
        st_med = _quantiles([r.get("solve_time_median") for r in rows], (0.5,))[0]
        st_p95 = _quantiles([r.get("solve_time_p95") for r in rows], (0.5,))[0]
        over = math.nan
        st_source = f"median over {n} episodes of the per-episode median / p95"
    doc.paragraph(
        f"The paper reports one run (MATLAB, fmincon, 150 scenarios, 7000 particles); here "
        f"{n} seeds of `{agent}` with {_settings_text(results)}. The tolerance-aware counts "
        "take a step as a violation only when the excess is above the tolerance, so that "
        "millimetre crossings, which even the oracle makes, do not hide the real ones."
    )
    doc.table(
        ["quantity", "paper (one run)", f"measured ({n} episodes)"],
        [
            [
                "track (position) constraints",
                "met at every step",
                f"zero track violations in {zero_track} of {n} episodes "
                f"({100.0 * zero_track / n:.0f}%)" + _tolerance_aware_text(results, rows, "track"),
            ],
            [
                "largest speed excess over the bounds [m/s]",
                f"{PAPER_SPEED_EXCESS:g}",
                f"median {fmt(med)}, 90% range [{fmt(p05)}, {fmt(p95)}]; "
                f"<= {PAPER_SPEED_EXCESS:g} in {within} of {n} episodes"
                + _tolerance_aware_text(results, rows, "speed"),
            ],
            [
                f"solve time per step vs sampling time {dt:g} s",
                "much slower than the sampling time",
                f"median {fmt(st_med)} s, p95 {fmt(st_p95)} s "
                f"({fmt(st_med / dt)}x / {fmt(st_p95 / dt)}x the sampling time"
                + (
                    f"; {100.0 * over:.0f}% of solves slower than {dt:g} s"
                    if np.isfinite(over)
                    else ""
                )
                + f"; {st_source})",
            ],
        ],
    )


def _coverage_section(doc: Document, results: Results) -> None:
    """The estimators' 2-sigma coverage and RMSE per state and force, table and figure."""
    cals = estimator_coverage(results)
    if not cals:  # no agent with a filter, or none saved its trajectories
        return
    doc.heading("Estimator coverage")
    doc.paragraph(
        "How well each filtering agent's estimator knows the state and the latent force it "
        "does not see: the fraction of steps with the truth inside the estimate's 2-sigma "
        f"band (a Gaussian band of the right width covers {TWO_SIGMA_COVERAGE:g}; less is "
        "overconfident) and the root-mean-square error, both pooled over steps and "
        f"episodes, with a 95% BCa bootstrap interval over whole episodes ({BOOTSTRAP_RESAMPLES} "
        "resamples). The estimate made from the measurement at step k is compared with the "
        "true state at step k, the force estimate with the force acting during step k."
    )
    header = ["quantity"] + [f"{agent_label(c.agent)}: `{c.estimator}`" for c in cals]
    rows = []
    for i, q in enumerate(cals[0].quantities):
        cells = [fmt_estimate(c.coverage[i]) for c in cals]
        rows.append([f"2-sigma coverage, {split_unit(q)[0]}", *cells])
    for i, q in enumerate(cals[0].quantities):
        rows.append([f"RMSE, {q}", *(fmt_estimate(c.rmse[i]) for c in cals)])
    rows.append(["episodes / steps"] + [f"{c.episodes} / {c.steps}" for c in cals])
    doc.table(header, rows)
    from_config = [agent_label(c.agent) for c in cals if c.estimator_source != "recorded"]
    if from_config:
        doc.paragraph(
            "The estimator of " + ", ".join(from_config) + " is the `agents.estimator` of "
            "config.yaml (its episodes did not record one); the others recorded theirs."
        )
    coverage = np.array([[[e.mean, e.low, e.high] for e in c.coverage] for c in cals])
    rmse = np.array([[[e.mean, e.low, e.high] for e in c.rmse] for c in cals])
    agents = {f"{agent_label(c.agent)} ({c.estimator})": plots.agent_colour(c.agent) for c in cals}
    fig = plots.coverage_figure(cals[0].quantities, agents, coverage, rmse, TWO_SIGMA_COVERAGE)
    rel = "figures/estimator_coverage.png"
    plots.save_figure(fig, results.directory / rel)
    doc.image(
        rel,
        "Estimator coverage side by side: 2-sigma coverage (top, dashed: that of a band of "
        "the right width) and RMSE (bottom) per state and for the latent force.",
    )


def _tolerance_aware_text(results: Results, rows: Sequence[dict], group: str) -> str:
    """``"; tolerance-aware: ..."``: per tolerance of ``group``, the zero-violation episodes
    and the mean violation steps beyond it; ``""`` when the rows hold none."""
    parts = []
    for g, t, column in tolerance_columns(results.system):
        steps = np.array([r.get(column, math.nan) for r in rows], dtype=float)
        steps = steps[np.isfinite(steps)]
        if g != group or not len(steps):
            continue
        zero = int(np.sum(steps == 0))
        parts.append(
            f"beyond {_beyond(results.system, g, t)[2:]}: zero in {zero} of {len(steps)} "
            f"episodes ({100.0 * zero / len(steps):.0f}%), {fmt(float(steps.mean()))} "
            "violation steps per episode"
        )
    return "; tolerance-aware, " + "; ".join(parts) if parts else ""


def _caveat(n_seeds: int) -> str:
    """`` ``+ the few-seeds caveat (:func:`~experiments.report.stats.few_seeds_caveat`), or
    ``""``."""
    text = few_seeds_caveat(n_seeds)
    return f" **{text}**" if text else ""


def _pooled_solve_times(results: Results, agent: str) -> np.ndarray:
    """All per-step solve times [s] of an agent's saved episodes (empty if any is missing)."""
    chunks = []
    for row in results.rows_of(agent):
        traj = load_trajectory(results, agent, row["seed"])
        if traj is None and results.trajectory_path(agent, row["seed"]) in results.damaged:
            continue  # (named in the report)
        if traj is None or "solve_time" not in traj:
            return np.zeros(0)
        chunks.append(np.asarray(traj["solve_time"], dtype=float))
    st = np.concatenate(chunks) if chunks else np.zeros(0)
    return st[np.isfinite(st)]


def write_report(
    results_dir: str | Path,
    figure_seed: int | None = None,
    gif: bool = True,
    sweep_dir: str | Path | None = None,
    baseline: str | None = None,
    allow_other_config: bool = False,
) -> Path:
    """Write ``report.md`` and ``report.html`` (figures embedded) of a results folder.

    Args:
        results_dir: folder with ``episodes.csv``, ``episodes/`` and ``config.yaml``.
        figure_seed: env seed of the episode figures and GIF; by default the smallest seed
            with a saved trajectory of the scenario agent.
        gif: also write ``figures/episode.gif``.
        sweep_dir: a risk sweep folder to include; by default ``results_dir`` if it holds
            a ``sweep.md``.
        baseline: the agent every paired table compares with (:func:`choose_baseline`).
        allow_other_config: include a sweep of another base config (listing the fields).

    Returns:
        Path of ``report.md`` (figures in ``figures/``).

    Raises:
        FileNotFoundError: if the folder, ``episodes.csv`` or ``config.yaml`` is missing.
        ValueError: no episodes, ``figure_seed`` without a trajectory, an unknown
            ``baseline`` or a sweep of another config (listing them).
    """
    with warnings_once():  # (a damaged file is read by several sections)
        return _write_report(results_dir, figure_seed, gif, sweep_dir, baseline, allow_other_config)


def _write_report(
    results_dir: str | Path,
    figure_seed: int | None,
    gif: bool,
    sweep_dir: str | Path | None,
    baseline: str | None,
    allow_other_config: bool,
) -> Path:
    """:func:`write_report`'s work."""
    owner = folder_in_use(results_dir)
    if owner is not None:
        warn(
            f"results folder {str(results_dir)!r} is still being written by {owner}; the "
            "report holds the episodes finished so far"
        )
    results = load_results(results_dir)
    baseline = choose_baseline(results, baseline)
    check_figure_seed(results, figure_seed)  # before writing any file
    sweep = load_report_sweep(results.directory, sweep_dir)
    differences = [] if sweep is None else check_sweep_config(results, sweep, allow_other_config)
    stats = summarize(results)
    doc = Document()
    title = f"Evaluation report: {results.directory.name}"
    doc.heading(title, 1)
    n_eps = len(results.rows)
    seeds = sorted({r["seed"] for r in results.rows})
    doc.paragraph(
        f"{n_eps} episodes of {len(results.agents)} agents on {len(seeds)} env seeds "
        f"({seeds[0]}..{seeds[-1]}) of the world `{results.config.ENV_ID}` (system "
        f"`{results.system.name}`); {_settings_text(results)}. On one env seed every agent "
        "faces the same hidden latent force and noise." + _caveat(len(seeds)) + " Agents:"
    )
    doc.bullets([f"`{a}`: {long_label(a)}" for a in results.agents])
    doc.paragraph(_cost_text(results))
    _model_section(doc, results)
    headline_section(doc, results, baseline)  # survival-unbiased metrics
    _summary_section(doc, results, stats)
    _errors_section(doc, results)
    _paired_section(doc, results, baseline)
    if results.config.ENV_ID == PAPER_ENV_ID and REFERENCE_AGENT in results.agents:
        _paper_vs_measured_section(doc, results, _pooled_solve_times(results, REFERENCE_AGENT))
    _coverage_section(doc, results)
    chance_section(doc, results)  # the chance constraint against its design
    if sweep is not None:
        sweep_section(doc, results, sweep, differences)
    figures_section(doc, results, figure_seed, gif)
    _damaged_section(doc, results)
    if owner is not None:
        doc.paragraph(
            f"Written while the results folder was still being written by {owner}: the "
            "report holds the episodes finished by then."
        )

    md_path = results.directory / "report.md"
    md_path.write_text(doc.markdown())
    (results.directory / "report.html").write_text(doc.html(title, results.directory))
    return md_path


__all__ = [
    "Document",
    "GIF_EMBED_LIMIT",
    "embedded_image",
    "Metric",
    "Estimate",
    "PairedDifference",
    "Results",
    "EstimatorCoverage",
    "agent_label",
    "bootstrap_ci",
    "estimator_coverage",
    "choose_baseline",
    "load_results",
    "load_trajectory",
    "group_metrics",
    "paired_differences",
    "paired_metrics",
    "paired_rows_difference",
    "pooled_ratio_ci",
    "read_episodes_csv",
    "summarize",
    "summary_metrics",
    "tolerance_metrics",
    "write_report",
    "zero_violation_metrics",
]
