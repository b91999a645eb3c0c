"""The report and the resume trust only what they can check against the episode records.

A results folder's ``episodes.csv`` is a table rebuilt from the per-episode records
(``episodes/<agent>__seed<S>.json``); each record names its trajectory's SHA-256 and the
config the episode ran with. Here the folder of a real evaluation (4 agents x 3 seeds) is
damaged as a careless user or a full disk would: the table cut short or replaced by bytes
that are not text, two trajectories swapped, ``config.yaml`` edited after the run; and a
folder written before the records held the trajectory's hash and the config still reads.
"""

from __future__ import annotations

import json

import pytest
import yaml

from experiments.cli import report_main
from experiments.evaluation import evaluate, load_trajectory
from experiments.report.results import load_results
from experiments.report.write import write_report
from tests.experiments.evaluation.tiny_runs import assert_same_trajectory
from tests.experiments.saved_results import AGENTS, SEEDS, TINY

N_EPISODES = len(AGENTS) * len(SEEDS)


def warnings_of(err: str) -> list[str]:
    return [line for line in err.splitlines() if line.startswith("warning:")]


def test_a_truncated_table_is_rebuilt_from_the_records_with_one_warning(results_copy, capsys):
    """Cut to 2,000 bytes, episodes.csv was reported as "7 episodes of 2 agents" with 12 on
    disk, with paired statistics on one seed, exit 0. Now the table is checked against the
    records, rebuilt from them with one warning naming it, and the report has all 12."""
    table = results_copy / "episodes.csv"
    whole = table.read_text()
    table.write_bytes(whole.encode()[:2000])
    assert report_main([str(results_copy), "--no-gif"]) == 0
    (warning,) = warnings_of(capsys.readouterr().err)
    assert str(table) in warning and "rebuilt" in warning
    md = (results_copy / "report.md").read_text()
    assert f"{N_EPISODES} episodes of {len(AGENTS)} agents on {len(SEEDS)} env seeds" in md
    assert table.read_text() == whole  # rebuilt as the run wrote it
    assert len(load_results(results_copy).rows) == N_EPISODES
    assert not warnings_of(capsys.readouterr().err)  # and trusted from then on


def test_a_table_of_other_rows_or_values_is_rebuilt(results_copy, capsys):
    table = results_copy / "episodes.csv"
    lines = table.read_text().splitlines()
    header, rows = lines[0], lines[1:]
    edited = rows[0].replace(",False,", ",True,", 1) if ",False," in rows[0] else rows[0] + "0"
    table.write_text("\n".join([header, edited, *rows[1:], rows[-1]]) + "\n")  # one twice
    assert len(load_results(results_copy).rows) == N_EPISODES
    (warning,) = warnings_of(capsys.readouterr().err)
    assert "episodes.csv" in warning and "rebuilt" in warning


def test_an_undecodable_table_is_named_and_rebuilt_or_refused(results_copy, capsys):
    """A table of random bytes failed with a decode error that named no file. Now it is
    named: rebuilt from the records where there are records, refused otherwise."""
    table = results_copy / "episodes.csv"
    table.write_bytes(bytes(range(256)) * 8)
    assert len(load_results(results_copy).rows) == N_EPISODES
    (warning,) = warnings_of(capsys.readouterr().err)
    assert str(table) in warning and "rebuilt" in warning
    table.write_bytes(bytes(range(256)) * 8)
    for record in (results_copy / "episodes").glob("*.json"):
        record.unlink()
    with pytest.raises(SystemExit) as exc:
        report_main([str(results_copy), "--no-gif"])
    assert exc.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert err.startswith("lfm-report: error:") and str(table) in err, err


def test_swapped_trajectories_are_named_and_left_out_then_run_again(results_copy, capsys):
    """Seed 0's and seed 1's npz swapped went unnoticed: the figures and the calibration
    tables read another episode's arrays. Now each record names its trajectory's SHA-256;
    the report leaves both out naming them, and a resumed run runs both again."""
    folder = results_copy / "episodes"
    a, b = folder / "scenario__seed0.npz", folder / "scenario__seed1.npz"
    data_a, data_b = a.read_bytes(), b.read_bytes()
    before = {s: load_trajectory(results_copy, "scenario", s) for s in (0, 1)}
    a.write_bytes(data_b)
    b.write_bytes(data_a)
    write_report(results_copy, gif=False)
    err = capsys.readouterr().err
    named = [line for line in warnings_of(err) if "scenario__seed" in line]
    assert any(str(a) in line for line in named) and any(str(b) in line for line in named)
    assert all("SHA-256" in line for line in named)
    md = (results_copy / "report.md").read_text()
    assert "scenario__seed0.npz" in md.split("Damaged episode files")[1]
    rows = evaluate(AGENTS, SEEDS, config=TINY, out=results_copy, progress=False)
    assert all(r["error"] == "" for r in rows)
    assert "running the episode again" in capsys.readouterr().err
    for seed in (0, 1):  # run again: the same arrays (but the solve times)
        assert_same_trajectory(load_trajectory(results_copy, "scenario", seed), before[seed])


def test_an_edited_config_is_noticed_by_the_report_and_the_resume(results_copy, capsys):
    """An edited config.yaml horizon was reported as the horizon the episodes ran with. Now
    every record holds the config its episode ran with: the report names the edited fields
    and reports the episodes' config; a resume is refused naming it."""
    path = results_copy / "config.yaml"
    data = yaml.safe_load(path.read_text())
    assert data["agents"]["horizon"] == 5
    data["agents"]["horizon"] = 9
    path.write_text(yaml.safe_dump(data))
    write_report(results_copy, gif=False)
    (warning,) = [w for w in warnings_of(capsys.readouterr().err) if "config.yaml" in w]
    assert "agents.horizon" in warning and "9" in warning and "5" in warning
    md = (results_copy / "report.md").read_text()
    assert "horizon = 5" in md and "horizon = 9" not in md
    assert load_results(results_copy).agent_settings["horizon"] == 5
    edited = dict(TINY, agents={**TINY["agents"], "horizon": 9})
    for config in (TINY, edited):
        with pytest.raises(ValueError, match=r"config\.yaml.*agents\.horizon"):
            evaluate(AGENTS, SEEDS, config=config, out=results_copy, progress=False)


def strip_to_todays_records(folder) -> None:
    """The records as the previous version wrote them: no config, no trajectory hash."""
    for path in (folder / "episodes").glob("*.json"):
        record = json.loads(path.read_text())
        record.pop("config", None)
        record.pop("npz_sha256", None)
        path.write_text(json.dumps(record, indent=1) + "\n")


def test_a_folder_of_the_previous_version_still_reads_and_reports(results_copy, capsys):
    strip_to_todays_records(results_copy)
    before = load_results(results_copy)
    assert len(before.rows) == N_EPISODES
    write_report(results_copy, gif=False)
    assert not warnings_of(capsys.readouterr().err)
    rows = evaluate(AGENTS, SEEDS, config=TINY, out=results_copy, progress=False)
    assert len(rows) == N_EPISODES  # resumed: nothing to run


def test_an_edited_config_of_a_previous_version_folder_is_refused_naming_it(results_copy):
    strip_to_todays_records(results_copy)
    path = results_copy / "config.yaml"
    path.write_text(path.read_text().replace("horizon: 5", "horizon: 9"))
    with pytest.raises(ValueError, match="config.yaml is not the config its episodes ran with"):
        load_results(results_copy)
