"""The report's figures (``experiments.report.figures``): which episode is drawn, and that
every figure and the GIF show something."""

from __future__ import annotations

import imageio.v3 as iio
import pytest

from experiments.report.write import (
    load_results,
    load_trajectory,
    write_report,
)
from lfm_env.worlds.registry import load_env_config
from tests.experiments.saved_results import TINY, is_car, is_road


def test_report_figures_are_not_blank(report_path):
    for name in (
        "seed0_scenario_trajectory.png",
        "seed0_scenario_inputs.png",
        "metrics_by_agent.png",
        "solve_time.png",
    ):
        image = iio.imread(report_path.parent / "figures" / name)
        assert image.ndim == 3 and image.shape[0] > 200 and image.shape[1] > 400
        assert image[..., :3].std() > 10, name


def test_report_default_figure_seed_is_smallest_scenario_seed(report_path):
    figures = report_path.parent / "figures"
    assert (figures / "seed0_scenario_latent_force.png").is_file()
    assert not list(figures.glob("seed1_*"))


def test_gif_replays_every_saved_state(results_dir, report_path):
    results = load_results(results_dir)
    row = next(r for r in results.rows if r["agent"] == "scenario" and r["seed"] == 0)
    traj = load_trajectory(results, "scenario", 0)
    assert len(traj["true_state"]) == int(row["steps"]) + 1
    frames = iio.imread(report_path.parent / "figures" / "episode.gif", index=None)
    assert frames.shape[0] == int(row["steps"]) + 1
    # The world's scene (480 x 240) above a panel of the estimate and the scenario fan.
    assert frames.shape[1:3] == (240 + 160, 480)
    for frame in frames[:: max(1, len(frames) // 5)]:
        scene, panel = frame[:240], frame[240:]
        assert scene[..., :3].std() > 10
        assert is_road(scene).sum() > 200
        assert is_car(scene).sum() > 10
    for frame in frames[:-1:4]:  # every step but the last has an estimate and a plan
        panel = frame[240:, :, :3].astype(int)
        red = (panel[..., 0] > 180) & (panel[..., 1] < 90) & (panel[..., 2] < 90)
        navy = (panel[..., 0] < 60) & (panel[..., 1] < 60) & (panel[..., 2] > 90)
        assert red.sum() > 5 and navy.sum() > 5
    meta = iio.immeta(report_path.parent / "figures" / "episode.gif")
    assert meta["duration"] == pytest.approx(1000.0 * load_env_config(TINY).dt)


def test_figure_seed_option(results_copy):
    write_report(results_copy, figure_seed=2, gif=False)
    assert (results_copy / "figures" / "seed2_scenario_states.png").is_file()
    with pytest.raises(ValueError, match="seed 9"):
        write_report(results_copy, figure_seed=9, gif=False)
