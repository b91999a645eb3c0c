"""The results folder's files (``experiments.evaluation.storage``): rows saved and read back,
older tables, the CSV table."""

from __future__ import annotations

import csv
import json
import os
import signal
import socket
import subprocess
import sys

import numpy as np
import pytest
import yaml

from controllers.config import load_config
from experiments.evaluation import run as evaluation
from experiments.evaluation.run import (
    DamagedEpisodeError,
    FolderLock,
    ResultsFolderError,
    config_hash,
    evaluate,
    load_trajectory,
    saved_rows,
    tolerance_columns,
    write_table,
)
from tests.experiments.evaluation.live_runs import (
    SMALL,
    assert_folder_consistent,
    quick_yaml,
    start_evaluate,
    table_rows,
    wait_for_episodes,
)
from tests.experiments.evaluation.tiny_runs import (
    RAW_GROUP_COLUMNS,
    SINE_TRACK_COLUMNS,
    TINY,
    episode_files,
)


def test_rows_of_older_tables_read_with_the_groups_they_hold(tmp_path):
    """A folder written before x_violation_steps existed reads as it was written."""
    rows = evaluate(["nominal"], [0, 1], TINY, out=tmp_path, progress=False)
    old = tmp_path / "episodes" / "nominal__seed0.json"
    record = json.loads(old.read_text())
    del record["x_violation_steps"]
    old.write_text(json.dumps(record))
    loaded = saved_rows(tmp_path)
    assert tuple(loaded[0]) == tuple(c for c in SINE_TRACK_COLUMNS if c != "x_violation_steps")
    assert tuple(loaded[1]) == SINE_TRACK_COLUMNS and loaded[1]["x_violation_steps"] == 0
    assert loaded[0]["max_x_excess"] == rows[0]["max_x_excess"]
    assert isinstance(loaded[0]["track_violation_steps"], int)
    # The table keeps the config's column order; the missing cell is written as nan.
    write_table(tmp_path)

    with (tmp_path / "episodes.csv").open() as fh:
        table = list(csv.DictReader(fh))
    assert tuple(table[0]) == SINE_TRACK_COLUMNS
    assert table[0]["x_violation_steps"] == "nan" and table[1]["x_violation_steps"] == "0"
    # Without a config.yaml, the columns are those the rows hold.
    (tmp_path / "config.yaml").unlink()
    write_table(tmp_path)
    with (tmp_path / "episodes.csv").open() as fh:
        header = next(iter(csv.reader(fh)))
    assert tuple(header) == SINE_TRACK_COLUMNS


def test_csv_holds_every_row_sorted(tmp_path):

    rows = evaluate(["pf", "nominal"], [2, 0], TINY, out=tmp_path, progress=False)
    with (tmp_path / "episodes.csv").open() as fh:
        table = list(csv.DictReader(fh))
    assert list(table[0]) == list(SINE_TRACK_COLUMNS)
    assert [(r["agent"], int(r["seed"])) for r in table] == [(r["agent"], r["seed"]) for r in rows]
    assert [(r["agent"], r["seed"]) for r in rows] == [
        ("nominal", 0),
        ("nominal", 2),
        ("pf", 0),
        ("pf", 2),
    ]
    # Floats are written exactly; NaN as "nan".
    assert float(table[0]["cost"]) == rows[0]["cost"]
    assert table[0]["latent_rmse"] == "nan"
    saved = yaml.safe_load((tmp_path / "config.yaml").read_text())
    assert saved["env"]["max_steps"] == 15 and saved["agents"]["n_particles"] == 300
    for path in episode_files(tmp_path, "json"):
        json.loads(path.read_text())  # strict JSON: NaN is written as null


