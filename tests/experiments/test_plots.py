"""Tests of the generic episode figures (``experiments.plots.episode``) on a system of their own.

The figures must come from the system definition alone: a point mass in the plane with
two force components, a wall and a round obstacle in the plane of its position, and a
speed bound, none of which the plotting code knows by name.
"""

from __future__ import annotations

import types

import gymnasium as gym
import numpy as np
import pytest

from experiments.plots import episode as plots
from experiments.plots import scenario_fan
from experiments.plots import summary as summary_plots
from lfm_env import gp
from lfm_env.env import LatentForceEnv
from lfm_env.model import LatentForceModel
from lfm_env.system import ControlSystem, QuadraticCost, xp

WALL_Y = 2.0  # [m] the wall: y <= 2
OBSTACLE = (2.0, 1.6, 0.4)  # [m] centre x, centre y and radius of the round obstacle
SPEED_MAX = 1.5  # [m/s] bound on v_x
DT = 0.1  # [s]


def point_mass_rhs(x, u, w):
    _, _, vx, vy = xp.unstack(x)
    ax, ay = xp.unstack(u)
    wx, wy = xp.unstack(w)
    return xp.stack([vx, vy, ax + wx, ay + wy])


def point_mass_constraints(x):
    px, py, vx, _ = xp.unstack(x)
    cx, cy, r = OBSTACLE
    return xp.stack([py - WALL_Y, r - xp.sqrt((px - cx) ** 2 + (py - cy) ** 2), vx - SPEED_MAX])


def point_mass_system() -> ControlSystem:
    return ControlSystem(
        name="point_mass",
        state_names=("q_x [m]", "q_y [m]", "v_x [m/s]", "v_y [m/s]"),
        input_names=("a_x [m/s^2]", "f_y [N]"),
        rhs=point_mass_rhs,
        input_lower=(-2.0, -3.0),
        input_upper=(2.0, 3.0),
        constraints=point_mass_constraints,
        constraint_names=("wall [m]", "obstacle [m]", "speed_x [m/s]"),
        force_names=("w_x [m/s^2]", "w_y [N]"),
        constraint_groups={"keep_out": (0, 1), "speed": (2,)},
    )


SYSTEM = point_mass_system()
GOAL = np.array([5.0, 0.5, 0.0, 0.0])


def synthetic_episode(T: int = 30) -> dict[str, np.ndarray]:
    """Arrays shaped as a saved episode of the point mass: a straight path below the obstacle."""
    t = np.arange(T + 1) * DT
    x = np.stack([t * 1.8, 0.3 + 0.3 * t, 1.8 + 0.05 * np.sin(t), np.full_like(t, 0.3)], axis=1)
    est = x[:T] + 0.02
    w = np.stack([np.sin(t[:T]), np.cos(t[:T])], axis=1)
    excess = np.maximum(SYSTEM.constraint_excess(x[1:]), 0.0)
    return {
        "true_state": x,
        "estimate": np.concatenate([est, np.zeros((T, 3))], axis=1),  # + latent states
        "estimate_std": np.full((T, 7), 0.05),
        "action": np.tile([0.5, -1.0], (T, 1)),
        "disturbance": w,
        "latent_force_est": w + 0.1,
        "latent_force_std": np.full((T, 2), 0.2),
        "keep_out_excess": excess[:, :2].max(axis=1),
        "speed_excess": excess[:, 2],
    }


def rendered(fig) -> np.ndarray:
    fig.canvas.draw()
    return np.asarray(fig.canvas.buffer_rgba())[..., :3]


def pixel(fig, ax, image: np.ndarray, x: float, y: float) -> np.ndarray:
    """The RGB colour of the figure at data point ``(x, y)`` of ``ax``."""
    px, py = ax.transData.transform((x, y))
    return image[image.shape[0] - int(round(py)), int(round(px))]


# --------------------------------------------------------------------------- the system


def test_constraint_structure_and_units_come_from_the_system():
    deps = plots.constraint_dependencies(SYSTEM)
    assert deps == (frozenset({1}), frozenset({0, 1}), frozenset({2}))
    assert plots.constraints_on(SYSTEM, (0, 1)) == (0, 1)
    assert plots.constraints_on(SYSTEM, (2,)) == (2,)
    assert plots.group_unit(SYSTEM, "keep_out") == "m"
    assert plots.group_unit(SYSTEM, "speed") == "m/s"
    assert plots.force_unit(SYSTEM) == "m/s^2, N"
    with pytest.raises(ValueError, match="'track'.*keep_out"):
        plots.group_unit(SYSTEM, "track")


