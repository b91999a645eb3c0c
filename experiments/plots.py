"""Figures of saved evaluation results: one episode drawn from the system definition, and
across-seed plots.

Every function takes arrays that were loaded from a results folder and returns a
:class:`matplotlib.figure.Figure` built without pyplot, so no global figure state leaks
and nothing opens a window; :func:`save_figure` writes it with the Agg canvas.

The episode figures know no particular world: they read the world's
:class:`~lfm_env.system.ControlSystem` only. Axis labels and units come from its state,
input, force and constraint names; input bounds from ``input_lower``/``input_upper``; the
feasible region from the system's own ``constraint_values`` evaluated on a grid (the
constraints that depend only on the plotted states, found from the structure of
``casadi_constraints``). On the sine track this draws the paper's figures (the track band
and x bounds around the path, the latent force, the acceleration against the disturbance,
the speed with its bounds); on the quadrotor the tunnel. Nothing here runs an episode: the
GIF frames are a replay of saved true states through the world's own scene
(:meth:`lfm_env.env.LatentForceEnv.make_scene`).

Time axes are in seconds: sample ``k`` of a trajectory is at ``t = k dt``; actions and the
disturbance act during ``[k dt, (k+1) dt)`` and are drawn as steps; the constraint excess
after step ``k`` is at ``t = (k+1) dt``.
"""

from __future__ import annotations

import inspect
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.patches import Circle, Ellipse, Patch

from lfm_env.system import ControlSystem, split_unit

# Colours follow the paper's captions where it names them (true path green dashed,
# estimate red); the agents get a fixed colour each so plots can be compared.
AGENT_COLOURS = {
    "nominal": "tab:gray",
    "pf": "tab:orange",
    "scenario": "tab:blue",
    "scenario_particles": "tab:green",
    "robust": "tab:red",
    "oracle": "tab:purple",
}
_FALLBACK_COLOURS = ("tab:brown", "tab:pink", "tab:olive", "tab:cyan")


def agent_colour(name: str) -> str:
    """A fixed colour per agent name (unknown names get a stable fallback)."""
    if name in AGENT_COLOURS:
        return AGENT_COLOURS[name]
    return _FALLBACK_COLOURS[sum(map(ord, name)) % len(_FALLBACK_COLOURS)]


def new_figure(width: float, height: float) -> Figure:
    """A pyplot-free figure of ``width`` x ``height`` inches with an Agg canvas."""
    fig = Figure(figsize=(width, height), layout="constrained")
    FigureCanvasAgg(fig)
    return fig


def save_figure(fig: Figure, path: str | Path, dpi: int = 110) -> Path:
    """Write ``fig`` as a PNG (or the format of the suffix) and return the path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=dpi)
    return path


def sample_times(n: int, dt: float) -> np.ndarray:
    """Times ``k dt`` [s] of ``n`` samples."""
    return np.arange(n) * dt


def _step_plot(ax, t: np.ndarray, values: np.ndarray, dt: float | None = None, **kwargs):
    """Draw per-step values held over ``[k dt, (k+1) dt)`` (zero-order hold)."""
    if len(values) == 0:
        return None
    if dt is None:
        dt = t[1] - t[0] if len(t) > 1 else 1.0
    tt = np.append(t, t[-1] + dt)
    vv = np.append(values, values[-1])
    return ax.step(tt, vv, where="post", **kwargs)


# --------------------------------------------------------------------------- the system


def unit_of(label: str) -> str:
    """The unit of a label ``"p_x [m]"`` (``"m"``); ``""`` when it has none."""
    return split_unit(label)[1]


def _joined_units(labels: Sequence[str]) -> str:
    """The distinct units of ``labels``, joined by ``", "`` (usually one)."""
    return ", ".join(u for u in dict.fromkeys(unit_of(x) for x in labels) if u)


def group_unit(system: ControlSystem, group: str) -> str:
    """The unit of a constraint group's excess: its constraints' unit (``"m"``)."""
    if group not in system.constraint_groups:
        raise ValueError(
            f"group {group!r}: not a constraint group of system {system.name!r}; "
            f"its groups are {list(system.constraint_groups)}"
        )
    return _joined_units([system.constraint_names[j] for j in system.constraint_groups[group]])


def force_unit(system: ControlSystem) -> str:
    """The unit of the latent force (of all its components; usually one)."""
    return _joined_units(system.force_names)


def constraint_dependencies(system: ControlSystem) -> tuple[frozenset[int], ...]:
    """The states each constraint ``g_j(x)`` depends on (structurally), one set per constraint.

    Read from the sparsity of the CasADi Jacobian ``dg/dx``: exact for the expression the
    system writes (a term multiplied by a literal zero may still count).
    """
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
    """Values of state ``state`` in ``[low, high]`` where a constraint on it alone is zero.

    Only constraints that depend on this state and no other count (e.g. the sine track's
    speed bounds for ``v``, its x bounds for ``p_x``).
    """
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


# --------------------------------------------------------------------------- episode plots


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
    """Axis limits of the plane: the data, grown to the feasible region near it.

    The feasible set of the plane's constraints is found on a grid over the data's box
    widened by its size on each side; where that set ends inside the widened box (the
    track band, the x bounds, a tunnel), the limits take it in; where it reaches the box's
    edge (an unbounded side) they stay with the data.
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
    fig = new_figure(11.0, float(np.clip(8.0 * ratio + 1.2, 3.6, 7.5)))
    ax = fig.add_subplot()
    _draw_feasible_region(ax, system, base, plane, xlim, ylim)
    _draw_goal(ax, goal, goal_radius)
    return fig, ax, xlim, ylim


