"""The risk sweep (``experiments.sweep``): a sweep run into its folder, resumed, refused
when the folder holds another, its values read by the keys' types; its table, figure and
report section as they come out of a run."""

from __future__ import annotations

import base64
import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from controllers.config import ConfigError
from controllers.config.experiment import split_values
from experiments import sweep
from experiments.cli import report_main, sweep_main
from experiments.evaluation import run as evaluation
from experiments.report import sweep_summary
from experiments.report.format import fmt_estimate
from experiments.report.stats import bootstrap_ci
from experiments.report.sweep_summary import metric_key
from experiments.report.write import write_report

TINY = {
    "env": {"max_steps": 15},
    "agents": {"horizon": 5, "n_scenarios": 5, "n_particles": 300},
}
OWN = "tests.experiments.own_agents"
REPO = Path(__file__).resolve().parents[2]
QUICK = REPO / "configs" / "quick.yaml"
SEEDS = [0, 1]
SETTING = "agents.backoff=0,2"


@pytest.fixture(scope="module")
def sweep_dir(tmp_path_factory) -> Path:
    """The quick config's scenario agent with back-off 0 and 2 against pf, on 2 seeds."""
    out = tmp_path_factory.mktemp("sweep") / "sweep"
    argv = ["--config", str(QUICK), "--agent", "scenario", "--set", SETTING]
    code = sweep_main([*argv, "--seeds", "0:2", "--out", str(out), "--quiet"])
    assert code == 0
    return out


def json_rows(folder: Path, agent: str) -> dict[int, dict]:
    """The rows of an evaluation folder, read from the episode files directly."""
    rows = {}
    for path in sorted((folder / "episodes").glob(f"{agent}__seed*.json")):
        record = json.loads(path.read_text())
        rows[record["seed"]] = record
    return rows


