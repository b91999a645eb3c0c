"""Tests of the report (``experiments.report.write``), its figures and the lfm-report/render
CLIs."""

from __future__ import annotations

import base64
import csv
import io
import re
import shutil
import subprocess
import sys
from pathlib import Path

import gymnasium as gym
import imageio.v3 as iio
import numpy as np
import pytest
import yaml

from experiments.cli import render_main, report_main
from experiments.evaluation import evaluate
from experiments.plots import episode as plots
from experiments.report.format import fmt_estimate
from experiments.report.write import (
    Results,
    bootstrap_ci,
    calibration,
    load_results,
    load_trajectory,
    paired_differences,
    pooled_ratio_ci,
    write_report,
)
from lfm_env.config import load_env_config

REPO = Path(__file__).resolve().parents[2]
TINY = {"env": {"max_steps": 20}, "agents": {"n_particles": 300, "n_scenarios": 5, "horizon": 5}}
AGENTS = ["nominal", "pf", "scenario", "oracle"]
SEEDS = [0, 1, 2]
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def is_road(frame: np.ndarray) -> np.ndarray:
    """Pixels of the white lane lines drawn by highway-env."""
    return np.all(frame[..., :3] >= 240, axis=-1)


def is_car(frame: np.ndarray) -> np.ndarray:
    """Pixels of the yellow car (highway-env's default vehicle colour (255, 255, 0))."""
    r, g, b = (frame[..., i].astype(int) for i in range(3))
    return (r >= 200) & (g >= 200) & (b <= 80)


@pytest.fixture(scope="session")
def results_dir(tmp_path_factory) -> Path:
    """A small results folder written by the evaluation: 4 agents x 3 seeds x 20 steps."""
    out = tmp_path_factory.mktemp("results") / "tiny"
    evaluate(AGENTS, SEEDS, config=TINY, out=out, progress=False)
    return out


@pytest.fixture(scope="session")
def report_path(results_dir) -> Path:
    return write_report(results_dir)


@pytest.fixture
def results_copy(results_dir, tmp_path) -> Path:
    """A private copy of the results folder that a test may alter."""
    dst = tmp_path / "copy"
    shutil.copytree(results_dir, dst, ignore=shutil.ignore_patterns("figures", "report.*"))
    return dst


def referenced_files(text: str, html: bool) -> list[str]:
    pattern = r'src="([^"]+)"' if html else r"!\[[^\]]*\]\(([^)]+)\)"
    return re.findall(pattern, text)


# --------------------------------------------------------------------------- the report


def test_report_has_agent_table_and_existing_figures(report_path):
    md = report_path.read_text()
    html_path = report_path.with_suffix(".html")
    html = html_path.read_text()
    assert report_path.name == "report.md" and html_path.is_file()
    for text in (md, html):
        assert "Results per agent" in text
        assert "oracle (upper bound)" in text
        for label in ("nominal MPC", "PF + CE MPC", "scenario MPC (paper)"):
            assert label in text
        for row in ("success rate", "max speed excess", "latent-force RMSE", "episodes"):
            assert row in text
        assert "Paper vs measured" in text and "Paired differences" in text
        assert "lfm_env/SineTrack-v0" in text and "sine_track" in text
    assert "| metric | nominal MPC |" in md
    # One row per constraint group metric of the sine track, with the group's unit.
    groups = [line.split(" | ")[0] for line in md.splitlines() if "excess [" in line]
    assert groups[:3] == [
        "| max track excess [m]",
        "| max x excess [m]",
        "| max speed excess [m/s]",
    ]
    assert "| x violation steps [steps] |" in md
    assert "<table>" in html and "<th>metric</th>" in html
    md_refs, html_refs = referenced_files(md, html=False), referenced_files(html, html=True)
    # The HTML shows the same figures as the Markdown, each embedded byte for byte.
    assert len(md_refs) == len(html_refs)
    for ref, src in zip(md_refs, html_refs, strict=True):
        assert src.startswith("data:image/"), src[:40]
        assert base64.b64decode(src.split(",", 1)[1]) == (report_path.parent / ref).read_bytes()
    pngs = [r for r in md_refs if r.endswith(".png")]
    # Five episode figures, two overlays of all agents, two across-seed plots.
    names = {Path(r).name for r in pngs}
    for name in ("trajectory", "latent_force", "inputs", "states", "constraints", "scenario_fan"):
        assert f"seed0_scenario_{name}.png" in names
    assert {"seed0_agents_trajectory.png", "seed0_agents_constraints.png"} <= names
    assert {"metrics_by_agent.png", "solve_time.png"} <= names
    for ref in md_refs:
        path = report_path.parent / ref
        assert path.is_file() and path.stat().st_size > 1000, ref
        assert path.parent.name == "figures"
    for ref in pngs:
        assert (report_path.parent / ref).read_bytes()[:8] == PNG_MAGIC, ref
    assert "figures/episode.gif" in md_refs


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


