"""The report's sections and tables (``experiments.report.write.write_report``), on a small saved
evaluation."""

from __future__ import annotations

import base64
import csv
import re
from pathlib import Path

import gymnasium as gym
import imageio.v3 as iio
import numpy as np
import pytest
import yaml

from experiments import plots
from experiments.cli import report_main
from experiments.evaluation import evaluate
from experiments.report.format import fmt_estimate
from experiments.report.write import (
    bootstrap_ci,
    load_results,
    load_trajectory,
    paired_differences,
    write_report,
)
from tests.experiments.saved_results import (
    AGENTS,
    PNG_MAGIC,
    REPO,
    add_error_row,
    copy_episodes,
    csv_values,
    referenced_files,
    rewrite_episodes,
    table_line,
)


def test_report_has_agent_table_and_existing_figures(report_path):
    md = report_path.read_text()
    html_path = report_path.with_suffix(".html")
    html = html_path.read_text()
    assert report_path.name == "report.md" and html_path.is_file()
    for text in (md, html):
        assert "Results per agent" in text
        assert "oracle (reads the truth)" in text
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


def test_errors_are_listed_not_dropped(results_copy):
    add_error_row(results_copy, "pf", 7, "RuntimeError: boom")
    md = write_report(results_copy, gif=False).read_text()
    section = md.split("## Episodes with errors")[1].split("##")[0]
    assert "RuntimeError: boom" in section and "| PF + CE MPC | 7 |" in section
    errors_row = next(line for line in md.splitlines() if line.startswith("| episodes with errors"))
    assert errors_row == "| episodes with errors | 0 | 1 | 0 | 0 |"
    assert not (results_copy / "figures" / "episode.gif").exists()


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


QUADROTOR_ID = "lfm_env/QuadrotorGust-v1"


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
    assert "## Estimator calibration" not in md  # no trajectory: nothing to calibrate


def paired_section(md: str) -> str:
    return md.split("## Paired differences against ")[1].split("\n## ")[0]


def test_paired_differences_against_the_chosen_baseline(results_copy, report_path):
    assert paired_section(report_path.read_text()).startswith("scenario MPC (paper)")
    path = write_report(results_copy, baseline="pf", gif=False)
    section = paired_section(path.read_text())
    assert section.startswith("PF + CE MPC")
    header = next(line for line in section.splitlines() if line.startswith("| metric"))
    assert header == "| metric | nominal MPC | scenario MPC (paper) | oracle (reads the truth) |"
    results = load_results(results_copy)
    cost = next(line for line in section.splitlines() if line.startswith("| cost |"))
    for cell, agent in zip(cost.split(" | ")[1:], ("nominal", "scenario", "oracle"), strict=True):
        d = paired_differences(results, "cost", agent, "pf")
        assert d.reference == "pf" and cell.startswith(fmt_estimate(d.estimate))
    plain = section.split("In plain words:")[1].strip().splitlines()
    assert plain[0].startswith("- `pf` has fewer track violation steps > 0.01 m on ")
    assert plain[0].endswith(" than `nominal`.") and len(plain) == 3
    headline = md_section(path.read_text(), "Headline: metrics that do not reward failing")
    assert "time to goal vs `pf` [s]" in headline  # the same baseline in every paired table


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
        "## Paired differences against oracle (reads the truth)"
        in (results_copy / "report.md").read_text()
    )


def test_default_baseline_without_the_scenario_agent_and_agents_of_any_name(results_copy):
    from experiments.report import choose_baseline

    own = "tests.experiments.own_agents.Factory"  # a user's agent, named by its import path
    rewrite_episodes(results_copy, {"nominal": "nominal", "pf": own, "oracle": "oracle"})
    results = load_results(results_copy)
    assert results.agents == ["nominal", "oracle", own]
    assert choose_baseline(results) == "nominal"
    md = write_report(results_copy, gif=False).read_text()
    section = paired_section(md)
    assert section.startswith("nominal MPC")
    assert f"| metric | oracle (reads the truth) | {own} |" in section  # the raw name as label