def test_state_bounds_are_the_zeros_of_constraints_on_that_state_alone():
    assert plots.state_bounds(SYSTEM, 2, -5.0, 5.0) == pytest.approx([SPEED_MAX], abs=1e-3)
    assert plots.state_bounds(SYSTEM, 1, -5.0, 5.0, GOAL) == pytest.approx([WALL_Y], abs=1e-3)
    # The obstacle depends on both positions: it bounds neither alone; v_y has no bound.
    assert plots.state_bounds(SYSTEM, 0, -10.0, 10.0) == []
    assert plots.state_bounds(SYSTEM, 3, -10.0, 10.0) == []


# --------------------------------------------------------------------------- the figures


def test_trajectory_figure_shades_where_the_system_is_infeasible():
    ep = synthetic_episode()
    fig = plots.trajectory_figure(
        SYSTEM, ep["true_state"], ep["estimate"], ep["estimate_std"], goal_state=GOAL
    )
    ax = fig.axes[0]
    assert ax.get_xlabel() == "q_x [m]" and ax.get_ylabel() == "q_y [m]"
    # The limits take in the wall near the data (y up to 1.2 m, the wall at 2 m).
    assert ax.get_ylim()[1] > WALL_Y
    image = rendered(fig)
    grey, white = np.array([224, 224, 224]), np.array([255, 255, 255])
    cx, cy, _ = OBSTACLE
    # Points off grid lines, paths and markers: in the disc, beyond the wall, feasible.
    assert np.abs(pixel(fig, ax, image, cx + 0.15, cy).astype(int) - grey).max() <= 3
    assert np.abs(pixel(fig, ax, image, 0.5, WALL_Y + 0.05).astype(int) - grey).max() <= 3
    assert np.array_equal(pixel(fig, ax, image, 4.5, 1.9), white)
    labels = ax.get_legend_handles_labels()[1]
    assert "bounds: wall, obstacle" in labels and "goal" in labels and "true path" in labels


def test_paths_figure_draws_every_agent():
    ep = synthetic_episode()
    other = ep["true_state"] * [1.0, 0.5, 1.0, 1.0]
    fig = plots.paths_figure(SYSTEM, {"A": (ep["true_state"], "tab:blue"), "B": (other, "red")})
    labels = fig.axes[0].get_legend_handles_labels()[1]
    assert {"A", "B", "end of episode"} <= set(labels)
    with pytest.raises(ValueError, match="plane"):
        plots.paths_figure(SYSTEM, {"A": (other, "red")}, plane=(0, 0))


def test_latent_force_figure_has_one_panel_per_component():
    ep = synthetic_episode()
    fig = plots.latent_force_figure(
        SYSTEM, DT, ep["disturbance"], ep["latent_force_est"], ep["latent_force_std"]
    )
    assert [ax.get_ylabel() for ax in fig.axes] == [
        "latent force w_x [m/s^2]",
        "latent force w_y [N]",
    ]
    with pytest.raises(ValueError, match=r"disturbance of shape \(30,\)"):
        plots.latent_force_figure(SYSTEM, DT, ep["disturbance"][:, 0])


def test_inputs_figure_draws_bounds_and_the_force_of_the_same_unit():
    ep = synthetic_episode()
    fig = plots.inputs_figure(SYSTEM, DT, ep["action"], ep["disturbance"])
    first, second = fig.axes
    assert (first.get_ylabel(), second.get_ylabel()) == ("a_x [m/s^2]", "f_y [N]")
    # w_x shares a_x's unit and w_y shares f_y's: each is drawn beside its input only.
    assert "disturbance w_x" in first.get_legend_handles_labels()[1]
    assert "disturbance w_y" not in first.get_legend_handles_labels()[1]
    assert "disturbance w_y" in second.get_legend_handles_labels()[1]
    levels = {round(line.get_ydata()[0], 6) for line in second.lines if len(line.get_ydata()) == 2}
    assert {-3.0, 3.0} <= levels  # f_y's bounds
    no_force = plots.inputs_figure(SYSTEM, DT, ep["action"])
    assert "disturbance w_x" not in no_force.axes[0].get_legend_handles_labels()[1]


