"""Figures of one saved episode, drawn from the world's :class:`~lfm_env.system.ControlSystem`
only (labels, units, bounds, the feasible region from its own constraints); the figures
across seeds are :mod:`experiments.plots.summary`'s. Each returns a pyplot-free
:class:`matplotlib.figure.Figure`. Sample ``k`` is at ``t = k dt``; actions and the force act
during ``[k dt, (k+1) dt)``; the excess after step ``k`` is at ``t = (k+1) dt``.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
from matplotlib.figure import Figure
from matplotlib.patches import Ellipse

from experiments.plots.feasible_region import (
    _axis_label,
    _base_state,
    _components,
    _constraints_along,
    _crossings,
    _finish_plane_axes,
    _limits,
    _plane_figure,
    constraint_dependencies,
)
from experiments.plots.style import _step_plot, group_unit, new_figure, sample_times, unit_of
from lfm_env.system import ControlSystem, split_unit


def trajectory_figure(
    system: ControlSystem,
    true_state: np.ndarray,
    estimate: np.ndarray | None = None,
    estimate_std: np.ndarray | None = None,
    goal_state: Any = None,
    goal_radius: float | None = None,
    plane: tuple[int, int] = (0, 1),
    title: str = "",
) -> Figure:
    """The path in the plane of two states with the estimate's 2-sigma band (paper Fig. 1), over
    the feasible region of the constraints on these two states (the others at ``goal_state``).

    Args:
        system: the world's system (labels, units, constraints).
        true_state: ``(T+1, nx)`` true states in the states' units.
        estimate: ``(T, d)`` state estimates (``d >= nx``; columns as the states).
        estimate_std: ``(T, d)`` their standard deviations (a 2-sigma ellipse per step).
        goal_state: ``(nx,)`` goal state; its components in the plane are the goal.
        goal_radius: radius of a goal disc (the plane's unit); ``None`` marks a point.
        plane: the two state indices of the horizontal and vertical axes.
        title: axes title.
    """
    i, j = plane
    sets = [true_state] + ([estimate] if estimate is not None and len(estimate) else [])
    fig, ax, xlim, ylim = _plane_figure(system, sets, goal_state, goal_radius, plane)
    if estimate is not None and estimate_std is not None and len(estimate):
        for (px, py), (sx, sy) in zip(estimate[:, [i, j]], estimate_std[:, [i, j]], strict=True):
            if np.isfinite(sx) and np.isfinite(sy) and (sx > 0 or sy > 0):
                ax.add_patch(
                    Ellipse((px, py), 4 * sx, 4 * sy, facecolor="red", alpha=0.15, lw=0, zorder=3)
                )
        ax.fill_between([], [], [], color="red", alpha=0.25, label="estimate $\\pm 2\\sigma$")
    if estimate is not None and len(estimate):
        ax.plot(estimate[:, i], estimate[:, j], color="red", lw=1.3, zorder=4, label="estimate")
    ax.plot(
        true_state[:, i],
        true_state[:, j],
        color="green",
        ls="--",
        lw=1.6,
        zorder=5,
        label="true path",
    )
    ax.plot(true_state[0, i], true_state[0, j], "go", ms=4, zorder=5)
    _finish_plane_axes(ax, system, plane, xlim, ylim, title)
    return fig


def paths_figure(
    system: ControlSystem,
    paths: Mapping[str, tuple[np.ndarray, str]],
    goal_state: Any = None,
    goal_radius: float | None = None,
    plane: tuple[int, int] = (0, 1),
    title: str = "",
) -> Figure:
    """True paths of several agents (same seed, ``label -> ((T+1, nx) states, colour)``) in the
    plane of two states, with the goal (disc of ``goal_radius``, or a point).
    """
    i, j = plane
    sets = [p for p, _ in paths.values()]
    fig, ax, xlim, ylim = _plane_figure(system, sets, goal_state, goal_radius, plane)
    for label, (states, colour) in paths.items():
        ax.plot(states[:, i], states[:, j], color=colour, lw=1.3, label=label, zorder=4)
        ax.plot(states[-1, i], states[-1, j], "x", color=colour, ms=6, zorder=5)
    ax.plot([], [], "kx", ms=6, label="end of episode")
    _finish_plane_axes(ax, system, plane, xlim, ylim, title)
    return fig


def _stacked_axes(n: int, width: float = 7.0, height: float = 2.4):
    fig = new_figure(width, 0.9 + height * n)
    return fig, fig.subplots(n, 1, sharex=True, squeeze=False)[:, 0]


def _finish_stacked(fig: Figure, axes, title: str) -> Figure:
    """The time axis under the last panel of :func:`_stacked_axes` and ``title`` over the first."""
    axes[-1].set_xlabel("time [s]")
    if title:
        axes[0].set_title(title)
    return fig


def _label_panel(ax, ylabel: str, **legend: Any) -> None:
    """A panel's y label, grid and legend (``legend``: more of the legend's options)."""
    ax.set_ylabel(ylabel)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, loc="best", **legend)


def _sigma_band(ax, t: np.ndarray, mean: np.ndarray, std: np.ndarray) -> None:
    """The estimate's 2-sigma band ``mean +- 2 std`` over the times ``t``."""
    ax.fill_between(
        t,
        mean - 2 * std,
        mean + 2 * std,
        color="tab:blue",
        alpha=0.2,
        lw=0,
        label="estimate $\\pm 2\\sigma$",
    )