def test_rows_without_tolerance_columns_read_as_written(tmp_path):
    """A folder written before the tolerance-aware columns: its rows read without them,
    and the table writes them as nan (the report counts them from the trajectories)."""

    evaluate(["nominal"], [0], TINY, out=tmp_path, progress=False)
    path = tmp_path / "episodes" / "nominal__seed0.json"
    record = json.loads(path.read_text())
    for key in [k for k in record if "_over_" in k]:
        del record[key]
    path.write_text(json.dumps(record))
    (row,) = saved_rows(tmp_path)
    assert tuple(row) == RAW_GROUP_COLUMNS
    assert isinstance(row["track_violation_steps"], int)
    write_table(tmp_path)
    with (tmp_path / "episodes.csv").open() as fh:
        (cells,) = list(csv.DictReader(fh))
    assert tuple(cells) == SINE_TRACK_COLUMNS and cells["track_violation_steps_over_0.01"] == "nan"


def test_saved_rows_hold_tolerance_counts_as_integers_equal_to_the_trajectory(tmp_path):
    (row,) = evaluate(["scenario"], [1], TINY, out=tmp_path, progress=False)
    (loaded,) = saved_rows(tmp_path)
    traj = load_trajectory(tmp_path, "scenario", 1)
    for g, t, column in tolerance_columns(load_config(TINY).make_system()):
        assert isinstance(loaded[column], int)
        assert loaded[column] == row[column] == np.sum(traj[f"{g}_excess"] > t)
    # The filtering agent says which estimator it ran; the trajectory keeps it per step.
    assert traj["estimator"].shape == (row["steps"],)
    assert set(traj["estimator"]) == {"bootstrap"}


def test_a_folder_in_use_by_a_live_run_is_refused_naming_it(tmp_path, monkeypatch):
    """Case 3: a second run into a folder another live process writes to."""
    out = tmp_path / "out"
    config = quick_yaml(tmp_path, max_steps=30)
    proc = start_evaluate(
        ["--config", str(config), "--agents", "nominal", "--seeds", "0:20", "--out", str(out)],
        tmp_path,
    )
    try:
        wait_for_episodes(out, proc, 1)
        assert (out / ".lock").read_text().split()[0] == str(proc.pid)
        monkeypatch.setattr(evaluation, "_episode_task", None)  # nothing may run
        with pytest.raises(ResultsFolderError, match=rf"in use by process {proc.pid} on "):
            evaluate(["nominal"], range(20), config, out=out, progress=False)
        _, stderr = proc.communicate(timeout=300)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    assert proc.returncode == 0, stderr  # the first run was not disturbed
    assert len(table_rows(out)) == 20
    assert_folder_consistent(out)


def test_a_stale_lock_of_a_dead_process_is_taken_over(tmp_path):
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    tmp_path.mkdir(exist_ok=True)
    (tmp_path / ".lock").write_text(f"{dead.pid} {socket.gethostname()}\n")
    rows = evaluate(["nominal"], [0], SMALL, out=tmp_path, progress=False)
    assert rows[0]["error"] == ""
    assert not (tmp_path / ".lock").exists()


def test_the_lock_refuses_a_second_owner_and_is_released(tmp_path):
    lock = FolderLock(tmp_path).acquire()
    with pytest.raises(ResultsFolderError, match=r"lock file .*\.lock"):
        FolderLock(tmp_path).acquire()
    lock.release()
    FolderLock(tmp_path).acquire().release()
    assert not (tmp_path / ".lock").exists()


def test_another_config_cannot_resume_into_a_folder_without_config_yaml(tmp_path, monkeypatch):
    """Case 3: the config is bound to every episode, not only to config.yaml."""
    evaluate(["nominal"], [0], SMALL, out=tmp_path, progress=False)
    saved = json.loads((tmp_path / "episodes" / "nominal__seed0.json").read_text())
    assert saved["config_hash"] == config_hash(evaluation.resolve_config(SMALL))
    (tmp_path / "config.yaml").unlink()
    other = {**SMALL, "env": {"max_steps": 16}}
    monkeypatch.setattr(evaluation, "_episode_task", None)  # nothing may run
    with pytest.raises(ResultsFolderError, match=r"different config.*nominal__seed0\.json"):
        evaluate(["nominal"], [1], other, out=tmp_path, progress=False)


@pytest.fixture
def counted_runs(monkeypatch):
    calls: list[tuple[str, int]] = []
    task = evaluation._episode_task

    def counting(agent, config, seed, *args):
        calls.append((agent.name, seed))
        return task(agent, config, seed, *args)

    monkeypatch.setattr(evaluation, "_episode_task", counting)
    return calls


