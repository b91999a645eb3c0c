"""The chance-constraint figure: violation probability per step of the horizon, per
constraint group, beside the design's violation level."""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np
from matplotlib.figure import Figure

from experiments.plots.style import new_figure


def chance_figure(
    panels: Sequence[str],
    agents: Mapping[str, str],
    offline: np.ndarray,
    closed_loop: np.ndarray,
    levels: Mapping[str, float],
) -> Figure:
    """One panel per constraint group (and the joint event): probability against step k.

    Args:
        panels: ``P`` panel titles.
        agents: ``label -> colour`` of the ``A`` agents.
        offline: ``(A, P, N, 3)`` mean, low, high of the offline probability at ``k = 1..N``.
        closed_loop: ``(A, P, 3)`` the closed-loop probability at ``k = 1`` (NaN: none).
        levels: ``label -> probability`` drawn dashed (the designs' epsilon).
    """
    offline = np.asarray(offline, dtype=float)
    closed_loop = np.asarray(closed_loop, dtype=float)
    labels = list(agents)
    n_p, n_k = len(panels), offline.shape[2]
    cols = min(n_p, 2)
    rows = int(np.ceil(n_p / cols))
    fig = new_figure(5.2 * cols, 3.3 * rows + 0.8)
    axes = np.atleast_1d(fig.subplots(rows, cols, squeeze=False)).ravel()
    k = np.arange(1, n_k + 1)
    styles = ("--", ":", "-.")
    for p, title in enumerate(panels):
        ax = axes[p]
        for a, label in enumerate(labels):
            colour = agents[label]
            m = offline[a, p]
            if np.isfinite(m[:, 0]).any():
                ax.plot(k, m[:, 0], color=colour, marker="o", ms=3, lw=1.4, label=label)
                ax.fill_between(k, m[:, 1], m[:, 2], color=colour, alpha=0.15, lw=0)
            c = closed_loop[a, p]
            if np.isfinite(c[0]):
                x = 1.0 - 0.06 * (a + 1)
                err = [[max(c[0] - c[1], 0.0)], [max(c[2] - c[0], 0.0)]]
                ax.errorbar([x], [c[0]], yerr=err, color=colour, marker="s", ms=4, capsize=2)
        for i, (name, level) in enumerate(levels.items()):
            if np.isfinite(level):
                ax.axhline(level, color="k", ls=styles[i % len(styles)], lw=1.0, label=name)
        ax.set_title(title, fontsize=9)
        ax.set_xticks(k)
        ax.set_xlim(1.0 - 0.06 * (len(labels) + 1), n_k + 0.2)
        ax.set_ylim(bottom=0.0)
        ax.grid(alpha=0.3)
        ax.set_xlabel("prediction step k", fontsize=8)
    for ax in axes[n_p:]:
        ax.set_visible(False)
    axes[0].set_ylabel("P(true state violates)", fontsize=8)
    handles, names = axes[0].get_legend_handles_labels()
    fig.legend(handles, names, loc="outside lower center", ncols=min(len(names), 4), fontsize=7)
    fig.suptitle(
        "Chance constraint: lines offline (open-loop plan, true force's law), squares closed "
        "loop at k = 1; bands and whiskers 95% over episodes",
        fontsize=9,
    )
    return fig