def test_sweep_writes_every_folder_the_table_and_the_figure(sweep_dir):
    manifest = json.loads((sweep_dir / "sweep.json").read_text())
    assert manifest == {
        "agent": "scenario",
        "baseline": "pf",
        "key": "agents.backoff",
        "values": ["0", "2"],
        "seeds": SEEDS,
    }
    for folder, agent in (
        ("baseline", "pf"),
        ("agents.backoff=0", "scenario"),
        ("agents.backoff=2", "scenario"),
    ):
        rows = json_rows(sweep_dir / folder, agent)
        assert sorted(rows) == SEEDS and all(r["error"] == "" for r in rows.values())
    # Each value's folder holds its own resolved config: the swept key set, nothing else.
    cfg = evaluation.resolve_config(sweep_dir / "agents.backoff=2" / "config.yaml")
    base = evaluation.resolve_config(sweep_dir / "baseline" / "config.yaml")
    assert cfg.agents.backoff == (2.0,) and base.agents.backoff == (0.0,)
    assert cfg.agents.n_particles == base.agents.n_particles == 3000  # the quick config's
    md = (sweep_dir / "sweep.md").read_text()
    assert "| metric | PF + CE MPC (baseline) | backoff=0 | backoff=2 |" in md
    assert "track violation steps > 0.01 m [steps]" in md
    assert "track zero-violation episodes (> 0.01 m)" in md
    assert "speed violation steps > 0.05 m/s [steps]" in md
    assert "time to goal (successful episodes) [s]" in md
    assert "![" in md and "(sweep.png)" in md
    assert (sweep_dir / "sweep.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_paired_intervals_match_a_direct_computation(sweep_dir):
    """Each cell's paired difference is the bootstrap interval of value - baseline per seed,
    computed here from the episode files themselves."""
    summary = sweep_summary.load_sweep(sweep_dir)
    base = json_rows(sweep_dir / "baseline", "pf")
    header, table = sweep_summary.sweep_table(summary)
    md = (sweep_dir / "sweep.md").read_text()
    column = "track_violation_steps_over_0.01"
    checked = 0
    for v in summary.values:
        rows = json_rows(sweep_dir / f"agents.backoff={v.text}", "scenario")
        for metric in summary.metrics:
            if metric.column == "time_to_goal":
                pairs = [
                    (rows[s]["time_to_goal"], base[s]["time_to_goal"])
                    for s in SEEDS
                    if rows[s]["success"] and base[s]["success"]
                ]
            elif metric.zero_count:
                pairs = [(rows[s][metric.column] == 0, base[s][metric.column] == 0) for s in SEEDS]
            else:
                pairs = [(rows[s][metric.column], base[s][metric.column]) for s in SEEDS]
            direct = bootstrap_ci([float(a) - float(b) for a, b in pairs])
            got = v.differences[metric_key(metric)].estimate
            assert got.n == direct.n == len(pairs)
            if direct.n:
                assert (got.mean, got.low, got.high) == pytest.approx(
                    (direct.mean, direct.low, direct.high)
                )
                checked += 1
        # The table shows the same interval.
        i = next(
            k for k, m in enumerate(summary.metrics) if m.column == column and not m.zero_count
        )
        direct = bootstrap_ci([rows[s][column] - base[s][column] for s in SEEDS])
        cell = table[i + 1][header.index(f"backoff={v.text}")]
        assert cell.endswith(f"Δ {fmt_estimate(direct)}")
        assert cell in md
        mean = np.mean([rows[s][column] for s in SEEDS])
        assert v.stats[metric_key(summary.metrics[i])].mean == pytest.approx(mean)
    assert checked >= 2 * (len(summary.metrics) - 1)


def test_rerun_resumes_without_running_an_episode(sweep_dir, tmp_path, monkeypatch):
    copy = tmp_path / "sweep"
    shutil.copytree(sweep_dir, copy)
    (copy / "sweep.md").unlink()
    monkeypatch.setattr(evaluation, "_episode_task", None)  # nothing may run
    summary = sweep.run_sweep("scenario", SETTING, SEEDS, QUICK, out=copy, progress=False)
    assert [v.text for v in summary.values] == ["0", "2"]
    assert (copy / "sweep.md").read_text() == (sweep_dir / "sweep.md").read_text()
    # Fewer seeds: the table counts only those (the folders keep the others).
    fewer = sweep.run_sweep("scenario", SETTING, [1], QUICK, out=copy, progress=False)
    assert fewer.seeds == (1,) and [r["seed"] for r in fewer.values[0].rows] == [1]


def test_another_sweep_into_the_same_folder_is_refused(sweep_dir, tmp_path, monkeypatch):
    copy = tmp_path / "sweep"
    shutil.copytree(sweep_dir, copy)
    monkeypatch.setattr(evaluation, "_episode_task", None)
    with pytest.raises(evaluation.ResultsFolderError, match="agents.n_scenarios"):
        sweep.run_sweep("scenario", "agents.n_scenarios=5,10", SEEDS, QUICK, out=copy)
    with pytest.raises(evaluation.ResultsFolderError, match="n_particles"):  # another base
        sweep.run_sweep("scenario", SETTING, SEEDS, {"agents": {"n_particles": 10}}, out=copy)


def test_values_are_read_by_the_keys_own_type():
    assert split_values("0, [1,2,0] ,3") == ["0", "[1,2,0]", "3"]
    cfg = sweep.config_with(QUICK, "agents.robust.backoff", "2")
    assert cfg.agents.robust.backoff == (2.0,)  # one value for a list key: a list of one
    assert sweep.config_with(QUICK, "agents.backoff", "[1, 2, 0]").agents.backoff == (1, 2, 0)
    assert sweep.config_with(QUICK, "agents.estimator", "ukf").agents.estimator == "ukf"
    assert sweep.config_with(QUICK, "agents.n_particles", "500").agents.n_particles == 500
    assert sweep.config_with(QUICK, "agents.ess_threshold", "null").agents.ess_threshold is None
    assert sweep.config_with(QUICK, "agents.slack_penalty", "1e3").agents.slack_penalty == 1000.0
    key, texts, configs = sweep.parse_setting("agents.n_scenarios=5,10", QUICK)
    assert (key, texts) == ("agents.n_scenarios", ["5", "10"])
    assert [c.agents.n_scenarios for c in configs] == [5, 10]
    assert sweep_summary.value_folder("agents.backoff", "[1, 2, 0]") == "agents.backoff=[1,2,0]"


@pytest.mark.parametrize(
    "setting, words",
    [
        ("agents.bakoff=1,2", ["agents", "'bakoff'", "backoff"]),
        ("agents.backoff=-1,2", ["agents.backoff", "[0, 10]"]),
        ("agents.n_particles=1.5", ["agents.n_particles", "integer"]),
        ("agents.estimator=kalman", ["agents.estimator", "bootstrap"]),
        ("agents.robust.nope=1", ["agents.robust", "'nope'"]),
        ("agents.robust=1", ["agents.robust", "section"]),
        ("env.dt=0.1", ["env.dt", "agents"]),
        ("agents.backoff", ["agents.backoff", "KEY=V1,V2"]),
        ("agents.backoff=1,1", ["agents.backoff", "repeat"]),
    ],
)
def test_bad_setting_names_the_key(setting, words, tmp_path, capsys):
    with pytest.raises(ConfigError) as exc:
        sweep.parse_setting(setting, QUICK)
    for word in words:
        assert word in str(exc.value)
    # The command line exits 2 with the message, before anything is written.
    out = tmp_path / "out"
    with pytest.raises(SystemExit) as code:
        sweep_main(["--config", str(QUICK), "--set", setting, "--out", str(out), "--quiet"])
    assert code.value.code == 2
    last = capsys.readouterr().err.strip().splitlines()[-1]
    assert words[0] in last and not out.exists()


def test_pareto_figure_has_one_point_per_value_and_the_baseline(sweep_dir):
    summary = sweep_summary.load_sweep(sweep_dir)
    fig = sweep_summary.sweep_figure(summary)
    ax = fig.axes[0]
    labels = ax.get_legend_handles_labels()[1]
    assert labels == ["PF + CE MPC (baseline)", "backoff=0", "backoff=2"]
    assert len(ax.containers) == 2  # one errorbar (x and y intervals) per value
    y = next(m for m in summary.metrics if m.column == "track_violation_steps_over_0.01")
    for container, v in zip(ax.containers, summary.values, strict=True):
        point = container.lines[0].get_xydata()[0]
        dx = v.differences["time_to_goal"].estimate.mean
        dy = v.differences[metric_key(y)].estimate.mean
        assert tuple(point) == pytest.approx((dx, dy))
    assert "track violation steps > 0.01 m" in ax.get_ylabel()


def test_report_includes_the_sweep(sweep_dir, tmp_path, capsys):
    # The baseline's folder is a results folder of lfm-evaluate: report it with the sweep.
    results = tmp_path / "results"
    shutil.copytree(sweep_dir / "baseline", results)
    assert report_main([str(results), "--sweep", str(sweep_dir), "--no-gif"]) == 0
    md = (results / "report.md").read_text()
    assert "## Risk trade-off: `agents.backoff` of `scenario`" in md
    assert "| metric | PF + CE MPC (baseline) | backoff=0 | backoff=2 |" in md
    header, rows = sweep_summary.sweep_table(sweep_summary.load_sweep(sweep_dir))
    for row in rows:
        assert "| " + " | ".join(row) + " |" in md
    assert (results / "figures" / "sweep.png").is_file() and "(figures/sweep.png)" in md
    png = base64.b64encode((results / "figures" / "sweep.png").read_bytes()).decode()
    assert f"data:image/png;base64,{png}" in (results / "report.html").read_text()  # embedded
    # A results folder that holds the sweep itself needs no option.
    both = tmp_path / "both"
    shutil.copytree(sweep_dir, both)
    for name in ("config.yaml", "episodes", "episodes.csv"):
        src = sweep_dir / "baseline" / name
        (shutil.copytree if src.is_dir() else shutil.copy)(src, both / name)
    assert "## Risk trade-off" in write_report(both, gif=False).read_text()
    # Without a sweep: no section; a folder without one is a clear error.
    assert "Risk trade-off" not in write_report(results, gif=False).read_text()
    with pytest.raises(FileNotFoundError, match="sweep.json"):
        write_report(results, gif=False, sweep_dir=tmp_path)


def test_sweeps_take_registered_agents_only():
    from experiments.sweep import run_sweep

    with pytest.raises(ValueError, match=r"only registered agents here"):
        run_sweep(f"{OWN}:ProportionalAgent", "agents.backoff=0,1", [0], TINY, out="/nonexistent")