def _finish_plane_axes(ax, system, plane, xlim, ylim, title: str) -> None:
    ax.set_xlim(*xlim)
    ax.set_ylim(*ylim)
    ax.set_xlabel(_axis_label(system.state_names[plane[0]]))
    ax.set_ylabel(_axis_label(system.state_names[plane[1]]))
    ax.grid(alpha=0.3)
    ax.legend(loc="upper left", bbox_to_anchor=(1.0, 1.0), fontsize=8, frameon=False)
    if title:
        ax.set_title(title)


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
    """The path in the plane of two states with the estimate's 2-sigma band (paper Fig. 1).

    The feasible region of the constraints that depend only on these two states is drawn
    from the system's ``constraint_values`` on a grid: infeasible area shaded, ``g = 0``
    dashed (the other states at ``goal_state``'s values).

    Args:
        system: the world's system (labels, units, constraints).
        true_state: ``(T+1, nx)`` true states in the states' units; green dashed.
        estimate: ``(T, d)`` state estimates (``d >= nx``; columns as the states), red.
        estimate_std: ``(T, d)`` their standard deviations; a ``2 sigma`` ellipse is drawn
            at every step, which reads as a shaded envelope.
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
    """True paths of several agents (same seed) in the plane of two states.

    Args:
        system: the world's system.
        paths: ``label -> ((T+1, nx) true states, colour)``.
        goal_state: ``(nx,)`` goal state; ``None`` draws no goal.
        goal_radius: radius of a goal disc; ``None`` marks a point.
        plane: the two state indices of the axes.
        title: axes title.
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


def latent_force_figure(
    system: ControlSystem,
    dt: float,
    disturbance: np.ndarray,
    estimate: np.ndarray | None = None,
    estimate_std: np.ndarray | None = None,
    title: str = "",
) -> Figure:
    """The true latent force (dashed) and its estimate with 2-sigma band (paper Fig. 2).

    One panel per force component (``system.force_names``).

    Args:
        system: the world's system.
        dt: sampling time [s].
        disturbance: true force acting during step ``k``: ``(T,)`` for one component,
            else ``(T, nw)``, in the force's units.
        estimate: the filter's estimate, shaped like ``disturbance`` (NaN: no filter).
        estimate_std: its standard deviation.
        title: title of the first panel.
    """
    nw = system.nw
    w = _components(disturbance, nw, "disturbance")
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
                ax.fill_between(
                    t,
                    est[:, c] - 2 * std[:, c],
                    est[:, c] + 2 * std[:, c],
                    color="tab:blue",
                    alpha=0.2,
                    lw=0,
                    label="estimate $\\pm 2\\sigma$",
                )
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
        ax.set_ylabel(f"latent force {_axis_label(system.force_names[c])}")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8, loc="best")
    axes[-1].set_xlabel("time [s]")
    if title:
        axes[0].set_title(title)
    return fig


