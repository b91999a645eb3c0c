"""The episode figures (``experiments.plots.episode``) drawn from a saved sine-track
evaluation."""

from __future__ import annotations

import numpy as np

from experiments import plots
from experiments.report.write import (
    load_results,
    load_trajectory,
)
from tests.experiments.saved_results import PNG_MAGIC


def test_episode_figures_of_an_agent_without_filter(results_dir, tmp_path):
    results = load_results(results_dir)
    traj = load_trajectory(results, "nominal", 1)
    assert np.all(np.isnan(traj["latent_force_est"]))
    cfg = results.config
    figs = plots.episode_figures(
        traj, results.system, cfg.dt, cfg.goal_state_rad, cfg.goal_radius, "nominal MPC"
    )
    assert list(figs) == ["trajectory", "latent_force", "inputs", "states", "constraints"]
    for name, fig in figs.items():
        path = plots.save_figure(fig, tmp_path / f"{name}.png")
        assert path.read_bytes()[:8] == PNG_MAGIC


def test_sine_track_figures_keep_the_papers_content(results_dir):
    """Drawn from the system alone, the figures still show the paper's quantities."""
    results = load_results(results_dir)
    cfg = results.config
    traj = load_trajectory(results, "scenario", 0)
    figs = plots.episode_figures(traj, results.system, cfg.dt, cfg.goal_state_rad, 1.0)
    plane = figs["trajectory"].axes[0]
    labels = plane.get_legend_handles_labels()[1]
    assert "bounds: track_left, track_right, x_min, x_max" in labels
    assert plane.get_xlim()[0] < cfg.x_min and plane.get_xlim()[1] > cfg.x_max  # x bounds
    pad = cfg.track_amplitude + cfg.track_half_width
    assert plane.get_ylim()[0] < -pad and plane.get_ylim()[1] > pad  # the whole band
    # The acceleration is drawn against the latent force (same unit); the steering is not.
    accel, steer = figs["inputs"].axes
    assert "latent_force w" in accel.get_legend_handles_labels()[1]
    assert "latent_force w" not in steer.get_legend_handles_labels()[1]
    # The speed panel shows the speed bounds, found from the speed constraints alone.
    speed = figs["states"].axes[0]
    assert speed.get_ylabel() == "v [m/s]"
    flat = {round(line.get_ydata()[0], 6) for line in speed.lines if len(line.get_ydata()) == 2}
    assert {cfg.speed_min, cfg.speed_max} <= flat