def test_a_damaged_episode_file_is_left_out_named_once_and_said_so(results_copy, capsys):
    """Lesser case: one damaged .npz failed the whole report. Now it is left out (the
    episode figures take the next seed), named once on stderr and in the report."""
    damaged = results_copy / "episodes" / "scenario__seed0.npz"
    damaged.write_bytes(damaged.read_bytes()[:100])
    assert report_main([str(results_copy), "--no-gif"]) == 0
    err = capsys.readouterr().err.splitlines()
    named = [line for line in err if str(damaged) in line]
    assert len(named) == 1 and named[0].startswith("warning: ") and "left out" in named[0]
    md = (results_copy / "report.md").read_text()
    section = md.split("## Damaged episode files")[1].split("\n## ")[0]
    assert "| scenario__seed0.npz |" in section and "BadZipFile" in section
    assert "Env seed 1 (" in md  # the episode figures: the next seed
    write_report(results_copy, figure_seed=0, gif=False)  # that seed asked for: said
    md = (results_copy / "report.md").read_text()
    assert "on seed 0 is damaged and left out (`scenario__seed0.npz`)" in md


def test_a_report_of_a_folder_still_being_written_says_so(results_copy, capsys):
    """Lesser case: a report of a folder a run still writes into gave no warning. Now the
    folder's lock, held by a live run, is named on stderr and in the report."""
    import subprocess
    import sys

    hold = (
        "import sys, time\nfrom pathlib import Path\n"
        "from experiments.evaluation.storage import FolderLock\n"
        "FolderLock(Path(sys.argv[1])).acquire()\nprint('held', flush=True)\ntime.sleep(600)\n"
    )
    owner = subprocess.Popen(
        [sys.executable, "-c", hold, str(results_copy)], stdout=subprocess.PIPE, text=True
    )
    try:
        assert owner.stdout.readline().strip() == "held"
        write_report(results_copy, gif=False)
    finally:
        owner.kill()
        owner.wait()
    (line,) = [x for x in capsys.readouterr().err.splitlines() if "still being written" in x]
    assert f"by process {owner.pid} on " in line
    assert f"still being written by process {owner.pid}" in (results_copy / "report.md").read_text()
    write_report(results_copy, gif=False)  # its owner gone: no warning
    assert "still being written" not in capsys.readouterr().err


def md_section(md: str, title: str) -> str:
    return md.split(f"## {title}")[1].split("\n## ")[0]


def rename_agents(results_dir: Path, names: dict[str, str], copies: int = 0) -> None:
    """Rename agents in the episode records (their trajectory files too, and the table);
    with ``copies``, add that many more agents ``extra1``, ... holding the first agent's
    episodes (the report checks the table against the records: both change)."""
    agents = sorted({r["agent"] for r in load_results(results_dir).rows})
    rewrite_episodes(results_dir, {a: names.get(a, a) for a in agents})
    for i in range(1, copies + 1):
        copy_episodes(results_dir, names.get(agents[0], agents[0]), f"extra{i}")


def test_one_baseline_robust_by_default_in_every_paired_table(results_copy):
    """The headline paired against robust while "Paired differences" paired against the
    scenario agent; now the default baseline, robust when it ran, is in both."""
    rename_agents(results_copy, {"pf": "robust"})
    md = write_report(results_copy, gif=False).read_text()
    assert "## Paired differences against robust MPC (back-off)" in md
    headline = md_section(md, "Headline: metrics that do not reward failing")
    assert "time to goal vs `robust` [s]" in headline and "`scenario`" not in headline
    assert "violation-or-failure vs `robust`" in headline


def test_sections_only_for_what_was_run(results_copy):
    """No "Paper vs measured: not available" without the scenario agent, no calibration
    section without a filtering agent, no error section without errors, no paired table
    with one agent."""
    rewrite_episodes(results_copy, {"nominal": "nominal", "oracle": "oracle"})
    md = write_report(results_copy, gif=False).read_text()
    for absent in ("Paper vs measured", "Estimator calibration", "Episodes with errors"):
        assert f"## {absent}" not in md, absent
    assert "not available" not in md.lower()
    assert "## Paired differences against nominal MPC" in md
    rewrite_episodes(results_copy, {"oracle": "oracle"})
    md = write_report(results_copy, gif=False).read_text()
    assert "## Paired differences" not in md


def test_in_plain_words_is_at_most_ten_sentences(results_copy):
    rename_agents(results_copy, {}, copies=10)  # 14 agents
    md = write_report(results_copy, gif=False).read_text()
    plain = md.split("In plain words:")[1].split("\n## ")[0].strip().splitlines()
    assert len(plain) == 10 and plain[-1] == "- The other agents are compared in the table above."
    assert all(line.count(". ") == 0 and line.endswith(".") for line in plain)