def test_states_figure_draws_the_other_states_with_their_bounds():
    ep = synthetic_episode()
    fig = plots.states_figure(SYSTEM, DT, ep["true_state"], ep["estimate"], ep["estimate_std"])
    assert [ax.get_ylabel() for ax in fig.axes] == ["v_x [m/s]", "v_y [m/s]"]
    speed = fig.axes[0]
    flat = [line.get_ydata()[0] for line in speed.lines if len(set(line.get_ydata())) == 1]
    assert any(abs(y - SPEED_MAX) < 1e-3 for y in flat)
    assert speed.get_ylim()[0] < SPEED_MAX < speed.get_ylim()[1]
    two_states = ControlSystem("pair", ("a [m]", "b [m]"), ("u [1]",), lambda x, u, w: x, [-1], [1])
    assert plots.states_figure(two_states, DT, np.zeros((3, 2))) is None


def test_constraint_excess_figure_has_one_panel_per_group():
    ep = synthetic_episode()
    runs = {
        "A": (plots.group_excess_of(ep, SYSTEM), "tab:blue"),
        "B": ({"speed": ep["speed_excess"] * 0.5}, "red"),  # a run without one group
    }
    fig = plots.constraint_excess_figure(SYSTEM, DT, runs)
    keep_out, speed = fig.axes
    assert keep_out.get_ylabel() == "keep_out excess [m]"
    assert speed.get_ylabel() == "speed excess [m/s]"
    assert len(speed.get_lines()) == 3 and len(keep_out.get_lines()) == 2  # + the zero line
    # The excess after step k is drawn at (k+1) dt.
    np.testing.assert_allclose(speed.get_lines()[0].get_xdata()[:2], [DT, 2 * DT])
    np.testing.assert_array_equal(speed.get_lines()[0].get_ydata(), ep["speed_excess"])


def test_episode_figures_of_a_new_system(tmp_path):
    ep = synthetic_episode()
    figs = plots.episode_figures(ep, SYSTEM, DT, goal_state=GOAL, goal_radius=0.3, label="me")
    assert list(figs) == ["trajectory", "latent_force", "inputs", "states", "constraints"]
    for name, fig in figs.items():
        path = plots.save_figure(fig, tmp_path / f"{name}.png")
        image = rendered(fig)
        assert path.stat().st_size > 1000 and image.std() > 10, name
    unconstrained = ControlSystem(
        "free", ("a [m]", "b [m]"), ("u [1]",), lambda x, u, w: x, [-1], [1]
    )
    free = {
        "true_state": np.zeros((4, 2)),
        "estimate": np.zeros((3, 2)),
        "estimate_std": np.zeros((3, 2)),
        "action": np.zeros((3, 1)),
        "disturbance": np.zeros(3),
        "latent_force_est": np.full(3, np.nan),
        "latent_force_std": np.full(3, np.nan),
    }
    assert list(plots.episode_figures(free, unconstrained, DT)) == [
        "trajectory",
        "latent_force",
        "inputs",
    ]


# --------------------------------------------------------------------------- replays


class DotScene:
    """Draws the position as a white 2 x 2 block on black, 1 px per 0.1 m, below the caption."""

    def __init__(self) -> None:
        self.state = np.zeros(4)
        self.closed = False

    def update(self, state: np.ndarray) -> None:
        self.state = np.asarray(state, dtype=float)

    def draw(self) -> np.ndarray:
        frame = np.zeros((60, 80, 3), dtype=np.uint8)
        col, row = int(self.state[0] * 10), 30 + int(self.state[1] * 10)
        frame[row : row + 2, col : col + 2] = 255
        return frame

    def close(self) -> None:
        self.closed = True


class DotEnv(LatentForceEnv):
    """The point mass as an env whose renderer takes no size or scaling options."""

    def __init__(self, config=None, render_mode=None) -> None:
        model = LatentForceModel(
            SYSTEM, kernel=[gp.matern(1.5, 0.1, 1.0)] * 2, dt=DT, process_noise_std=[0.0] * 4
        )
        cost = QuadraticCost(Q=[1, 1, 0, 0], R=[0.1, 0.1], x_goal=GOAL)
        super().__init__(
            model,
            cost,
            initial_state=np.zeros(4),
            measurement_std=[0.01] * 4,
            render_mode=render_mode,
            scene_factory=lambda env: DotScene(),
        )