def test_errors_are_listed_not_dropped(results_copy):
    table = results_copy / "episodes.csv"
    with table.open(newline="") as fh:
        rows = list(csv.DictReader(fh))
    bad = dict(rows[0], agent="pf", seed="7", success="False", error="RuntimeError: boom")
    with table.open("a", newline="") as fh:
        csv.DictWriter(fh, list(rows[0])).writerow(bad)
    md = write_report(results_copy, gif=False).read_text()
    section = md.split("## Episodes with errors")[1].split("##")[0]
    assert "RuntimeError: boom" in section and "| PF + CE MPC | 7 |" in section
    errors_row = next(line for line in md.splitlines() if line.startswith("| episodes with errors"))
    assert errors_row == "| episodes with errors | 0 | 1 | 0 | 0 |"
    assert not (results_copy / "figures" / "episode.gif").exists()


def test_figure_seed_option(results_copy):
    write_report(results_copy, figure_seed=2, gif=False)
    assert (results_copy / "figures" / "seed2_scenario_states.png").is_file()
    with pytest.raises(ValueError, match="seed 9"):
        write_report(results_copy, figure_seed=9, gif=False)


def test_missing_or_empty_results_give_clear_errors(tmp_path, results_dir):
    missing = tmp_path / "nowhere"
    with pytest.raises(FileNotFoundError, match=re.escape(str(missing))):
        write_report(missing)
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(FileNotFoundError, match="episodes.csv"):
        write_report(empty)
    header_only = tmp_path / "header_only"
    header_only.mkdir()
    first_line = (results_dir / "episodes.csv").read_text().splitlines()[0]
    (header_only / "episodes.csv").write_text(first_line + "\n")
    with pytest.raises(ValueError, match="no episodes"):
        write_report(header_only)


# --------------------------------------------------------------------------- statistics


def test_bootstrap_ci_contains_mean_and_is_deterministic():
    values = np.random.default_rng(1).gamma(2.0, 1.5, size=25)
    est = bootstrap_ci(values)
    assert est.low <= est.mean <= est.high
    assert est.mean == pytest.approx(values.mean())
    assert est.n == 25 and est.high > est.low
    assert bootstrap_ci(values) == est  # same seed, same interval
    assert bootstrap_ci(list(values) + [np.nan]) == est  # NaN is left out
    wider = bootstrap_ci(values, level=0.99)
    assert wider.low <= est.low and wider.high >= est.high
    one = bootstrap_ci([3.0])
    assert (one.mean, one.low, one.high, one.n) == (3.0, 3.0, 3.0, 1)
    assert np.isnan(bootstrap_ci([np.nan]).mean) and bootstrap_ci([]).n == 0


def _row(agent: str, seed: int, cost: float, error: str = "") -> dict:
    return {"agent": agent, "seed": seed, "cost": cost, "time_to_goal": np.nan, "error": error}