def inputs_figure(
    system: ControlSystem,
    dt: float,
    action: np.ndarray,
    disturbance: np.ndarray | None = None,
    title: str = "",
) -> Figure:
    """The applied inputs with their bounds, one panel per input (paper Fig. 3 on the track).

    A force component in the same unit as an input (the sine track's ``w`` and its
    acceleration ``a``, both m/s^2) is drawn on that input's panel with its negative:
    an input lying on ``-w`` would cancel the force exactly.

    Args:
        system: the world's system (input names, ``input_lower``/``input_upper``).
        dt: sampling time [s].
        action: ``(T, nu)`` applied inputs in the inputs' units.
        disturbance: true force in the same steps, ``(T,)`` or ``(T, nw)``; ``None`` for
            none.
        title: title of the first panel.
    """
    u = _components(action, system.nu, "action")
    w = None if disturbance is None else _components(disturbance, system.nw, "disturbance")
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
                _step_plot(ax, t, w[:, c], dt, ls="--", label=f"disturbance {fname}", **style)
                _step_plot(
                    ax, t, -w[:, c], dt, ls=":", label=f"$-${fname} (full cancellation)", **style
                )
        lo, hi = system.input_lower[k], system.input_upper[k]
        for b in (lo, hi):
            ax.axhline(b, color="k", lw=0.8, ls="-.")
        ax.plot([], [], "k-.", lw=0.8, label=f"bounds {lo:.3g} / {hi:.3g}")
        ax.set_ylabel(_axis_label(system.input_names[k]))
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8, loc="best", ncols=2)
    axes[-1].set_xlabel("time [s]")
    if title:
        axes[0].set_title(title)
    return fig


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
    """States over time, true (dashed) and estimated with 2-sigma band (paper Fig. 4).

    Bounds on a state alone (a constraint that depends on it and no other state, e.g.
    the sine track's speed bounds) are drawn dashed with the infeasible side shaded.

    Args:
        system: the world's system.
        dt: sampling time [s].
        true_state: ``(T+1, nx)`` true states.
        estimate: ``(T, d)`` estimates at the first ``T`` samples (``d >= nx``).
        estimate_std: ``(T, d)`` their standard deviations (zeros draw no band).
        states: the state indices to draw; by default every state but the first two
            (those are in :func:`trajectory_figure`).
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
                    ax.fill_between(
                        te,
                        e - 2 * sd,
                        e + 2 * sd,
                        color="tab:blue",
                        alpha=0.2,
                        lw=0,
                        label="estimate $\\pm 2\\sigma$",
                    )
        ylim = _limits(system, i, values, base)
        _draw_state_bounds(ax, system, i, base, ylim)
        ax.set_ylim(*ylim)
        ax.set_ylabel(_axis_label(system.state_names[i]))
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8, loc="best")
    axes[-1].set_xlabel("time [s]")
    if title:
        axes[0].set_title(title)
    return fig


def constraint_excess_figure(
    system: ControlSystem,
    dt: float,
    runs: Mapping[str, tuple[Mapping[str, np.ndarray], str]],
    title: str = "",
) -> Figure | None:
    """Each constraint group's excess over time, one panel per group.

    Args:
        system: the world's system (its ``constraint_groups`` and their units).
        dt: sampling time [s]; the excess after step ``k`` is drawn at ``(k+1) dt``.
        runs: ``label -> ({group: (T,) excess}, colour)``: one agent, or several on the
            same seed. A group missing from a run is left out of its panel.
        title: title of the first panel.

    Returns:
        The figure, or ``None`` when the system has no constraints.
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
    axes[-1].set_xlabel("time [s]")
    if title:
        axes[0].set_title(title)
    return fig


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
    """The figures of one saved episode, drawn from the system definition.

    Args:
        trajectory: arrays of one episode (``true_state``, ``estimate``, ``estimate_std``,
            ``action``, ``disturbance``, ``latent_force_est``, ``latent_force_std``,
            ``<group>_excess``).
        system: the world's system.
        dt: sampling time [s].
        goal_state: ``(nx,)`` goal state (the task's), in the states' units.
        goal_radius: radius of the goal disc in the plane of the first two states, if the
            world has one.
        label: the agent's label, used in titles.

    Returns:
        ``name -> Figure`` for ``"trajectory"`` (states 0 and 1 with the feasible region),
        ``"latent_force"``, ``"inputs"``, ``"states"`` (the other states; left out when
        ``nx <= 2``) and ``"constraints"`` (each group's excess; left out without
        constraints).
    """
    x = np.asarray(trajectory["true_state"])
    est = np.asarray(trajectory["estimate"])
    std = np.asarray(trajectory["estimate_std"])
    w = np.asarray(trajectory["disturbance"])
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


