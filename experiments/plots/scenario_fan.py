"""What scenario MPC plans: the saved scenario predictions of an episode (``predicted_scenarios``
``(T, S, N+1, nx)``, or older files' first scenario ``predicted``, a fan of one), drawn at a
few steps over the feasible region (:func:`scenario_fan_figure`) or at every step for the
episode's GIF (:func:`plan_panel_frames`).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
from matplotlib.collections import LineCollection
from matplotlib.figure import Figure
from matplotlib.patches import Ellipse

from experiments.plots.feasible_region import (
    _axis_label,
    _base_state,
    _draw_feasible_region,
    _draw_goal,
    _plane_limits,
)
from experiments.plots.style import new_figure, unit_of
from lfm_env.system import ControlSystem

FAN_COLOUR = "tab:blue"
PLAN_COLOUR = "navy"


def saved_fans(trajectory: Mapping[str, np.ndarray]) -> tuple[np.ndarray, bool]:
    """The saved scenario predictions ``(T, S, N+1, nx)`` of an episode, and whether they
    are the compact fan (``False``: an older file, only the first scenario, ``S = 1``)."""
    if "predicted_scenarios" in trajectory:
        return np.asarray(trajectory["predicted_scenarios"], dtype=float), True
    predicted = np.asarray(trajectory.get("predicted", np.zeros((0, 1, 0))), dtype=float)
    return predicted[:, None], False


def fan_steps(fans: np.ndarray, n: int = 4) -> list[int]:
    """``n`` steps spread evenly over the episode among those with a finite prediction."""
    finite = [k for k in range(len(fans)) if np.isfinite(fans[k]).all(axis=(1, 2)).any()]
    if not finite:
        return []
    picks = np.linspace(0, len(finite) - 1, min(n, len(finite)))
    return sorted({finite[int(round(p))] for p in picks})


def _finite_fan(fan: np.ndarray, plane: tuple[int, int]) -> np.ndarray:
    """The scenarios of one step ``(S, N+1, 2)`` in the plane, NaN-padded ones left out."""
    pts = fan[..., list(plane)]
    return pts[np.all(np.isfinite(pts), axis=(1, 2))]


def _window(points: np.ndarray, aspect: float, min_half: float) -> tuple[tuple, tuple]:
    """Limits around ``points`` ``(n, 2)`` with height / width = ``aspect``, padded."""
    lo, hi = np.nanmin(points, axis=0), np.nanmax(points, axis=0)
    centre = 0.5 * (lo + hi)
    half_x = max(0.5 * (hi[0] - lo[0]), 0.5 * (hi[1] - lo[1]) / aspect, min_half) * 1.3
    half_y = half_x * aspect
    return (centre[0] - half_x, centre[0] + half_x), (centre[1] - half_y, centre[1] + half_y)


def _draw_estimate(ax, mean: np.ndarray, std: np.ndarray, label: str | None) -> None:
    """The estimate at one step: a red dot and its 2-sigma ellipse."""
    if np.all(np.isfinite(std)) and np.any(std > 0):
        ax.add_patch(Ellipse(tuple(mean), 4 * std[0], 4 * std[1], facecolor="red", alpha=0.2, lw=0))
    ax.plot(*mean, "o", color="red", ms=4, zorder=6, label=label)


def _draw_fan(ax, fan: np.ndarray, label: str | None = None) -> None:
    """The scenarios' predicted paths (thin blue), their end points and their mean (navy)."""
    ax.add_collection(
        LineCollection(
            list(fan), colors=FAN_COLOUR, linewidths=0.8, alpha=0.6, zorder=3, label=label
        )
    )
    if len(fan):
        ax.plot(*fan[:, -1].T, ".", color=FAN_COLOUR, ms=3, zorder=4)
        ax.plot(
            *fan.mean(axis=0).T, color=PLAN_COLOUR, lw=1.6, zorder=4, label="mean of the scenarios"
        )


