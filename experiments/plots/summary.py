"""Across-seed figures: metric distributions per agent, solve times, estimator
coverage and the risk sweep's Pareto picture.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np
from matplotlib.figure import Figure
from matplotlib.patches import Patch

from experiments.plots.style import agent_colour, new_figure, unit_of
from lfm_env.system import split_unit

TICK_LABEL_CHARS = 30  # longest tick label of an agent; longer ones keep their end


def tick_label(label: str) -> str:
    """``label`` on one line, cut to its last :data:`TICK_LABEL_CHARS` characters with an
    ellipsis when longer (``"...own_agents:Factory"``: the end names the agent)."""
    text = " ".join(str(label).split())
    if len(text) <= TICK_LABEL_CHARS:
        return text
    return "\u2026" + text[-(TICK_LABEL_CHARS - 1) :]


def distribution_axes(
    ax,
    values: Mapping[str, np.ndarray],
    colours: Sequence[str] | None = None,
    log: bool = False,
    seed: int = 0,
) -> None:
    """Box plot per group (``label -> values``, NaN left out) with the values as a jittered strip
    (seeded), optionally on a log scale.
    """
    rng = np.random.default_rng(seed)
    labels = list(values)
    data = []
    for v in values.values():
        v = np.asarray(v, dtype=float)
        v = v[np.isfinite(v)]
        if log:
            v = v[v > 0]
        data.append(v)
    positions = np.arange(1, len(labels) + 1)
    nonempty = [i for i, d in enumerate(data) if len(d)]
    if nonempty:
        ax.boxplot(
            [data[i] for i in nonempty],
            positions=positions[nonempty],
            widths=0.5,
            showfliers=False,
            medianprops={"color": "k"},
        )
    for i, d in enumerate(data):
        colour = colours[i] if colours else None
        if len(d):
            jitter = rng.uniform(-0.15, 0.15, size=len(d))
            ax.scatter(positions[i] + jitter, d, s=14, alpha=0.75, color=colour, zorder=3)
        else:
            ax.text(
                positions[i],
                0.5,
                "n/a",
                ha="center",
                va="center",
                transform=ax.get_xaxis_transform(),
                color="0.5",
            )
    # Slanted, one line each and at most TICK_LABEL_CHARS long, so that six agents (or an
    # agent named by its import path) do not run into each other.
    short = [tick_label(label) for label in labels]
    ax.set_xticks(positions, short, fontsize=8, rotation=30, ha="right", rotation_mode="anchor")
    ax.set_xlim(0.4, len(labels) + 0.6)
    if log:
        ax.set_yscale("log")
    ax.grid(axis="y", alpha=0.3)


def metric_distributions_figure(
    metrics: Mapping[str, Mapping[str, np.ndarray]],
    agent_names: Sequence[str],
    ncols: int = 3,
    log_scale: Sequence[str] = (),
) -> Figure:
    """A grid of per-agent distributions over seeds, one panel per metric
    (``axis label -> {agent label -> values}``); ``log_scale``: the panels on a log axis.
    """
    n = len(metrics)
    nrows = int(np.ceil(n / ncols))
    fig = new_figure(4.0 * ncols, 3.2 * nrows)
    axes = fig.subplots(nrows, ncols, squeeze=False).ravel()
    colours = [agent_colour(a) for a in agent_names]
    for ax, (ylabel, values) in zip(axes, metrics.items(), strict=False):
        distribution_axes(ax, values, colours, log=ylabel in log_scale)
        ax.set_ylabel(ylabel)
    for ax in axes[n:]:
        ax.set_visible(False)
    fig.suptitle("Distributions over seeds (one point per episode)")
    return fig


def solve_time_figure(
    median: Mapping[str, np.ndarray],
    p95: Mapping[str, np.ndarray],
    agent_names: Sequence[str],
    dt: float,
) -> Figure:
    """Per-episode solve-time median and 95th percentile [s] per agent label, log scale, with the
    sampling time ``dt`` [s] as the real-time limit.
    """
    fig = new_figure(10.0, 3.6)
    axes = fig.subplots(1, 2, sharey=True)
    colours = [agent_colour(a) for a in agent_names]
    for ax, (title, values) in zip(
        axes, (("median per episode", median), ("95th percentile per episode", p95)), strict=True
    ):
        distribution_axes(ax, values, colours, log=True)
        ax.axhline(dt, color="red", ls="--", lw=1.0, label=f"sampling time {dt:g} s")
        ax.set_title(f"Solve time: {title}")
        ax.legend(fontsize=8, loc="best")
    axes[0].set_ylabel("solve time per step [s]")
    return fig


def _interval_errors(values: np.ndarray) -> np.ndarray:
    """Error-bar lengths ``(2, n)`` below and above from ``(n, 3)`` rows (mean, low, high)."""
    v = np.asarray(values, dtype=float).reshape(-1, 3)
    return np.vstack([v[:, 0] - v[:, 1], v[:, 2] - v[:, 0]])


def coverage_figure(
    quantities: Sequence[str],
    agents: Mapping[str, str],
    coverage: np.ndarray,
    rmse: np.ndarray,
    nominal: float = 0.9545,
) -> Figure:
    """Estimators side by side: 2-sigma coverage (top) and RMSE (bottom) per quantity.

    Args:
        quantities: ``Q`` labels with units (the states, then the latent force).
        agents: ``label -> colour`` of the ``A`` agents.
        coverage: ``(A, Q, 3)`` mean, low and high of the 2-sigma coverage (a fraction).
        rmse: ``(A, Q, 3)`` mean, low and high of the RMSE [the quantity's unit].
        nominal: the coverage of a calibrated 2-sigma band, drawn dashed.
    """
    coverage = np.asarray(coverage, dtype=float)
    rmse = np.asarray(rmse, dtype=float)
    n_q, labels = len(quantities), list(agents)
    fig = new_figure(max(6.0, 2.4 * n_q), 5.4)
    axes = fig.subplots(2, n_q, squeeze=False)
    x = np.arange(len(labels))
    colours = [agents[a] for a in labels]
    lowest = np.nanmin(coverage[..., 1]) if np.isfinite(coverage[..., 1]).any() else nominal
    for q, name in enumerate(quantities):
        top, bottom = axes[0, q], axes[1, q]
        for ax, values in ((top, coverage[:, q]), (bottom, rmse[:, q])):
            ax.bar(x, values[:, 0], color=colours, alpha=0.8, label=None)
            ax.errorbar(x, values[:, 0], yerr=_interval_errors(values), fmt="none", ecolor="k")
            ax.set_xticks(x, [])
            ax.grid(axis="y", alpha=0.3)
        top.axhline(nominal, color="k", ls="--", lw=1.0)
        top.set_ylim(max(0.0, min(0.8, lowest - 0.05)), 1.005)
        top.set_title(split_unit(name)[0], fontsize=9)
        unit = unit_of(name)
        bottom.set_ylabel(f"RMSE [{unit}]" if unit else "RMSE", fontsize=8)
    axes[0, 0].set_ylabel(f"2-sigma coverage\n(dashed: {nominal:g})", fontsize=8)
    handles = [Patch(color=c, alpha=0.8, label=a) for a, c in agents.items()]
    fig.legend(handles=handles, loc="outside lower center", ncols=min(len(labels), 4), fontsize=8)
    fig.suptitle("Estimator coverage (bars: pooled over steps; whiskers: 95% over episodes)")
    return fig


def pareto_figure(
    points: Sequence[tuple[str, np.ndarray, np.ndarray]],
    baseline: str,
    xlabel: str,
    ylabel: str,
    title: str = "",
) -> Figure:
    """The risk trade-off: paired differences to ``baseline`` (at the origin), one point per
    setting: ``(label, x, y)``, each ``(mean, low, high)``; NaN points left out.
    """
    fig = new_figure(6.4, 4.8)
    ax = fig.subplots()
    ax.axhline(0.0, color="0.6", lw=0.8, ls="--")
    ax.axvline(0.0, color="0.6", lw=0.8, ls="--")
    ax.plot([0.0], [0.0], marker="*", ms=16, color="k", ls="none", label=f"{baseline} (baseline)")
    colours = [f"C{i % 10}" for i in range(len(points))]
    drawn = []
    for (label, xv, yv), colour in zip(points, colours, strict=True):
        xv, yv = np.asarray(xv, dtype=float), np.asarray(yv, dtype=float)
        if not (np.isfinite(xv[0]) and np.isfinite(yv[0])):
            continue
        ax.errorbar(
            xv[0],
            yv[0],
            xerr=_interval_errors(xv),
            yerr=_interval_errors(yv),
            fmt="o",
            color=colour,
            capsize=3,
            label=label,
        )
        ax.annotate(label, (xv[0], yv[0]), textcoords="offset points", xytext=(6, 6), fontsize=8)
        drawn.append((xv[0], yv[0]))
    if len(drawn) > 1:  # the settings in the order given: the knob's path
        d = np.array(drawn)
        ax.plot(d[:, 0], d[:, 1], color="0.5", lw=0.8, zorder=0)
    ax.margins(0.15)  # room for the labels beside the outermost points
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, loc="best")
    if title:
        ax.set_title(title, fontsize=10)
    return fig