def test_paired_differences_use_matching_seeds_only():
    rows = [
        _row("scenario", 0, 10.0),
        _row("scenario", 1, 20.0),
        _row("scenario", 2, 30.0),
        _row("scenario", 3, 40.0, error="RuntimeError: x"),  # errors never pair
        _row("pf", 1, 25.0),
        _row("pf", 2, 29.0),
        _row("pf", 3, 50.0),
        _row("pf", 4, 70.0),  # no scenario episode on seed 4
        _row("pf", 5, np.nan),
    ]
    results = Results(Path("."), rows, load_env_config(None))
    d = paired_differences(results, "cost", "pf")
    assert d.seeds == (1, 2)
    assert d.differences == (5.0, -1.0)
    assert d.estimate.mean == pytest.approx(2.0) and d.estimate.n == 2
    assert (d.agent_lower, d.reference_lower, d.ties) == (1, 1, 0)
    none = paired_differences(results, "time_to_goal", "pf")
    assert none.seeds == () and np.isnan(none.estimate.mean)


# --------------------------------------------------------------------------- plots


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
    # The acceleration is drawn against the disturbance (same unit); the steering is not.
    accel, steer = figs["inputs"].axes
    assert "disturbance w" in accel.get_legend_handles_labels()[1]
    assert "disturbance w" not in steer.get_legend_handles_labels()[1]
    # The speed panel shows the speed bounds, found from the speed constraints alone.
    speed = figs["states"].axes[0]
    assert speed.get_ylabel() == "v [m/s]"
    flat = {round(line.get_ydata()[0], 6) for line in speed.lines if len(line.get_ydata()) == 2}
    assert {cfg.speed_min, cfg.speed_max} <= flat


def test_report_of_a_folder_written_before_x_violation_steps(results_copy):
    """An older table (no x_violation_steps column) is reported with what it holds."""
    table = results_copy / "episodes.csv"
    with table.open(newline="") as fh:
        rows = list(csv.DictReader(fh))
    columns = [c for c in rows[0] if c != "x_violation_steps"]
    with table.open("w", newline="") as fh:
        writer = csv.DictWriter(fh, columns, extrasaction="ignore")
        writer.writeheader()
        writer.writerows(rows)
    md = write_report(results_copy, gif=False).read_text()
    line = next(x for x in md.splitlines() if x.startswith("| x violation steps"))
    assert line == "| x violation steps [steps] | n/a | n/a | n/a | n/a |"
    assert "| max x excess [m] | 0 [0, 0] |" in md


# --------------------------------------------------------------------------- command lines


@pytest.mark.parametrize("main", [report_main, render_main])
def test_cli_help(main, capsys):
    with pytest.raises(SystemExit) as exc:
        main(["--help"])
    assert exc.value.code == 0
    text = capsys.readouterr().out
    assert "usage:" in text and "examples:" in text
    if main is report_main:
        assert "--no-gif" in text and "--seed" in text
    else:
        assert all(opt in text for opt in ("--config", "--agent", "--seed", "--out", "--steps"))