DOT_ID = "test_plots/Dot-v0"
if DOT_ID not in gym.registry:
    gym.register(DOT_ID, entry_point=DotEnv)


def test_replay_draws_saved_states_with_the_worlds_own_scene():
    states = np.array([[1.0, 1.0, 0, 0], [2.0, 1.5, 0, 0], [3.5, 2.5, 0, 0]])
    config = types.SimpleNamespace(env_id=DOT_ID, env={"any": "world config"})
    # screen_size and scaling are dropped: this world's env does not take them.
    frames = plots.replay_frames(states, config, screen_size=(10, 10), caption="dot")
    assert len(frames) == 3
    for frame, (x, y, _, _) in zip(frames, states, strict=True):
        assert frame.shape == (60, 80, 3)
        row, col = 30 + int(y * 10), int(x * 10)
        assert frame[row, col].tolist() == [255, 255, 255]
        assert frame[row + 3 :, col + 3 :].max() == 0  # nothing else drawn below-right
    assert frames[0][:12].std() > 0  # the caption strip
    with pytest.raises(ValueError, match="ENV_ID"):
        plots.replay_frames(states, object())


# --------------------------------------------------------------------------- calibration


def test_calibration_figure_sets_estimators_side_by_side():
    quantities = [*SYSTEM.state_names, *(f"latent force {w}" for w in SYSTEM.force_names)]
    rng = np.random.default_rng(0)
    coverage = np.sort(rng.uniform(0.6, 1.0, size=(2, len(quantities), 3)), axis=-1)[..., [1, 0, 2]]
    rmse = np.sort(rng.uniform(0.1, 1.0, size=(2, len(quantities), 3)), axis=-1)[..., [1, 0, 2]]
    agents = {"PF (bootstrap)": "tab:orange", "robust (rbpf)": "tab:red"}
    fig = plots.calibration_figure(quantities, agents, coverage, rmse)
    axes = np.array(fig.axes).reshape(2, len(quantities))
    for q, name in enumerate(quantities):
        top, bottom = axes[:, q]
        np.testing.assert_allclose([b.get_height() for b in top.patches], coverage[:, q, 0])
        np.testing.assert_allclose([b.get_height() for b in bottom.patches], rmse[:, q, 0])
        assert top.get_title() == name.split(" [")[0]
        assert bottom.get_ylabel() == f"RMSE [{plots.unit_of(name)}]"
        # The calibrated level is drawn in every coverage panel.
        assert any(np.allclose(line.get_ydata(), 0.9545) for line in top.lines)
    assert [t.get_text() for t in fig.legends[0].get_texts()] == list(agents)
    assert rendered(fig).std() > 10


# --------------------------------------------------------------------------- scenario fan


def fanned_episode(T: int = 30, S: int = 6, N: int = 5) -> dict[str, np.ndarray]:
    """The synthetic episode with a fan of ``S`` straight predictions of ``N`` steps per step:
    scenario ``s`` drifts by ``0.002 s`` m per step in y (a known, small spread)."""
    traj = synthetic_episode(T)
    x = traj["true_state"]
    steps = np.arange(N + 1)[:, None] * (x[1] - x[0])  # (N+1, nx) straight ahead
    fans = x[:T, None, None, :] + steps[None, None]  # (T, 1, N+1, nx)
    fans = np.repeat(fans, S, axis=1)
    fans[..., 1] += 0.002 * np.arange(S)[None, :, None] * np.arange(N + 1)[None, None, :]
    traj["predicted_scenarios"] = fans.astype(np.float32)
    traj["predicted"] = fans[:, 0]
    return traj


def fan_collections(ax) -> list:
    from matplotlib.collections import LineCollection

    return [c for c in ax.collections if isinstance(c, LineCollection)]


