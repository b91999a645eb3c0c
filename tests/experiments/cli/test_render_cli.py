"""``lfm-render`` (``experiments.cli.render``): one episode drawn with the world's renderer."""

from __future__ import annotations

from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest
import yaml

from experiments import plots
from experiments.cli import render_main
from experiments.report.write import (
    load_results,
    load_trajectory,
)
from tests.experiments.saved_results import PNG_MAGIC, TINY, is_car, is_road


@pytest.fixture
def tiny_config(tmp_path) -> Path:
    path = tmp_path / "tiny.yaml"
    path.write_text(yaml.safe_dump(TINY))
    return path


def test_render_png_shows_road_and_car(tiny_config, tmp_path):
    out = tmp_path / "x.png"
    argv = ["--config", str(tiny_config), "--agent", "scenario", "--seed", "0"]
    assert render_main([*argv, "--out", str(out), "--steps", "3"]) == 0
    assert out.read_bytes()[:8] == PNG_MAGIC
    frame = iio.imread(out)
    assert frame.shape[:2] == (240, 480)
    assert is_road(frame).sum() > 200
    assert is_car(frame).sum() > 10


def test_render_gif_is_the_evaluated_episode(tiny_config, tmp_path, results_dir):
    out = tmp_path / "sub" / "x.gif"
    argv = ["--config", str(tiny_config), "--agent", "pf", "--seed", "1", "--steps", "4"]
    assert render_main([*argv, "--out", str(out)]) == 0
    frames = iio.imread(out, index=None)
    assert frames.shape[0] == 5
    assert all(is_car(f).sum() > 10 for f in frames)
    # Same config, agent and seed as the evaluation: the same states, so the same pixels
    # as a replay of the saved trajectory (below the caption strip, whose text differs).
    results = load_results(results_dir)
    saved = load_trajectory(results, "pf", 1)["true_state"][:5]
    replay = plots.replay_frames(saved, results.config)
    for a, b in zip(frames, replay, strict=True):
        np.testing.assert_array_equal(a[20:, :, :3], b[20:, :, :3])


def test_render_rejects_bad_arguments(tiny_config, tmp_path, capsys):
    base = ["--config", str(tiny_config), "--steps", "1"]
    for extra in (["--out", str(tmp_path / "x.jpg")], ["--agent", "nope", "--out", "x.gif"]):
        with pytest.raises(SystemExit) as exc:
            render_main(base + extra)
        assert exc.value.code == 2
    assert "--agent nope" in capsys.readouterr().err