def latent_force_figure(
    system: ControlSystem,
    dt: float,
    latent_force: np.ndarray,
    estimate: np.ndarray | None = None,
    estimate_std: np.ndarray | None = None,
    title: str = "",
) -> Figure:
    """The true latent force (dashed) and its estimate with 2-sigma band (paper Fig. 2), one panel
    per force component.

    Args:
        system: the world's system.
        dt: sampling time [s].
        latent_force: true force in step ``k``, ``(T,)`` or ``(T, nw)``, in its units.
        estimate: the filter's estimate, shaped like ``latent_force`` (NaN: no filter).
        estimate_std: its standard deviation.
        title: title of the first panel.
    """
    nw = system.nw
    w = _components(latent_force, nw, "latent_force")
    est = None if estimate is None else _components(estimate, nw, "estimate")
    std = None if estimate_std is None else _components(estimate_std, nw, "estimate_std")
    fig, axes = _stacked_axes(nw, height=3.0 if nw == 1 else 2.4)
    t = sample_times(len(w), dt)
    for c, ax in enumerate(axes):
        name = split_unit(system.force_names[c])[0]
        ax.plot(t, w[:, c], color="tab:blue", ls="--", lw=1.5, label=f"true {name}")
        if est is not None and np.any(np.isfinite(est[:, c])):
            ax.plot(t, est[:, c], color="tab:blue", lw=1.5, label="estimate")
            if std is not None:
                _sigma_band(ax, t, est[:, c], std[:, c])
        else:
            ax.text(
                0.02,
                0.04,
                "no latent-force estimate (agent has no filter)",
                transform=ax.transAxes,
                fontsize=8,
                color="0.4",
            )
        ax.axhline(0.0, color="k", lw=0.5)
        _label_panel(ax, f"latent force {_axis_label(system.force_names[c])}")
    return _finish_stacked(fig, axes, title)


