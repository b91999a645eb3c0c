"""Figures of saved evaluation results: the paper's four episode plots and across-seed plots.

Every function takes arrays that were loaded from a results folder and returns a
:class:`matplotlib.figure.Figure` built without pyplot, so no global figure state leaks
and nothing opens a window; :func:`save_figure` writes it with the Agg canvas. Nothing
here runs an episode: the GIF frames are a replay of saved true states through the env's
renderer (:class:`lfm_env.rendering.TrackScene`).

Time axes are in seconds: sample ``k`` of a trajectory is at ``t = k dt``; actions and the
disturbance act during ``[k dt, (k+1) dt)`` and are drawn as steps.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.patches import Circle, Ellipse

from lfm_env.config import EnvConfig
from lfm_env.systems.sine_track import SineTrack

# Colours follow the paper's captions where it names them (true path green dashed,
# estimate red); the agents get a fixed colour each so plots can be compared.
AGENT_COLOURS = {
    "nominal": "tab:gray",
    "pf": "tab:orange",
    "scenario": "tab:blue",
    "scenario_particles": "tab:green",
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


def _step_plot(ax, t: np.ndarray, values: np.ndarray, **kwargs):
    """Draw per-step values held over ``[k dt, (k+1) dt)`` (zero-order hold)."""
    if len(values) == 0:
        return None
    dt = t[1] - t[0] if len(t) > 1 else 1.0
    tt = np.append(t, t[-1] + dt)
    vv = np.append(values, values[-1])
    return ax.step(tt, vv, where="post", **kwargs)


# --------------------------------------------------------------------------- episode plots


def _draw_track(ax, track: SineTrack, goal: Sequence[float], goal_radius: float) -> None:
    """Track band (shaded), centre line, dashed black bounds, x bounds and the goal disc."""
    xs = np.linspace(track.x_min, track.x_max, 800)
    centre = track.centre_y(xs)
    ax.fill_between(
        xs, centre - track.half_width, centre + track.half_width, color="0.93", zorder=0
    )
    ax.plot(xs, centre, color="0.6", lw=0.8, ls=":", label="track centre")
    ax.plot(xs, centre + track.half_width, "k--", lw=1.0, label="track bounds")
    ax.plot(xs, centre - track.half_width, "k--", lw=1.0)
    for xb in (track.x_min, track.x_max):
        ax.axvline(xb, color="k", lw=0.6, ls="-.", alpha=0.5)
    ax.add_patch(
        Circle(tuple(goal), goal_radius, facecolor="gold", edgecolor="k", alpha=0.6, zorder=2)
    )
    ax.plot([], [], "o", color="gold", mec="k", label=f"goal disc (r = {goal_radius:g} m)")


def _finish_track_axes(ax, track: SineTrack, paths: Sequence[np.ndarray], title: str) -> None:
    """Axis labels, limits that show the whole track and every path, legend outside."""
    ax.set_xlabel("$p_x$ [m]")
    ax.set_ylabel("$p_y$ [m]")
    pad = track.amplitude + track.half_width + 1.0
    ys = np.concatenate([np.asarray(p)[:, 1] for p in paths] + [np.array([-pad, pad])])
    xs = np.concatenate([np.asarray(p)[:, 0] for p in paths] + [[track.x_min, track.x_max]])
    ys, xs = ys[np.isfinite(ys)], xs[np.isfinite(xs)]
    ax.set_ylim(min(-pad, ys.min() - 0.5), max(pad, ys.max() + 0.5))
    ax.set_xlim(min(track.x_min, xs.min()) - 1.0, max(track.x_max, xs.max()) + 1.0)
    ax.grid(alpha=0.3)
    ax.legend(loc="upper left", bbox_to_anchor=(1.0, 1.0), fontsize=8, frameon=False)
    if title:
        ax.set_title(title)


def trajectory_figure(
    track: SineTrack,
    true_state: np.ndarray,
    estimate: np.ndarray | None = None,
    estimate_std: np.ndarray | None = None,
    goal: Sequence[float] = (62.83, 0.0),
    goal_radius: float = 1.0,
    title: str = "",
) -> Figure:
    """The paper's Fig. 1: the x-y path on the track with the estimate and its 2-sigma band.

    Args:
        track: the track geometry (centre line, half width, x bounds) [m].
        true_state: ``(T+1, 4)`` true states ``[m, m, m/s, rad]``; the path is green dashed.
        estimate: ``(T, d)`` state estimates (first two columns ``p_x, p_y`` [m]), red.
        estimate_std: ``(T, d)`` their standard deviations [m]; a ``2 sigma`` ellipse is
            drawn at every step, which reads as a shaded envelope.
        goal: goal position [m].
        goal_radius: radius [m] of the goal disc.
        title: axes title.
    """
    fig = new_figure(11.0, 3.8)
    ax = fig.add_subplot()
    _draw_track(ax, track, goal, goal_radius)
    if estimate is not None and estimate_std is not None and len(estimate):
        for (px, py), (sx, sy) in zip(estimate[:, :2], estimate_std[:, :2], strict=True):
            if np.isfinite(sx) and np.isfinite(sy) and (sx > 0 or sy > 0):
                ax.add_patch(
                    Ellipse((px, py), 4 * sx, 4 * sy, facecolor="red", alpha=0.15, lw=0, zorder=3)
                )
        ax.fill_between([], [], [], color="red", alpha=0.25, label="estimate $\\pm 2\\sigma$")
    if estimate is not None and len(estimate):
        ax.plot(estimate[:, 0], estimate[:, 1], color="red", lw=1.3, zorder=4, label="estimate")
    ax.plot(
        true_state[:, 0],
        true_state[:, 1],
        color="green",
        ls="--",
        lw=1.6,
        zorder=5,
        label="true path",
    )
    ax.plot(*true_state[0, :2], "go", ms=4, zorder=5)
    _finish_track_axes(ax, track, [true_state], title)
    return fig


def paths_figure(
    track: SineTrack,
    paths: Mapping[str, tuple[np.ndarray, str]],
    goal: Sequence[float] = (62.83, 0.0),
    goal_radius: float = 1.0,
    title: str = "",
) -> Figure:
    """True x-y paths of several agents on the same track (same seed).

    Args:
        track: the track geometry [m].
        paths: ``label -> ((T+1, 4) true states [m, m, m/s, rad], colour)``.
        goal: goal position [m].
        goal_radius: radius [m] of the goal disc.
        title: axes title.
    """
    fig = new_figure(11.0, 3.8)
    ax = fig.add_subplot()
    _draw_track(ax, track, goal, goal_radius)
    for label, (states, colour) in paths.items():
        ax.plot(states[:, 0], states[:, 1], color=colour, lw=1.3, label=label, zorder=4)
        ax.plot(states[-1, 0], states[-1, 1], "x", color=colour, ms=6, zorder=5)
    ax.plot([], [], "kx", ms=6, label="end of episode")
    _finish_track_axes(ax, track, [p for p, _ in paths.values()], title)
    return fig


def latent_force_figure(
    dt: float,
    disturbance: np.ndarray,
    estimate: np.ndarray | None = None,
    estimate_std: np.ndarray | None = None,
    title: str = "",
) -> Figure:
    """The paper's Fig. 2: the true latent force (dashed) and its estimate with 2-sigma band.

    Args:
        dt: sampling time [s].
        disturbance: ``(T,)`` true force ``w`` [m/s^2] acting during step ``k``.
        estimate: ``(T,)`` filter estimate of ``w_k`` [m/s^2] (NaN: agent has no filter).
        estimate_std: ``(T,)`` its standard deviation [m/s^2].
        title: axes title.
    """
    fig = new_figure(7.0, 3.4)
    ax = fig.add_subplot()
    t = sample_times(len(disturbance), dt)
    ax.plot(t, disturbance, color="tab:blue", ls="--", lw=1.5, label="true $w$")
    if estimate is not None and np.any(np.isfinite(estimate)):
        ax.plot(t, estimate, color="tab:blue", lw=1.5, label="estimate")
        if estimate_std is not None:
            ax.fill_between(
                t,
                estimate - 2 * estimate_std,
                estimate + 2 * estimate_std,
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
    ax.set_xlabel("time [s]")
    ax.set_ylabel("latent force $w$ [m/s$^2$]")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, loc="best")
    if title:
        ax.set_title(title)
    return fig


def acceleration_figure(
    dt: float,
    acceleration: np.ndarray,
    disturbance: np.ndarray,
    accel_max: float | None = None,
    title: str = "",
) -> Figure:
    """The paper's Fig. 3: the acceleration input against the disturbance.

    The paper reads the controller's counteraction as a symmetry between ``a`` and ``w``;
    ``-w`` is drawn so that full cancellation would show as ``a`` lying on it.

    Args:
        dt: sampling time [s].
        acceleration: ``(T,)`` applied acceleration ``a`` [m/s^2].
        disturbance: ``(T,)`` true latent force ``w`` [m/s^2] in the same steps.
        accel_max: input bound ``|a| <= accel_max`` [m/s^2], drawn if given.
        title: axes title.
    """
    fig = new_figure(7.0, 3.4)
    ax = fig.add_subplot()
    t = sample_times(len(acceleration), dt)
    _step_plot(ax, t, acceleration, color="tab:red", lw=1.6, label="acceleration $a$")
    _step_plot(ax, t, disturbance, color="tab:blue", lw=1.0, ls="--", label="disturbance $w$")
    _step_plot(
        ax,
        t,
        -np.asarray(disturbance),
        color="tab:blue",
        lw=1.0,
        ls=":",
        label="$-w$ (full cancellation)",
    )
    if accel_max is not None:
        for b in (-accel_max, accel_max):
            ax.axhline(b, color="k", lw=0.8, ls="-.")
        ax.plot([], [], "k-.", lw=0.8, label=f"$|a| \\leq {accel_max:g}$")
    ax.set_xlabel("time [s]")
    ax.set_ylabel("[m/s$^2$]")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, loc="best", ncols=2)
    if title:
        ax.set_title(title)
    return fig


def speed_figure(
    dt: float,
    true_speed: np.ndarray,
    estimate: np.ndarray | None = None,
    estimate_std: np.ndarray | None = None,
    speed_min: float = 0.0,
    speed_max: float = 8.0,
    title: str = "",
) -> Figure:
    """The paper's Fig. 4: the speed, true (dashed) and estimated with its 2-sigma band.

    Args:
        dt: sampling time [s].
        true_speed: ``(T+1,)`` true speed [m/s].
        estimate: ``(T,)`` estimated speed [m/s] at the first ``T`` samples.
        estimate_std: ``(T,)`` its standard deviation [m/s] (zeros draw no band).
        speed_min: lower speed bound [m/s].
        speed_max: upper speed bound [m/s].
        title: axes title.
    """
    fig = new_figure(7.0, 3.4)
    ax = fig.add_subplot()
    t = sample_times(len(true_speed), dt)
    ax.plot(t, true_speed, color="tab:orange", ls="--", lw=1.6, label="true speed")
    if estimate is not None and len(estimate):
        te = sample_times(len(estimate), dt)
        ax.plot(te, estimate, color="tab:blue", lw=1.4, label="estimate")
        if estimate_std is not None and np.any(estimate_std > 0):
            ax.fill_between(
                te,
                estimate - 2 * estimate_std,
                estimate + 2 * estimate_std,
                color="tab:blue",
                alpha=0.2,
                lw=0,
                label="estimate $\\pm 2\\sigma$",
            )
    _finish_speed_axes(ax, speed_min, speed_max, title)
    return fig


def _finish_speed_axes(ax, speed_min: float, speed_max: float, title: str) -> None:
    for b in (speed_min, speed_max):
        ax.axhline(b, color="k", ls="--", lw=1.0)
    ax.plot([], [], "k--", lw=1.0, label=f"bounds {speed_min:g} / {speed_max:g} m/s")
    ax.set_xlabel("time [s]")
    ax.set_ylabel("speed $v$ [m/s]")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, loc="best")
    if title:
        ax.set_title(title)


def speeds_figure(
    dt: float,
    speeds: Mapping[str, tuple[np.ndarray, str]],
    speed_min: float = 0.0,
    speed_max: float = 8.0,
    title: str = "",
) -> Figure:
    """True speeds of several agents on the same seed.

    Args:
        dt: sampling time [s].
        speeds: ``label -> ((T+1,) true speed [m/s], colour)``.
        speed_min: lower speed bound [m/s].
        speed_max: upper speed bound [m/s].
        title: axes title.
    """
    fig = new_figure(7.0, 3.4)
    ax = fig.add_subplot()
    for label, (v, colour) in speeds.items():
        ax.plot(sample_times(len(v), dt), v, color=colour, lw=1.3, label=label)
    _finish_speed_axes(ax, speed_min, speed_max, title)
    return fig


def episode_figures(
    trajectory: Mapping[str, np.ndarray],
    config: EnvConfig,
    label: str = "",
) -> dict[str, Figure]:
    """The paper's four figures for one saved episode.

    Args:
        trajectory: arrays of one episode (``true_state``, ``estimate``, ``estimate_std``,
            ``action``, ``disturbance``, ``latent_force_est``, ``latent_force_std``).
        config: the env config of the run (track, bounds, ``dt``).
        label: the agent's label, used in titles.

    Returns:
        ``{"trajectory", "latent_force", "acceleration", "speed"} -> Figure``.
    """
    dt = config.dt
    x = np.asarray(trajectory["true_state"])
    est = np.asarray(trajectory["estimate"])
    std = np.asarray(trajectory["estimate_std"])
    suffix = f" - {label}" if label else ""
    return {
        "trajectory": trajectory_figure(
            config.track,
            x,
            est,
            std,
            goal=config.goal,
            goal_radius=config.goal_radius,
            title=f"Trajectory on the track{suffix}",
        ),
        "latent_force": latent_force_figure(
            dt,
            np.asarray(trajectory["disturbance"]),
            np.asarray(trajectory["latent_force_est"]),
            np.asarray(trajectory["latent_force_std"]),
            title=f"Latent force{suffix}",
        ),
        "acceleration": acceleration_figure(
            dt,
            np.asarray(trajectory["action"])[:, 0],
            np.asarray(trajectory["disturbance"]),
            accel_max=config.accel_max,
            title=f"Acceleration input vs disturbance{suffix}",
        ),
        "speed": speed_figure(
            dt,
            x[:, 2],
            est[:, 2],
            std[:, 2],
            config.speed_min,
            config.speed_max,
            title=f"Speed{suffix}",
        ),
    }


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


def replay_frames(
    true_state: np.ndarray,
    config: EnvConfig,
    screen_size: tuple[int, int] = (480, 240),
    scaling: float = 20.0,
    caption: str = "",
) -> list[np.ndarray]:
    """Frames of a saved episode drawn by the env's renderer, one per saved true state.

    This replays ``true_state``; it does not simulate anything.

    Args:
        true_state: ``(T+1, 4)`` true states ``[m, m, m/s, rad]``.
        config: env config of the run (track, goal, ``dt``).
        screen_size: frame ``(width, height)`` [px].
        scaling: [px/m].
        caption: text put before the time stamp on each frame.

    Returns:
        ``T+1`` RGB frames ``(height, width, 3)`` uint8.
    """
    from lfm_env.rendering import TrackScene

    scene = TrackScene(config.track, config, screen_size=screen_size, scaling=scaling)
    goal = np.asarray(config.goal, dtype=float)
    frames = []
    try:
        for k, state in enumerate(np.asarray(true_state, dtype=float)):
            scene.update(state)
            frame = scene.draw(goal, config.goal_radius)
            text = f"t = {k * config.dt:.1f} s | v = {state[2]:.1f} m/s"
            text = f"{caption} | {text}" if caption else text
            frames.append(annotate_frame(frame, text))
    finally:
        scene.close()
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