def _zoom_on_fan_end(ax, fan: np.ndarray, xlim: tuple, ylim: tuple) -> float:
    """An inset magnifying the fan's last steps when it is too narrow to see at the
    panel's scale; returns the fan's width at its end (largest distance of two end
    points, in the plane's unit)."""
    if len(fan) < 2:
        return 0.0
    ends = fan[:, -1]
    spread = float(np.max(np.linalg.norm(ends[:, None] - ends[None], axis=-1)))
    width = xlim[1] - xlim[0]
    if not 0.0 < spread < 0.08 * width:
        return spread
    centre = ends.mean(axis=0)
    half = 0.9 * spread
    # The inset goes in the corner away from the fan's end, so it hides none of it.
    right = centre[0] < 0.5 * (xlim[0] + xlim[1])
    top = centre[1] < 0.5 * (ylim[0] + ylim[1])
    box = (0.6 if right else 0.02, 0.52 if top else 0.03, 0.38, 0.45)
    inset = ax.inset_axes(box, zorder=10)
    _draw_fan(inset, fan)
    inset.set_xlim(centre[0] - half, centre[0] + half)
    inset.set_ylim(centre[1] - half, centre[1] + half)
    inset.set_aspect("equal", adjustable="box")
    inset.tick_params(labelsize=6)
    inset.set_title(f"its end, magnified x{width / (2 * half):.0f}", fontsize=7, pad=3)
    return spread


def scenario_fan_figure(
    system: ControlSystem,
    trajectory: Mapping[str, np.ndarray],
    dt: float,
    steps: Sequence[int] | None = None,
    goal_state: Any = None,
    goal_radius: float | None = None,
    plane: tuple[int, int] = (0, 1),
    title: str = "",
) -> Figure | None:
    """The scenario fan of the plan at a few steps, one panel each, over the feasible region:
    the predictions and their mean, the estimate with its 2-sigma ellipse, the true path so far
    and over the next ``N`` steps, to scale.

    Args:
        system: the world's system (labels, constraints).
        trajectory: the arrays of one saved episode.
        dt: sampling time [s].
        steps: the steps drawn; ``None`` for four spread over the episode.
        goal_state: ``(nx,)`` goal state (the unplotted states of the region take it).
        goal_radius: radius of the goal disc in the plane, if the world has one.
        plane: the two state indices of the axes.
        title: the figure's title.

    Returns:
        The figure, or ``None`` when the episode saved no finite prediction.
    """
    fans, compact = saved_fans(trajectory)
    steps = fan_steps(fans) if steps is None else [int(k) for k in steps]
    if not steps:
        return None
    i, j = plane
    true = np.asarray(trajectory["true_state"], dtype=float)
    est = np.asarray(trajectory["estimate"], dtype=float)
    std = np.asarray(trajectory["estimate_std"], dtype=float)
    base = _base_state(system, goal_state)
    goal = None if goal_state is None else base[[i, j]]
    horizon = fans.shape[2] - 1
    ncols = 2 if len(steps) > 1 else 1
    nrows = int(np.ceil(len(steps) / ncols))
    fig = new_figure(11.0, 3.4 * nrows + 0.9)
    axes = fig.subplots(nrows, ncols, squeeze=False).ravel()
    for ax, k in zip(axes, steps, strict=False):
        fan = _finite_fan(fans[k], plane)
        future = true[k : k + horizon + 1][:, [i, j]]
        points = np.vstack([fan.reshape(-1, 2), future, est[k : k + 1, [i, j]]])
        xlim, ylim = _window(points, aspect=0.5, min_half=0.5)
        _draw_feasible_region(ax, system, base, plane, xlim, ylim, resolution=(300, 150))
        _draw_goal(ax, goal, goal_radius)
        _draw_fan(ax, fan, label=f"scenario predictions ({len(fan)} shown)")
        spread = _zoom_on_fan_end(ax, fan, xlim, ylim)
        ax.plot(*true[: k + 1, [i, j]].T, color="0.45", lw=1.0, zorder=4, label="true path so far")
        ax.plot(
            *future.T, color="green", ls="--", lw=1.4, zorder=5, label="true path, next N steps"
        )
        _draw_estimate(ax, est[k, [i, j]], std[k, [i, j]], "estimate, 2-sigma ellipse")
        ax.set_xlim(*xlim)
        ax.set_ylim(*ylim)
        ax.set_aspect("equal", adjustable="box")
        ax.set_title(
            f"t = {k * dt:.1f} s (step {k}); fan width after N = {horizon} steps: {spread:.2g} "
            + unit_of(system.state_names[i]),
            fontsize=9,
        )
        ax.set_xlabel(_axis_label(system.state_names[i]))
        ax.set_ylabel(_axis_label(system.state_names[j]))
        ax.grid(alpha=0.3)
    for ax in axes[len(steps) :]:
        ax.set_visible(False)
    handles, labels = axes[0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="outside lower center", ncols=3, fontsize=8, frameon=False)
    note = "" if compact else " (older file: only the first scenario was saved)"
    fig.suptitle((title or "The plan's scenario fan") + note)
    return fig