def inputs_figure(
    system: ControlSystem,
    dt: float,
    action: np.ndarray,
    latent_force: np.ndarray | None = None,
    title: str = "",
) -> Figure:
    """The applied inputs with their bounds, one panel per input (paper Fig. 3 on the track); a
    force component in an input's unit is drawn there as its negative (``-w``).

    Args:
        system: the world's system (input names, ``input_lower``/``input_upper``).
        dt: sampling time [s].
        action: ``(T, nu)`` applied inputs in the inputs' units.
        latent_force: true force, ``(T,)`` or ``(T, nw)``; ``None`` for none.
        title: title of the first panel.
    """
    u = _components(action, system.nu, "action")
    w = None if latent_force is None else _components(latent_force, system.nw, "latent_force")
    fig, axes = _stacked_axes(system.nu)
    t = sample_times(len(u), dt)
    for k, ax in enumerate(axes):
        name, unit = split_unit(system.input_names[k])
        _step_plot(ax, t, u[:, k], dt, color="tab:red", lw=1.6, label=f"input {name}")
        if w is not None and unit:
            for c, force in enumerate(system.force_names):
                if unit_of(force) != unit:
                    continue
                fname = split_unit(force)[0]
                style = {"color": "tab:blue", "lw": 1.0}
                _step_plot(ax, t, w[:, c], dt, ls="--", label=f"latent_force {fname}", **style)
                _step_plot(
                    ax, t, -w[:, c], dt, ls=":", label=f"$-${fname} (full cancellation)", **style
                )
        lo, hi = system.input_lower[k], system.input_upper[k]
        for b in (lo, hi):
            ax.axhline(b, color="k", lw=0.8, ls="-.")
        ax.plot([], [], "k-.", lw=0.8, label=f"bounds {lo:.3g} / {hi:.3g}")
        _label_panel(ax, _axis_label(system.input_names[k]), ncols=2)
    return _finish_stacked(fig, axes, title)


def _draw_state_bounds(ax, system, state: int, base: np.ndarray, ylim) -> None:
    """Shade the values of ``state`` that violate a constraint on it alone; bounds dashed."""
    which = [j for j, d in enumerate(constraint_dependencies(system)) if d == {state}]
    if not which:
        return
    s = np.linspace(ylim[0], ylim[1], 2001)
    g = _constraints_along(system, base, {state: s}, which)
    bad = np.max(g, axis=-1) > 0.0
    edges = np.flatnonzero(np.diff(np.concatenate([[0], bad.astype(int), [0]])))
    for a, b in zip(edges[::2], edges[1::2], strict=True):
        ax.axhspan(s[a], s[b - 1], color="0.88", lw=0, zorder=0)
    if bad.any():
        ax.fill_between([], [], [], color="0.88", label="infeasible ($g > 0$)")
    bounds = _crossings(s, g)
    for b in bounds:
        ax.axhline(b, color="k", ls="--", lw=1.0)
    if bounds:
        labels = ", ".join(system.constraint_labels[j] for j in which)
        ax.plot(
            [],
            [],
            "k--",
            lw=1.0,
            label=f"bounds {' / '.join(f'{b:.3g}' for b in bounds)} ({labels})",
        )


def states_figure(
    system: ControlSystem,
    dt: float,
    true_state: np.ndarray,
    estimate: np.ndarray | None = None,
    estimate_std: np.ndarray | None = None,
    states: Sequence[int] | None = None,
    goal_state: Any = None,
    title: str = "",
) -> Figure | None:
    """States over time, true (dashed) and estimated with 2-sigma band (paper Fig. 4), with the
    bounds on a state alone dashed and their infeasible side shaded.

    Args:
        system: the world's system.
        dt: sampling time [s].
        true_state: ``(T+1, nx)`` true states.
        estimate: ``(T, d)`` estimates (``d >= nx``).
        estimate_std: ``(T, d)`` their standard deviations (zeros draw no band).
        states: the state indices to draw; by default all but the first two.
        goal_state: ``(nx,)`` values of the other states where a bound is evaluated.
        title: title of the first panel.

    Returns:
        The figure, or ``None`` when there is no state to draw.
    """
    states = list(range(2, system.nx)) if states is None else [int(i) for i in states]
    if not states:
        return None
    base = _base_state(system, goal_state)
    x = np.asarray(true_state, dtype=float)
    fig, axes = _stacked_axes(len(states), height=2.4 if len(states) > 1 else 3.0)
    for i, ax in zip(states, axes, strict=True):
        name = split_unit(system.state_names[i])[0]
        ax.plot(
            sample_times(len(x), dt),
            x[:, i],
            color="tab:orange",
            ls="--",
            lw=1.6,
            label=f"true {name}",
        )
        values = [x[:, i]]
        if estimate is not None and len(estimate):
            te = sample_times(len(estimate), dt)
            e = np.asarray(estimate, dtype=float)[:, i]
            ax.plot(te, e, color="tab:blue", lw=1.4, label="estimate")
            values.append(e)
            if estimate_std is not None:
                sd = np.asarray(estimate_std, dtype=float)[:, i]
                if np.any(sd > 0):
                    _sigma_band(ax, te, e, sd)
        ylim = _limits(system, i, values, base)
        _draw_state_bounds(ax, system, i, base, ylim)
        ax.set_ylim(*ylim)
        _label_panel(ax, _axis_label(system.state_names[i]))
    return _finish_stacked(fig, axes, title)


