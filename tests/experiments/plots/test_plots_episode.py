"""One episode's figures (``experiments.plots.episode``), drawn from the definition of a
system the library does not know (a point mass defined in the tests)."""

from __future__ import annotations

import numpy as np
import pytest

from experiments import plots
from experiments.plots import summary as summary_plots
from lfm_env.system import ControlSystem
from tests.experiments.plots.point_mass import (
    DT,
    GOAL,
    OBSTACLE,
    SPEED_MAX,
    SYSTEM,
    WALL_Y,
    rendered,
    synthetic_episode,
)


def pixel(fig, ax, image: np.ndarray, x: float, y: float) -> np.ndarray:
    """The RGB colour of the figure at data point ``(x, y)`` of ``ax``."""
    px, py = ax.transData.transform((x, y))
    return image[image.shape[0] - int(round(py)), int(round(px))]


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
        SYSTEM, DT, ep["latent_force"], ep["latent_force_est"], ep["latent_force_std"]
    )
    assert [ax.get_ylabel() for ax in fig.axes] == [
        "latent force w_x [m/s^2]",
        "latent force w_y [N]",
    ]
    with pytest.raises(ValueError, match=r"latent_force of shape \(30,\)"):
        plots.latent_force_figure(SYSTEM, DT, ep["latent_force"][:, 0])


def test_inputs_figure_draws_bounds_and_the_force_of_the_same_unit():
    ep = synthetic_episode()
    fig = plots.inputs_figure(SYSTEM, DT, ep["action"], ep["latent_force"])
    first, second = fig.axes
    assert (first.get_ylabel(), second.get_ylabel()) == ("a_x [m/s^2]", "f_y [N]")
    # w_x shares a_x's unit and w_y shares f_y's: each is drawn beside its input only.
    assert "latent_force w_x" in first.get_legend_handles_labels()[1]
    assert "latent_force w_y" not in first.get_legend_handles_labels()[1]
    assert "latent_force w_y" in second.get_legend_handles_labels()[1]
    levels = {round(line.get_ydata()[0], 6) for line in second.lines if len(line.get_ydata()) == 2}
    assert {-3.0, 3.0} <= levels  # f_y's bounds
    no_force = plots.inputs_figure(SYSTEM, DT, ep["action"])
    assert "latent_force w_x" not in no_force.axes[0].get_legend_handles_labels()[1]


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
        "latent_force": np.zeros(3),
        "latent_force_est": np.full(3, np.nan),
        "latent_force_std": np.full(3, np.nan),
    }
    assert list(plots.episode_figures(free, unconstrained, DT)) == [
        "trajectory",
        "latent_force",
        "inputs",
    ]


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
