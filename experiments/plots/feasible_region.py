"""The feasible region of a system in a plane of two states, from the constraints that depend
only on them (structure of the CasADi Jacobian ``dg/dx``); axis limits and labels.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
from matplotlib.patches import Circle

from experiments.plots.style import new_figure
from lfm_env.system import ControlSystem, split_unit


def constraint_dependencies(system: ControlSystem) -> tuple[frozenset[int], ...]:
    """The states each constraint ``g_j(x)`` depends on, from the sparsity of CasADi's ``dg/dx``."""
    import casadi as ca

    if system.ng == 0:
        return ()
    x = ca.SX.sym("x", system.nx)
    rows, cols = ca.jacobian(system.casadi_constraints()(x), x).sparsity().get_triplet()
    deps: list[set[int]] = [set() for _ in range(system.ng)]
    for r, c in zip(rows, cols, strict=True):
        deps[r].add(c)
    return tuple(frozenset(d) for d in deps)


def constraints_on(system: ControlSystem, states: Sequence[int]) -> tuple[int, ...]:
    """Indices of the constraints that depend on some of ``states`` and on no other state."""
    chosen = set(states)
    return tuple(j for j, d in enumerate(constraint_dependencies(system)) if d and d <= chosen)


def _base_state(system: ControlSystem, base_state: Any) -> np.ndarray:
    """The state the unplotted components take on a grid: ``base_state`` or zeros."""
    if base_state is None:
        return np.zeros(system.nx)
    base = np.asarray(base_state, dtype=float).reshape(-1)
    if base.shape != (system.nx,):
        raise ValueError(
            f"goal_state={base_state!r}: must be {system.nx} numbers, one per state "
            f"{list(system.state_names)}"
        )
    return base


def _constraints_along(
    system: ControlSystem, base: np.ndarray, values: Mapping[int, np.ndarray], which: Sequence[int]
) -> np.ndarray:
    """``g_which`` at ``base`` with state ``i`` set to ``values[i]`` (broadcast grids)."""
    shape = np.broadcast_shapes(*(np.shape(v) for v in values.values()))
    states = np.broadcast_to(base, shape + (system.nx,)).copy()
    for i, v in values.items():
        states[..., i] = v
    g = np.asarray(system.constraint_values(states), dtype=float)
    return g[..., list(which)]


def _crossings(s: np.ndarray, g: np.ndarray) -> list[float]:
    """Where the columns of ``g`` (sampled at ``s``) cross zero, linearly interpolated."""
    out: set[float] = set()
    for col in np.atleast_2d(g.T):
        a, b = col[:-1], col[1:]
        # Feasible (< 0) on one side only; a sample exactly at zero counts once.
        for k in np.flatnonzero(np.isfinite(a) & np.isfinite(b) & ((a < 0.0) != (b < 0.0))):
            out.add(float(s[k] + (s[k + 1] - s[k]) * a[k] / (a[k] - b[k])))
    return sorted(out)


def state_bounds(
    system: ControlSystem, state: int, low: float, high: float, base_state: Any = None
) -> list[float]:
    """Values of ``state`` in ``[low, high]`` where a constraint on it alone is zero."""
    which = [j for j, d in enumerate(constraint_dependencies(system)) if d == {state}]
    if not which or not high > low:
        return []
    s = np.linspace(low, high, 4001)
    g = _constraints_along(system, _base_state(system, base_state), {state: s}, which)
    return sorted(_crossings(s, g))


def _data_range(values: Sequence[np.ndarray]) -> tuple[float, float]:
    v = np.concatenate([np.asarray(x, dtype=float).reshape(-1) for x in values] + [np.zeros(0)])
    v = v[np.isfinite(v)]
    if len(v) == 0:
        return 0.0, 1.0
    return float(v.min()), float(v.max())


def _near_span(lo: float, hi: float) -> float:
    """How far beyond the data ``[lo, hi]`` a bound counts as near: the data's extent, or
    half its magnitude when the data hardly vary (a speed held at its bound)."""
    span = max(hi - lo, 0.5 * max(abs(lo), abs(hi)))
    return span if span > 0.0 else 1.0


def _limits(
    system: ControlSystem, state: int, values: Sequence[np.ndarray], base: np.ndarray
) -> tuple[float, float]:
    """Axis limits of a state: its data, and the bounds on it alone near the data."""
    lo, hi = _data_range(values)
    span = _near_span(lo, hi)
    near = state_bounds(system, state, lo - 0.5 * span, hi + 0.5 * span, base)
    lo, hi = min([lo, *near]), max([hi, *near])
    pad = 0.06 * (hi - lo) if hi > lo else 0.5 * span
    return lo - pad, hi + pad


def _axis_label(label: str) -> str:
    """An axis label from a system label: ``"p_x [m]"`` as written."""
    name, unit = split_unit(label)
    return f"{name} [{unit}]" if unit else name


def _components(values: Any, n: int, name: str) -> np.ndarray:
    """Per-step values of ``n`` components as ``(T, n)``: ``(T,)`` is one component."""
    a = np.asarray(values, dtype=float)
    if a.ndim == 1 and n == 1:
        return a[:, None]
    if a.ndim != 2 or a.shape[1] != n:
        raise ValueError(
            f"{name} of shape {a.shape}: expected (T, {n}) (or (T,) for one component)"
        )
    return a