# --------------------------------------------------------------------------- across seeds


def distribution_axes(
    ax,
    values: Mapping[str, np.ndarray],
    colours: Sequence[str] | None = None,
    log: bool = False,
    seed: int = 0,
) -> None:
    """Box plot per group with the individual values as a jittered strip on top.

    Args:
        ax: matplotlib axes.
        values: ``label -> values``; NaNs are left out, an all-NaN group shows "n/a".
        colours: one colour per group.
        log: log-scale y axis (non-positive values are left out).
        seed: seed of the horizontal jitter, so figures are reproducible.
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
    ax.set_xticks(positions, labels, fontsize=8 if len(labels) <= 4 else 6.5)
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
    """A grid of per-agent distributions over seeds, one panel per metric.

    Args:
        metrics: ``axis label (with unit) -> {agent label -> values over seeds}``.
        agent_names: agent names in the same order as the labels (for the colours).
        ncols: panels per row.
        log_scale: axis labels of the panels drawn on a log scale (heavy-tailed metrics).
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
    """Per-episode solve-time median and 95th percentile per agent, log scale.

    Args:
        median: ``agent label -> per-episode median solve time [s]``.
        p95: ``agent label -> per-episode 95th-percentile solve time [s]``.
        agent_names: agent names in the same order as the labels (for the colours).
        dt: sampling time [s], drawn as the real-time limit.
    """
    fig = new_figure(10.0, 3.6)
    axes = fig.subplots(1, 2, sharey=True)
    colours = [agent_colour(a) for a in agent_names]
    for ax, (title, values) in zip(
        axes,
        (("median per episode", median), ("95th percentile per episode", p95)),
        strict=True,
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


def calibration_figure(
    quantities: Sequence[str],
    agents: Mapping[str, str],
    coverage: np.ndarray,
    rmse: np.ndarray,
    nominal: float = 0.9545,
) -> Figure:
    """Estimators side by side: 2-sigma coverage (top) and RMSE (bottom) per quantity.

    Args:
        quantities: ``Q`` labels with units (the states, then the latent force).
        agents: ``label -> colour`` of the ``A`` agents (with their estimator's name).
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
    fig.suptitle("Estimator calibration (bars: pooled over steps; whiskers: 95% over episodes)")
    return fig


def pareto_figure(
    points: Sequence[tuple[str, np.ndarray, np.ndarray]],
    baseline: str,
    xlabel: str,
    ylabel: str,
    title: str = "",
) -> Figure:
    """The risk trade-off: paired differences to a baseline, one point per setting.

    Args:
        points: ``(label, x, y)`` per setting; ``x`` and ``y`` are ``(mean, low, high)``
            of the paired difference to the baseline (x: e.g. time to goal [s]; y: e.g.
            violation steps beyond a tolerance). NaN points are left out.
        baseline: the baseline's label, drawn at the origin.
        xlabel: x axis label (with its unit).
        ylabel: y axis label.
        title: figure title.
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


# --------------------------------------------------------------------------- frames


def annotate_frame(frame: np.ndarray, text: str) -> np.ndarray:
    """A copy of an RGB ``frame`` with ``text`` in its top-left corner.

    Besides telling the time, the caption keeps consecutive frames distinct: a GIF writer
    merges identical frames, and a stopped car would otherwise lose frames.
    """
    from PIL import Image, ImageDraw

    image = Image.fromarray(np.ascontiguousarray(frame[..., :3]))
    draw = ImageDraw.Draw(image)
    box = draw.textbbox((4, 4), text)
    draw.rectangle((box[0] - 2, box[1] - 2, box[2] + 2, box[3] + 2), fill=(0, 0, 0))
    draw.text((4, 4), text, fill=(255, 255, 255))
    return np.asarray(image)


def _world(config: Any) -> tuple[str, Any]:
    """``(env_id, world config)`` of an ``ExperimentConfig`` or of a world config."""
    env_id, world = getattr(config, "env_id", None), getattr(config, "env", None)
    if isinstance(env_id, str) and world is not None:
        return env_id, world
    env_id = getattr(config, "ENV_ID", "")
    if not env_id:
        raise ValueError(
            f"config of type {type(config).__name__}: expected an ExperimentConfig or a world "
            "config (e.g. lfm_env.config.EnvConfig) that names its env (ENV_ID)"
        )
    return env_id, config


def make_render_env(config: Any, render_mode: str = "rgb_array", **options: Any):
    """``gym.make(env_id, config=world, render_mode=...)`` of the config's world.

    Args:
        config: an :class:`~controllers.config.ExperimentConfig` (its ``env_id`` and
            ``env``) or a world config (its ``ENV_ID``).
        render_mode: ``"rgb_array"`` (frames) or ``"human"``.
        **options: drawing options such as ``screen_size`` [px] or ``scaling`` [px/m];
            those the world's env does not take are left out (each world draws its own
            way).
    """
    import gymnasium as gym

    import lfm_env  # noqa: F401  (registers the envs)

    env_id, world = _world(config)
    entry = gym.spec(env_id).entry_point
    if not callable(entry):
        from gymnasium.envs.registration import load_env_creator

        entry = load_env_creator(entry)
    params = inspect.signature(entry).parameters
    if not any(p.kind is inspect.Parameter.VAR_KEYWORD for p in params.values()):
        options = {k: v for k, v in options.items() if k in params}
    return gym.make(env_id, config=world, render_mode=render_mode, **options)


def replay_frames(
    true_state: np.ndarray,
    config: Any,
    screen_size: tuple[int, int] = (480, 240),
    scaling: float | None = None,
    caption: str = "",
) -> list[np.ndarray]:
    """Frames of a saved episode drawn by the world's own scene, one per saved true state.

    This replays ``true_state`` through ``env.unwrapped.make_scene()`` of the config's
    env (``scene.update(x)``, ``scene.draw()``); it does not simulate anything.

    Args:
        true_state: ``(T+1, nx)`` true states in the states' units.
        config: an ``ExperimentConfig`` or the world config of the run.
        screen_size: frame ``(width, height)`` [px], if the world's env takes it.
        scaling: [px/m], if the world's env takes it; ``None`` for the world's own default
            (the sine track follows the car at 25 px/m, the quadrotor fits the tunnel).
        caption: text put before the time stamp on each frame.

    Returns:
        ``T+1`` RGB frames ``(height, width, 3)`` uint8.
    """
    options = {} if scaling is None else {"scaling": scaling}
    env = make_render_env(config, screen_size=screen_size, **options)
    try:
        dt = env.unwrapped.model.dt
        scene = env.unwrapped.make_scene()
        frames = []
        try:
            for k, state in enumerate(np.asarray(true_state, dtype=float)):
                scene.update(state)
                frame = scene.draw()
                text = f"t = {k * dt:.1f} s"
                text = f"{caption} | {text}" if caption else text
                frames.append(annotate_frame(frame, text))
        finally:
            scene.close()
    finally:
        env.close()
    return frames


def write_gif(frames: Sequence[np.ndarray], path: str | Path, fps: float) -> Path:
    """Write RGB ``frames`` as a looping GIF at ``fps`` frames per second."""
    import imageio.v3 as iio

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    if not frames:
        raise ValueError(f"no frames to write to {path}")
    iio.imwrite(path, np.stack(frames), extension=".gif", duration=1000.0 / fps, loop=0)
    return path