def constraint_excess_figure(
    system: ControlSystem,
    dt: float,
    runs: Mapping[str, tuple[Mapping[str, np.ndarray], str]],
    title: str = "",
) -> Figure | None:
    """Each constraint group's excess over time (drawn at ``(k+1) dt``), one panel per group, for
    ``runs``: ``label -> ({group: (T,) excess}, colour)``; ``None`` without constraints.
    """
    groups = list(system.constraint_groups)
    if not groups:
        return None
    fig, axes = _stacked_axes(len(groups), height=2.2)
    for g, ax in zip(groups, axes, strict=True):
        for label, (excess, colour) in runs.items():
            if g not in excess:
                continue
            e = np.asarray(excess[g], dtype=float)
            ax.plot((np.arange(len(e)) + 1) * dt, e, color=colour, lw=1.3, label=label)
        ax.axhline(0.0, color="k", lw=0.6)
        unit = group_unit(system, g)
        ax.set_ylabel(f"{g} excess [{unit}]" if unit else f"{g} excess")
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=8, loc="best")
    return _finish_stacked(fig, axes, title)


def group_excess_of(
    trajectory: Mapping[str, np.ndarray], system: ControlSystem
) -> dict[str, np.ndarray]:
    """The saved ``<group>_excess`` arrays of an episode, by group (missing ones left out)."""
    return {
        g: np.asarray(trajectory[f"{g}_excess"])
        for g in system.constraint_groups
        if f"{g}_excess" in trajectory
    }


def episode_figures(
    trajectory: Mapping[str, np.ndarray],
    system: ControlSystem,
    dt: float,
    goal_state: Any = None,
    goal_radius: float | None = None,
    label: str = "",
) -> dict[str, Figure]:
    """The figures of one saved episode (arrays of :func:`experiments.evaluation.run_episode`).

    Args:
        trajectory: arrays of one episode.
        system: the world's system.
        dt: sampling time [s].
        goal_state: ``(nx,)`` goal state (the task's), in the states' units.
        goal_radius: radius of the goal disc in the plane of the first two states, if any.
        label: the agent's label, used in titles.

    Returns:
        ``name -> Figure``: ``"trajectory"``, ``"latent_force"``, ``"inputs"``, ``"states"``
        (when ``nx > 2``) and ``"constraints"`` (when there are constraints).
    """
    x = np.asarray(trajectory["true_state"])
    est = np.asarray(trajectory["estimate"])
    std = np.asarray(trajectory["estimate_std"])
    w = np.asarray(trajectory["latent_force"])
    suffix = f" - {label}" if label else ""
    plane = " / ".join(split_unit(system.state_names[i])[0] for i in (0, 1))
    figures: dict[str, Figure | None] = {
        "trajectory": trajectory_figure(
            system,
            x,
            est,
            std,
            goal_state=goal_state,
            goal_radius=goal_radius,
            title=f"Trajectory in the plane {plane}{suffix}",
        ),
        "latent_force": latent_force_figure(
            system,
            dt,
            w,
            np.asarray(trajectory["latent_force_est"]),
            np.asarray(trajectory["latent_force_std"]),
            title=f"Latent force{suffix}",
        ),
        "inputs": inputs_figure(
            system, dt, np.asarray(trajectory["action"]), w, title=f"Inputs{suffix}"
        ),
        "states": states_figure(
            system, dt, x, est, std, goal_state=goal_state, title=f"States{suffix}"
        ),
        "constraints": constraint_excess_figure(
            system,
            dt,
            {label or "excess": (group_excess_of(trajectory, system), "tab:red")},
            title=f"Constraint excess{suffix}",
        ),
    }
    return {k: f for k, f in figures.items() if f is not None}