def _draw_feasible_region(
    ax,
    system: ControlSystem,
    base: np.ndarray,
    plane: tuple[int, int],
    xlim: tuple[float, float],
    ylim: tuple[float, float],
    resolution: tuple[int, int] = (600, 300),
) -> None:
    """Shade where the constraints on the plane's two states are violated; dashed ``g = 0``."""
    which = constraints_on(system, plane)
    if not which:
        return
    xs = np.linspace(*xlim, resolution[0])
    ys = np.linspace(*ylim, resolution[1])
    gx, gy = np.meshgrid(xs, ys)
    g = _constraints_along(system, base, {plane[0]: gx, plane[1]: gy}, which)
    worst = np.max(g, axis=-1)
    if np.nanmax(worst) > 0.0:
        top = float(np.nanmax(worst))
        ax.contourf(
            xs, ys, worst, levels=[0.0, top + max(1.0, abs(top))], colors=["0.88"], zorder=0
        )
        ax.fill_between([], [], [], color="0.88", label="infeasible ($g > 0$)")
    drawn = []
    for k, j in enumerate(which):
        gk = g[..., k]
        if np.nanmin(gk) < 0.0 < np.nanmax(gk):
            ax.contour(xs, ys, gk, levels=[0.0], colors="k", linestyles="--", linewidths=1.0)
            drawn.append(system.constraint_labels[j])
    if drawn:
        ax.plot([], [], "k--", lw=1.0, label="bounds: " + ", ".join(drawn))


def _draw_goal(ax, goal: np.ndarray | None, goal_radius: float | None) -> None:
    if goal is None:
        return
    if goal_radius is not None and goal_radius > 0:
        ax.add_patch(
            Circle(tuple(goal), goal_radius, facecolor="gold", edgecolor="k", alpha=0.6, zorder=2)
        )
        ax.plot([], [], "o", color="gold", mec="k", label=f"goal disc (r = {goal_radius:g})")
    else:
        ax.plot(*goal, "*", color="gold", mec="k", ms=14, zorder=6, label="goal")


def _plane_limits(
    system: ControlSystem,
    base: np.ndarray,
    plane: tuple[int, int],
    xs: Sequence[np.ndarray],
    ys: Sequence[np.ndarray],
    resolution: int = 400,
) -> tuple[tuple[float, float], tuple[float, float]]:
    """Axis limits of the plane: the data, grown to take in the feasible region's ends found on a
    grid over the data's box widened by its size (an unbounded side stays with the data).
    """
    box = []
    for values in (xs, ys):
        lo, hi = _data_range(values)
        span = _near_span(lo, hi)
        box.append([lo, hi, lo - span, hi + span])
    which = constraints_on(system, plane)
    if which:
        gx = np.linspace(box[0][2], box[0][3], resolution)
        gy = np.linspace(box[1][2], box[1][3], resolution)
        g = _constraints_along(
            system, base, dict(zip(plane, np.meshgrid(gx, gy), strict=True)), which
        )
        feasible = np.all(g <= 0.0, axis=-1)
        for axis, grid, used in ((0, gx, feasible.any(axis=0)), (1, gy, feasible.any(axis=1))):
            if used.any():
                lo, hi = grid[used].min(), grid[used].max()
                if lo > grid[0]:
                    box[axis][0] = min(box[axis][0], lo)
                if hi < grid[-1]:
                    box[axis][1] = max(box[axis][1], hi)
    limits = []
    for lo, hi, _, _ in box:
        pad = 0.06 * (hi - lo) if hi > lo else 0.5
        limits.append((lo - pad, hi + pad))
    return limits[0], limits[1]


def _plane_figure(
    system: ControlSystem,
    point_sets: Sequence[np.ndarray],
    goal_state: Any,
    goal_radius: float | None,
    plane: tuple[int, int],
):
    """A figure and axes of the plane of two states, with the region and the goal drawn."""
    i, j = plane
    if not (0 <= i < system.nx and 0 <= j < system.nx and i != j):
        raise ValueError(f"plane={plane}: two different state indices in [0, {system.nx})")
    base = _base_state(system, goal_state)
    goal = None if goal_state is None else base[[i, j]]
    pts = [np.asarray(p, dtype=float)[:, [i, j]] for p in point_sets if len(p)]
    r = goal_radius or 0.0
    xs = [p[:, 0] for p in pts] + ([goal[:1] - r, goal[:1] + r] if goal is not None else [])
    ys = [p[:, 1] for p in pts] + ([goal[1:] - r, goal[1:] + r] if goal is not None else [])
    xlim, ylim = _plane_limits(system, base, plane, xs, ys)
    ratio = (ylim[1] - ylim[0]) / (xlim[1] - xlim[0])
    # Equal axes (same unit) draw the plane to scale: the figure is as tall as that needs.
    low = 2.0 if _same_unit(system, plane) else 3.6
    fig = new_figure(11.0, float(np.clip(8.0 * ratio + 1.2, low, 7.5)))
    ax = fig.add_subplot()
    _draw_feasible_region(ax, system, base, plane, xlim, ylim)
    _draw_goal(ax, goal, goal_radius)
    return fig, ax, xlim, ylim


def _same_unit(system: ControlSystem, plane: tuple[int, int]) -> bool:
    """Whether the plane's two states share a unit (then one metre is one metre)."""
    units = [split_unit(system.state_names[i])[1] for i in plane]
    return units[0] == units[1]


def _finish_plane_axes(ax, system, plane, xlim, ylim, title: str) -> None:
    ax.set_xlim(*xlim)
    ax.set_ylim(*ylim)
    if _same_unit(system, plane):  # lengths drawn to scale: the goal disc is a circle
        ax.set_aspect("equal", adjustable="box")
    ax.set_xlabel(_axis_label(system.state_names[plane[0]]))
    ax.set_ylabel(_axis_label(system.state_names[plane[1]]))
    ax.grid(alpha=0.3)
    ax.legend(loc="upper left", bbox_to_anchor=(1.0, 1.0), fontsize=8, frameon=False)
    if title:
        ax.set_title(title)