def test_damaged_episode_files_are_named_and_run_again(tmp_path, counted_runs, capsys):
    """Case 4: a truncated npz, a json of another seed, a garbage json."""
    first = evaluate(["nominal"], range(4), SMALL, out=tmp_path, progress=False)
    episodes = tmp_path / "episodes"
    npz = episodes / "nominal__seed1.npz"
    npz.write_bytes(npz.read_bytes()[: npz.stat().st_size // 2])  # truncated
    wrong = json.loads((episodes / "nominal__seed0.json").read_text())
    (episodes / "nominal__seed2.json").write_text(json.dumps(wrong))  # holds seed 0
    (episodes / "nominal__seed3.json").write_text("{garbage")
    with pytest.raises(DamagedEpisodeError, match=r"nominal__seed1\.npz"):
        load_trajectory(tmp_path, "nominal", 1)
    capsys.readouterr()
    counted_runs.clear()

    # (in this process: counted_runs counts this process's episodes)
    second = evaluate(["nominal"], range(4), SMALL, out=tmp_path, progress=False, isolate=False)
    err = capsys.readouterr().err
    assert sorted(counted_runs) == [("nominal", 1), ("nominal", 2), ("nominal", 3)]
    for name in ("nominal__seed1.npz", "nominal__seed2.json", "nominal__seed3.json"):
        assert name in err
    key = [c for c in first[0] if c not in evaluation.TIMING_COLUMNS]

    def values(rows):  # (NaN equal to NaN: rows come from a child process and from disk)
        return [[repr(r[c]) for c in key] for r in rows]

    assert values(second) == values(first)
    assert len(load_trajectory(tmp_path, "nominal", 1)["reward"]) == first[1]["steps"]
    assert_folder_consistent(tmp_path)


def test_each_damaged_file_is_named_once_per_run(tmp_path, capsys):
    """Lesser case: every damaged-file warning printed twice (the folder is read before and
    after its lock is taken). Now once per run."""
    evaluate(["nominal"], range(3), SMALL, out=tmp_path, progress=False)
    episodes = tmp_path / "episodes"
    npz = episodes / "nominal__seed1.npz"
    npz.write_bytes(npz.read_bytes()[:100])
    (episodes / "nominal__seed2.json").write_text("{garbage")
    capsys.readouterr()
    evaluate(["nominal"], range(3), SMALL, out=tmp_path, progress=False)
    err = capsys.readouterr().err
    for name in ("nominal__seed1.npz", "nominal__seed2.json"):
        assert err.count(name) == 1, err


def test_a_copied_or_garbage_json_is_named_and_not_counted(tmp_path, capsys):
    """Case 4: a copy of an episode json counted once; garbage named, not dropped silently."""
    evaluate(["nominal"], range(3), SMALL, out=tmp_path, progress=False)
    episodes = tmp_path / "episodes"
    copy = episodes / "nominal__seed1 (copy).json"
    copy.write_bytes((episodes / "nominal__seed1.json").read_bytes())
    junk = episodes / "notes.json"
    junk.write_text("[1, 2")
    capsys.readouterr()
    write_table(tmp_path)
    err = capsys.readouterr().err
    assert [(r["agent"], r["seed"]) for r in table_rows(tmp_path)] == [
        ("nominal", "0"),
        ("nominal", "1"),
        ("nominal", "2"),
    ]
    assert copy.name in err and junk.name in err
    assert len(saved_rows(tmp_path)) == 3


def test_an_episode_saved_before_the_rename_reads_its_force_as_latent_force(tmp_path):
    from experiments.evaluation.storage import episode_stem, load_trajectory

    folder = tmp_path / "episodes"
    folder.mkdir()
    np.savez(folder / f"{episode_stem('pf', 3)}.npz", disturbance=np.arange(4.0))
    arrays = load_trajectory(tmp_path, "pf", 3)
    assert "disturbance" not in arrays
    np.testing.assert_array_equal(arrays["latent_force"], np.arange(4.0))