def test_scenario_fan_figure_draws_every_saved_scenario_at_four_steps():
    traj = fanned_episode()
    traj["predicted_scenarios"][10, 4:] = np.nan  # a step with fewer scenarios (padding)
    fig = plots.scenario_fan_figure(SYSTEM, traj, DT, steps=[0, 10, 20, 29], goal_state=GOAL)
    panels = [ax for ax in fig.axes if ax.get_visible() and ax.get_title().startswith("t = ")]
    assert len(panels) == 4
    for ax, k, n in zip(panels, (0, 10, 20, 29), (6, 4, 6, 6), strict=True):
        assert f"(step {k})" in ax.get_title()
        (fan,) = fan_collections(ax)  # one collection: one line per saved scenario
        assert len(fan.get_segments()) == n
        np.testing.assert_allclose(fan.get_segments()[0][0], traj["true_state"][k, :2], atol=1e-5)
        assert ax.get_aspect() == 1.0  # lengths to scale
    # The spread at the horizon's end, in the plane's unit: (S - 1) * 0.002 * N.
    assert "0.05 m" in panels[0].get_title()
    # The fan is far narrower than the panel: an inset magnifies its end.
    insets = [a for ax in panels for a in ax.child_axes if a.get_title().startswith("its end")]
    assert len(insets) == 4 and all(len(fan_collections(ax)) == 1 for ax in insets)


def test_scenario_fan_figure_default_steps_and_older_files():
    traj = fanned_episode(T=30)
    assert scenario_fan.fan_steps(traj["predicted_scenarios"]) == [0, 10, 19, 29]
    del traj["predicted_scenarios"]  # a file of before the saved fans: one scenario each
    fig = plots.scenario_fan_figure(SYSTEM, traj, DT, goal_state=GOAL)
    panels = [ax for ax in fig.axes if ax.get_title().startswith("t = ")]
    assert [len(fan_collections(ax)[0].get_segments()) for ax in panels] == [1, 1, 1, 1]
    assert "only the first scenario" in fig._suptitle.get_text()
    traj["predicted"] = np.full_like(traj["predicted"], np.nan)  # an agent without a plan
    assert plots.scenario_fan_figure(SYSTEM, traj, DT) is None


def test_plan_panel_frames_show_the_estimate_and_the_fan():
    traj = fanned_episode(T=12)
    frames = plots.plan_panel_frames(SYSTEM, traj, size=(320, 160), goal_state=GOAL)
    assert len(frames) == 13 and frames[0].shape == (160, 320, 3)
    for frame in frames[:-1]:
        f = frame.astype(int)
        red = (f[..., 0] > 180) & (f[..., 1] < 90) & (f[..., 2] < 90)
        navy = (f[..., 0] < 60) & (f[..., 1] < 60) & (f[..., 2] > 90)
        assert red.sum() > 5 and navy.sum() > 5
    last = frames[-1].astype(int)  # after the final step: no estimate, no plan
    assert not ((last[..., 0] > 180) & (last[..., 1] < 90) & (last[..., 2] < 90)).any()
    stacked = plots.stack_frames([np.zeros((50, 300, 3), np.uint8)] * 13, frames)
    assert stacked[0].shape == (210, 320, 3) and (stacked[0][:50, 300:] == 255).all()


def test_plane_figures_are_to_scale_and_agent_labels_stay_short():
    fig = plots.trajectory_figure(SYSTEM, synthetic_episode()["true_state"], goal_state=GOAL,
                                  goal_radius=0.3)  # fmt: skip
    assert fig.axes[0].get_aspect() == 1.0  # the goal disc is a circle
    values = {name: np.arange(3.0) for name in ("nominal MPC", "tests.experiments.own:Factory")}
    fig = plots.metric_distributions_figure({"cost": values}, ["nominal", "own"])
    labels = [t.get_text() for t in fig.axes[0].get_xticklabels()]
    assert labels[0] == "nominal MPC" and labels[1].endswith("own:Factory")
    assert len(labels[1]) <= summary_plots.TICK_LABEL_CHARS
    assert all(t.get_rotation() == 30 for t in fig.axes[0].get_xticklabels())


def test_registered_agents_keep_their_colours_and_others_get_a_stable_fallback():
    from controllers.agents.registry import AGENT_REGISTRY
    from experiments.plots.style import agent_colour

    assert {n: agent_colour(n) for n in AGENT_REGISTRY} == {
        n: s.colour for n, s in AGENT_REGISTRY.items()
    }
    assert agent_colour("rl") == "tab:olive"  # what its name got before it had a record
    assert agent_colour("my_agent") == agent_colour("my_agent") != ""