def plan_panel_frames(
    system: ControlSystem,
    trajectory: Mapping[str, np.ndarray],
    size: tuple[int, int] = (480, 200),
    goal_state: Any = None,
    goal_radius: float | None = None,
    plane: tuple[int, int] = (0, 1),
) -> list[np.ndarray]:
    """``T+1`` RGB panels ``(height, width, 3)`` uint8 of ``size`` [px]: a camera following the true
    state, the estimate of step ``k`` with its 2-sigma ellipse and the plan's fan from it.
    """
    fans, _ = saved_fans(trajectory)
    i, j = plane
    true = np.asarray(trajectory["true_state"], dtype=float)
    est = np.asarray(trajectory["estimate"], dtype=float)
    std = np.asarray(trajectory["estimate_std"], dtype=float)
    base = _base_state(system, goal_state)
    dpi = 100
    fig = new_figure(size[0] / dpi, size[1] / dpi)
    fig.set_layout_engine("none")
    ax = fig.add_axes((0.0, 0.0, 1.0, 1.0))
    ax.set_axis_off()
    reach = [np.ptp(_finite_fan(f, plane).reshape(-1, 2), axis=0).max() for f in fans if
             len(_finite_fan(f, plane))]  # fmt: skip
    half_x = max(float(np.median(reach)) if reach else 1.0, 0.5)
    aspect = size[1] / size[0]
    # The region once, over the whole episode's plane and as far as the camera sees past
    # it; each frame only moves the camera.
    full_x, full_y = _plane_limits(system, base, plane, [true[:, i]], [true[:, j]])
    reach_x, reach_y = 1.2 * half_x, 1.2 * aspect * half_x
    full_x = (full_x[0] - reach_x, full_x[1] + reach_x)
    full_y = (full_y[0] - reach_y, full_y[1] + reach_y)
    _draw_feasible_region(ax, system, base, plane, full_x, full_y, resolution=(1200, 400))
    _draw_goal(ax, None if goal_state is None else base[[i, j]], goal_radius)
    ax.plot(*true[:, [i, j]].T, color="green", ls="--", lw=1.0, alpha=0.6)
    fan_lines = LineCollection([], colors=FAN_COLOUR, linewidths=0.8, alpha=0.6, zorder=3)
    ax.add_collection(fan_lines)
    (mean_line,) = ax.plot([], [], color=PLAN_COLOUR, lw=2.0, zorder=4)
    (car,) = ax.plot([], [], "s", color="green", ms=8, zorder=6)
    (dot,) = ax.plot([], [], "o", color="red", ms=4, zorder=7)
    ellipse = Ellipse((0.0, 0.0), 0.0, 0.0, facecolor="red", alpha=0.25, lw=0, zorder=5)
    ax.add_patch(ellipse)
    ax.text(
        0.01, 0.03, "true state (green), estimate 2-sigma (red), scenario fan (blue), mean (navy)",
        transform=ax.transAxes, fontsize=7, color="0.2",
    )  # fmt: skip
    frames = []
    for k, state in enumerate(true):
        fan = _finite_fan(fans[k], plane) if k < len(fans) else np.zeros((0, 2, 2))
        fan_lines.set_segments(list(fan))
        mean_line.set_data(*(fan.mean(axis=0).T if len(fan) else ([], [])))
        car.set_data([state[i]], [state[j]])
        if k < len(est) and np.all(np.isfinite(est[k, [i, j]])):
            dot.set_data([est[k, i]], [est[k, j]])
            ellipse.set_center(tuple(est[k, [i, j]]))
            ellipse.set_width(4 * float(np.nan_to_num(std[k, i])))
            ellipse.set_height(4 * float(np.nan_to_num(std[k, j])))
        else:
            dot.set_data([], [])
            ellipse.set_width(0.0)
        ax.set_xlim(state[i] - reach_x, state[i] + reach_x)
        ax.set_ylim(state[j] - reach_y, state[j] + reach_y)
        fig.canvas.draw()
        frames.append(np.asarray(fig.canvas.buffer_rgba())[..., :3].copy())
    return frames