@pytest.mark.parametrize("script", ["report.py", "render.py"])
def test_scripts_help(script):
    proc = subprocess.run(
        [sys.executable, str(REPO / "scripts" / script), "--help"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 0, proc.stderr
    assert "usage:" in proc.stdout


def test_report_main_writes_report(results_copy, capsys):
    assert report_main([str(results_copy), "--seed", "1", "--no-gif"]) == 0
    assert (results_copy / "report.html").is_file()
    assert (results_copy / "figures" / "seed1_scenario_trajectory.png").is_file()
    assert not (results_copy / "figures" / "episode.gif").exists()
    assert "report:" in capsys.readouterr().out


def test_report_main_missing_folder_exits_2(tmp_path, capsys):
    with pytest.raises(SystemExit) as exc:
        report_main([str(tmp_path / "nowhere")])
    assert exc.value.code == 2
    assert "nowhere" in capsys.readouterr().err


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


# --------------------------------------------------------------------------- another world

QUADROTOR_ID = "lfm_env/QuadrotorGust-v0"


@pytest.mark.skipif(QUADROTOR_ID not in gym.registry, reason="no quadrotor world")
def test_report_of_the_quadrotor_is_drawn_from_its_system(tmp_path):
    config = yaml.safe_load((REPO / "configs" / "quadrotor.yaml").read_text())
    config["env"]["max_steps"] = 15
    config["agents"].update(horizon=5, n_scenarios=5, n_particles=300)
    out = tmp_path / "quad"
    rows = evaluate(["nominal", "oracle"], [0], config=config, out=out, progress=False)
    assert all(r["error"] == "" for r in rows)
    assert "corridor_violation_steps" in rows[0] and "track_violation_steps" not in rows[0]
    md = write_report(out).read_text()
    assert "| max corridor excess [m] |" in md and "| x violation steps [steps] |" in md
    assert "track" not in md.lower() and "speed" not in md.lower()
    assert "Paper vs measured" not in md  # the sine track's own section
    results = load_results(out)
    cfg = results.config
    traj = load_trajectory(results, "nominal", 0)
    figs = plots.episode_figures(traj, results.system, cfg.dt, cfg.goal_state_rad, 0.3)
    labels = figs["trajectory"].axes[0].get_legend_handles_labels()[1]
    assert "bounds: corridor_floor, corridor_ceiling, x_min, x_max" in labels
    assert [ax.get_ylabel() for ax in figs["inputs"].axes] == ["T [N]", "theta_cmd [rad]"]
    for ref in referenced_files(md, html=False):
        assert (out / ref).is_file(), ref
    frames = iio.imread(out / "figures" / "episode.gif", index=None)
    assert frames.shape[0] == rows[0]["steps"] + 1 and frames[0].std() > 10


# --------------------------------------------------------------------------- tolerances


def table_line(md: str, label: str, section: str = "## Results per agent") -> list[str]:
    """The cells of the table row starting with ``label`` in ``section``."""
    text = md.split(section)[1].split("\n## ")[0]
    line = next(x for x in text.splitlines() if x.startswith(f"| {label} |"))
    return [c.strip() for c in line.strip("|").split(" | ")][1:]


def csv_values(results_dir: Path, agent: str, column: str) -> np.ndarray:
    with (results_dir / "episodes.csv").open(newline="") as fh:
        rows = [r for r in csv.DictReader(fh) if r["agent"] == agent]
    return np.array([float(r[column]) for r in sorted(rows, key=lambda r: int(r["seed"]))])


def test_report_has_tolerance_rows_and_zero_violation_fractions(results_dir, report_path):
    md = report_path.read_text()
    steps = csv_values(results_dir, "scenario", "track_violation_steps_over_0.01")
    assert len(steps) == 3
    scenario = AGENTS.index("scenario")
    row = table_line(md, "track violation steps > 0.01 m [steps]")
    assert row[scenario] == fmt_estimate(bootstrap_ci(steps))
    row = table_line(md, "track zero-violation episodes (> 0.01 m)")
    assert row[scenario] == fmt_estimate(bootstrap_ci(steps == 0))
    raw = csv_values(results_dir, "scenario", "track_violation_steps")
    assert table_line(md, "track zero-violation episodes")[scenario] == fmt_estimate(
        bootstrap_ci(raw == 0)
    )
    for label in ("x violation steps > 0.05 m [steps]", "speed violation steps > 0.05 m/s [steps]"):
        assert len(table_line(md, label)) == len(AGENTS)
    # The paired table has one row per metric, the tolerance counts among them.
    results = load_results(results_dir)
    d = paired_differences(results, "track_violation_steps_over_0.05", "pf")
    paired = table_line(md, "track violation steps > 0.05 m [steps]", "## Paired differences")
    others = [a for a in AGENTS if a != "scenario"]
    assert paired[others.index("pf")] == fmt_estimate(d.estimate) + " (3 seeds)"
    # "Paper vs measured" says which counts are tolerance-aware.
    section = md.split("## Paper vs measured")[1].split("\n## ")[0]
    zero = int(np.sum(steps == 0))
    assert f"tolerance-aware, beyond 0.01 m: zero in {zero} of 3 episodes" in section
    assert "beyond 0.05 m/s: zero in" in section


def drop_columns(table: Path, words: str) -> None:
    with table.open(newline="") as fh:
        rows = list(csv.DictReader(fh))
    columns = [c for c in rows[0] if words not in c]
    with table.open("w", newline="") as fh:
        writer = csv.DictWriter(fh, columns, extrasaction="ignore")
        writer.writeheader()
        writer.writerows(rows)


def test_old_folder_gets_tolerance_counts_from_its_trajectories(results_copy, results_dir):
    """A table written before the tolerance columns: counted from the saved episodes."""
    drop_columns(results_copy / "episodes.csv", "_over_")
    new = load_results(results_dir)
    old = load_results(results_copy)
    for a, b in zip(old.rows, new.rows, strict=True):
        for column in ("track_violation_steps_over_0.01", "speed_violation_steps_over_0.05"):
            assert a[column] == b[column]
    md = write_report(results_copy, gif=False).read_text()
    label = "track violation steps > 0.01 m [steps]"
    assert table_line(md, label) == table_line(write_report(results_dir).read_text(), label)


def test_old_folder_without_trajectories_leaves_tolerance_rows_out(results_copy):
    drop_columns(results_copy / "episodes.csv", "_over_")
    for path in (results_copy / "episodes").glob("*.npz"):
        path.unlink()
    md = write_report(results_copy, gif=False).read_text()
    assert "violation steps >" not in md and "zero-violation episodes (>" not in md
    assert "| track violation steps [steps] |" in md  # the raw counts are still there
    assert "| track zero-violation episodes |" in md
    assert "No agent with a filter has saved trajectories" in md


# --------------------------------------------------------------------------- calibration


def test_pooled_ratio_ci():
    est = pooled_ratio_ci([1.0, 2.0, 6.0], [2.0, 4.0, 6.0])
    assert est.mean == pytest.approx(9.0 / 12.0) and est.n == 3
    assert 0.5 <= est.low <= est.mean <= est.high <= 1.0  # between the episodes' own ratios
    assert pooled_ratio_ci([1.0, 2.0, 6.0], [2.0, 4.0, 6.0]) == est  # seeded
    root = pooled_ratio_ci([1.0, 2.0, 6.0], [2.0, 4.0, 6.0], root=True)
    assert (root.mean, root.low, root.high) == pytest.approx(
        (np.sqrt(est.mean), np.sqrt(est.low), np.sqrt(est.high))
    )
    assert pooled_ratio_ci([3.0, 5.0], [0.0, 5.0]).n == 1  # episodes without steps: out
    assert np.isnan(pooled_ratio_ci([], []).mean)


def test_calibration_pools_the_evaluations_per_episode_metrics(results_dir, report_path):
    """The pooled latent-force coverage and RMSE agree with the rows' per-episode values
    weighted by their steps (computed by the evaluation, another code path)."""
    results = load_results(results_dir)
    cals = {c.agent: c for c in calibration(results)}
    assert list(cals) == ["pf", "scenario"]  # the nominal MPC and the oracle have no filter
    for agent, cal in cals.items():
        steps = csv_values(results_dir, agent, "steps")
        coverage = csv_values(results_dir, agent, "latent_coverage")
        rmse = csv_values(results_dir, agent, "latent_rmse")
        assert cal.quantities[-1] == "latent force w [m/s^2]"
        assert cal.quantities[:4] == results.system.state_names
        assert cal.coverage[-1].mean == pytest.approx(np.sum(coverage * steps) / steps.sum())
        assert cal.rmse[-1].mean == pytest.approx(np.sqrt(np.sum(rmse**2 * steps) / steps.sum()))
        assert cal.steps == steps.sum() and cal.episodes == 3
        assert (cal.estimator, cal.estimator_source) == ("bootstrap", "recorded")
        for e in (*cal.coverage, *cal.rmse):
            assert e.low <= e.mean <= e.high
    md = report_path.read_text()
    assert "| quantity | PF + CE MPC: `bootstrap` | scenario MPC (paper): `bootstrap` |" in md
    row = table_line(md, "2-sigma coverage, latent force w", "## Estimator calibration")
    assert row == [
        fmt_estimate(cals["pf"].coverage[-1]),
        fmt_estimate(cals["scenario"].coverage[-1]),
    ]
    assert table_line(md, "RMSE, p_x [m]", "## Estimator calibration")[0] == fmt_estimate(
        cals["pf"].rmse[0]
    )
    assert (report_path.parent / "figures" / "estimator_calibration.png").is_file()


def test_calibration_names_the_configs_estimator_when_none_was_recorded(results_copy):
    for path in (results_copy / "episodes").glob("pf__seed*.npz"):
        with np.load(path, allow_pickle=False) as data:
            arrays = {k: data[k] for k in data.files if k != "estimator"}
        np.savez_compressed(path, **arrays)
    config = yaml.safe_load((results_copy / "config.yaml").read_text())
    config["agents"]["estimator"] = "ukf"  # as if the run had used it
    (results_copy / "config.yaml").write_text(yaml.safe_dump(config))
    cals = {c.agent: c for c in calibration(load_results(results_copy))}
    assert (cals["pf"].estimator, cals["pf"].estimator_source) == ("ukf", "config.yaml")
    assert (cals["scenario"].estimator, cals["scenario"].estimator_source) == (
        "bootstrap",
        "recorded",
    )
    md = write_report(results_copy, gif=False).read_text()
    assert "PF + CE MPC: `ukf`" in md and "The estimator of PF + CE MPC is the" in md


# --------------------------------------------------------------------------- self-contained


def embedded_images(html: str) -> list[tuple[str, bytes]]:
    """``(mime, bytes)`` of every ``data:`` image of a page; fails on any other reference."""
    refs = re.findall(r'(?:src|href)="([^"]+)"', html)
    assert refs and all(r.startswith("data:image/") for r in refs), [r[:60] for r in refs]
    out = []
    for ref in refs:
        head, data = ref[len("data:") :].split(";base64,", 1)
        out.append((head, base64.b64decode(data, validate=True)))
    return out


def test_html_alone_shows_every_figure(report_path, tmp_path):
    alone = tmp_path / "alone"
    alone.mkdir()
    shutil.copy(report_path.with_suffix(".html"), alone / "report.html")
    html = (alone / "report.html").read_text()
    assert 'src="figures/' not in html and "figures/" not in re.sub(r"data:[^\"]+", "", html)
    images = embedded_images(html)
    md_refs = referenced_files(report_path.read_text(), html=False)
    assert len(images) == len(md_refs) >= 10
    for (mime, raw), ref in zip(images, md_refs, strict=True):
        assert mime == ("image/gif" if ref.endswith(".gif") else "image/png"), ref
        pixels = iio.imread(io.BytesIO(raw), index=None)  # every frame decodes
        assert pixels.shape[-1] in (3, 4) and pixels[..., :3].std() > 10, ref


def test_a_gif_over_the_limit_is_embedded_as_a_labelled_still(results_copy, monkeypatch):
    from experiments.report import document

    monkeypatch.setattr(document, "GIF_EMBED_LIMIT", 1000)
    path = write_report(results_copy)
    html = path.with_suffix(".html").read_text()
    assert "data:image/gif" not in html
    assert "STILL (last frame) of the animation" in html and "figures/episode.gif" in html
    assert all(mime == "image/png" for mime, _ in embedded_images(html))
    assert "](figures/episode.gif)" in path.read_text()  # Markdown still links the GIF


# --------------------------------------------------------------------------- baseline


def paired_section(md: str) -> str:
    return md.split("## Paired differences against ")[1].split("\n## ")[0]


def test_paired_differences_against_the_chosen_baseline(results_copy, report_path):
    assert paired_section(report_path.read_text()).startswith("scenario MPC (paper)")
    path = write_report(results_copy, baseline="pf", gif=False)
    section = paired_section(path.read_text())
    assert section.startswith("PF + CE MPC")
    header = next(line for line in section.splitlines() if line.startswith("| metric"))
    assert header == "| metric | nominal MPC | scenario MPC (paper) | oracle (upper bound) |"
    results = load_results(results_copy)
    cost = next(line for line in section.splitlines() if line.startswith("| cost |"))
    for cell, agent in zip(cost.split(" | ")[1:], ("nominal", "scenario", "oracle"), strict=True):
        d = paired_differences(results, "cost", agent, "pf")
        assert d.reference == "pf" and cell.startswith(fmt_estimate(d.estimate))
    assert "- pf has a lower cost than scenario MPC (paper) in " in section


def test_unknown_baseline_names_the_agents(results_copy, capsys):
    with pytest.raises(ValueError, match="'bogus'.*choose one of nominal, pf, scenario, oracle"):
        write_report(results_copy, baseline="bogus")
    assert not (results_copy / "report.md").exists()  # refused before writing anything
    with pytest.raises(SystemExit) as exc:
        report_main([str(results_copy), "--baseline", "bogus"])
    assert exc.value.code == 2
    assert "choose one of nominal, pf, scenario, oracle" in capsys.readouterr().err
    assert report_main([str(results_copy), "--baseline", "oracle", "--no-gif"]) == 0
    assert (
        "## Paired differences against oracle (upper bound)"
        in (results_copy / "report.md").read_text()
    )


def test_default_baseline_without_the_scenario_agent_and_agents_of_any_name(results_copy):
    from experiments.report import choose_baseline

    table = results_copy / "episodes.csv"
    with table.open(newline="") as fh:
        rows = [r for r in csv.DictReader(fh) if r["agent"] != "scenario"]
    own = "tests.experiments.own_agents:Factory"  # a user's agent, named by its import path
    for r in rows:
        r["agent"] = own if r["agent"] == "pf" else r["agent"]
    with table.open("w", newline="") as fh:
        writer = csv.DictWriter(fh, list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    results = load_results(results_copy)
    assert results.agents == ["nominal", "oracle", own]
    assert choose_baseline(results) == "nominal"
    md = write_report(results_copy, gif=False).read_text()
    section = paired_section(md)
    assert section.startswith("nominal MPC")
    assert f"| metric | oracle (upper bound) | {own} |" in section  # the raw name as label


# --------------------------------------------------------------------------- loading


def test_one_load_results_for_every_reader(results_dir):
    from experiments import sweep
    from experiments.evaluation import run as evaluation
    from experiments.report import results
    from experiments.report import write as report

    assert report.load_results is results.load_results is load_results
    for module in (evaluation, sweep):
        assert not hasattr(module, "load_results")
    loaded = load_results(results_dir)
    assert isinstance(loaded, Results) and loaded.directory == results_dir
    assert loaded.system.name == "sine_track" and loaded.agents == AGENTS
    saved = evaluation.saved_rows(results_dir)  # the storage layer's episode records
    table = sorted(loaded.rows, key=lambda r: (r["agent"], r["seed"]))
    assert [(r["agent"], r["seed"]) for r in table] == [(r["agent"], r["seed"]) for r in saved]
    for a, b in zip(table, saved, strict=True):
        for column in ("success", "steps", "cost", "max_track_excess", "latent_rmse"):
            assert a[column] == pytest.approx(float(b[column]), nan_ok=True), column


def test_registered_agents_get_their_short_labels_and_order_then_the_others_sorted(tmp_path):
    from experiments.report.format import agent_label
    from experiments.report.results import Results

    assert agent_label("rl") == "RL baseline"
    assert agent_label("my_agent") == "my_agent"
    assert agent_label("scenario_particles", wrap=True) == "scenario MPC,\nparticle starts"
    names = ["zeta", "rl", "oracle", "alpha", "nominal", "pf"]
    rows = [{"agent": n, "seed": 0, "error": ""} for n in names]
    results = Results(directory=tmp_path, rows=rows, config=None)
    assert results.agents == ["nominal", "pf", "oracle", "rl", "alpha", "zeta"]
