"""Evaluation over seeds (``experiments.evaluation.run.evaluate``): serial, process pool and
Dask runs agree; reruns resume; bad input is refused before any work."""

from __future__ import annotations

import json
import math
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from controllers.agents.registry import AgentSpec
from experiments.evaluation import run as evaluation
from experiments.evaluation.run import (
    ResultsFolderError,
    evaluate,
    load_trajectory,
    saved_rows,
)
from tests.experiments.evaluation.tiny_runs import (
    TINY,
    assert_same_trajectory,
    comparable,
    episode_files,
    write_tiny_yaml,
)

REPO = Path(__file__).resolve().parents[3]
#: lfm-evaluate through this interpreter (as the installed command runs it).
EVALUATE_MAIN = "import sys; from experiments.cli import evaluate_main; sys.exit(evaluate_main())"


def test_serial_processes_and_dask_give_identical_tables(tmp_path):
    distributed = pytest.importorskip("distributed")
    agents, seeds = ["nominal", "pf", "scenario", "oracle"], [0, 1]
    serial = evaluate(agents, seeds, TINY, out=tmp_path / "serial", progress=False)
    procs = evaluate(agents, seeds, TINY, out=tmp_path / "procs", jobs=2, progress=False)
    with distributed.LocalCluster(
        n_workers=2,
        threads_per_worker=1,
        processes=True,
        host="127.0.0.1",
        dashboard_address=None,
    ) as cluster:
        address = cluster.scheduler_address
        dask = evaluate(
            agents, seeds, TINY, out=tmp_path / "dask", scheduler=address, progress=False
        )

    assert all(r["error"] == "" for r in serial), [r["error"] for r in serial if r["error"]]
    assert [(r["agent"], r["seed"]) for r in serial] == sorted(
        (a, s) for a in agents for s in seeds
    )
    assert comparable(procs) == comparable(serial)
    assert comparable(dask) == comparable(serial)
    # What was saved is what was returned, and the trajectories agree too.
    for name in ("serial", "procs", "dask"):
        assert comparable(saved_rows(tmp_path / name)) == comparable(serial)
    for a in agents:
        ref = load_trajectory(tmp_path / "serial", a, 1)
        assert_same_trajectory(load_trajectory(tmp_path / "procs", a, 1), ref)
        assert_same_trajectory(load_trajectory(tmp_path / "dask", a, 1), ref)


def test_dask_workers_start_a_local_cluster(tmp_path):
    pytest.importorskip("distributed")
    serial = evaluate(["oracle"], [4], TINY, progress=False)
    dask = evaluate(["oracle"], [4], TINY, out=tmp_path, dask_workers=1, progress=False)
    assert comparable(dask) == comparable(serial)


def test_rerun_skips_finished_episodes_and_redoes_lost_ones(tmp_path, monkeypatch):
    first = evaluate(["nominal"], range(3), TINY, out=tmp_path, progress=False)
    (tmp_path / "episodes" / "nominal__seed1.json").unlink()  # an episode that was lost
    (tmp_path / "episodes" / ".nominal__seed1.npz.123.abcd.tmp").write_bytes(b"torn")

    calls = []
    task = evaluation._episode_task

    def counting(agent, config, seed, out, record, *rest):
        calls.append((agent.name, seed))
        return task(agent, config, seed, out, record, *rest)

    monkeypatch.setattr(evaluation, "_episode_task", counting)
    # (in this process: the counting function is this process's)
    second = evaluate(["nominal"], range(3), TINY, out=tmp_path, progress=False, isolate=False)
    assert calls == [("nominal", 1)]
    assert comparable(second) == comparable(first)
    assert not list(tmp_path.rglob("*.tmp"))

    calls.clear()
    again = evaluate(["nominal"], [2], TINY, out=tmp_path, progress=False, isolate=False)
    assert comparable(again) == (comparable(first[2:]))
    assert calls == []


def test_other_config_in_same_folder_is_refused(tmp_path, monkeypatch):
    evaluate(["nominal"], [0], TINY, out=tmp_path, progress=False)
    other = {"env": {"max_steps": 16}, "agents": TINY["agents"]}
    monkeypatch.setattr(evaluation, "_episode_task", None)  # nothing may run
    with pytest.raises(ResultsFolderError, match=r"env\.max_steps"):
        evaluate(["nominal"], [1], other, out=tmp_path, progress=False)


def test_failing_episode_is_recorded_and_retried(tmp_path, monkeypatch):
    real_build = AgentSpec.build

    def flaky_build(spec, config, env=None):
        agent = real_build(spec, config, env=env)
        if spec.name == "pf":
            act, n = agent.act, []

            def act_then_fail(obs):
                n.append(1)
                if len(n) == 3:
                    raise RuntimeError("solver exploded\non step 3")
                return act(obs)

            agent.act = act_then_fail
        return agent

    monkeypatch.setattr(AgentSpec, "build", flaky_build)  # where episodes build agents
    # (in this process: the flaky agent is this process's)
    rows = evaluate(["nominal", "pf"], [0, 1], TINY, out=tmp_path, progress=False, isolate=False)
    by_agent = {a: [r for r in rows if r["agent"] == a] for a in ("nominal", "pf")}
    assert all(r["error"] == "" for r in by_agent["nominal"])
    for r in by_agent["pf"]:
        assert r["error"] == "RuntimeError: solver exploded on step 3"
        assert math.isnan(r["cost"]) and math.isnan(r["steps"]) and math.isnan(r["success"])
    record = json.loads((tmp_path / "episodes" / "pf__seed0.json").read_text())
    assert "act_then_fail" in record["traceback"] and record["cost"] is None
    partial = load_trajectory(tmp_path, "pf", 0)
    assert partial["action"].shape == (2, 2) and partial["true_state"].shape == (3, 4)
    assert len(saved_rows(tmp_path)) == 4

    # Without retries the failure stays; by default a rerun retries it.
    kept = evaluate(["pf"], [0], TINY, out=tmp_path, progress=False, retry_failed=False)
    assert kept[0]["error"].startswith("RuntimeError")
    monkeypatch.setattr(AgentSpec, "build", real_build)
    retried = evaluate(["nominal", "pf"], [0, 1], TINY, out=tmp_path, progress=False)
    assert all(r["error"] == "" for r in retried)
    assert comparable([r for r in retried if r["agent"] == "nominal"]) == comparable(
        by_agent["nominal"]
    )


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"agents": ["nominal", "bogus"]}, "bogus"),
        ({"agents": []}, "at least one agent"),
        ({"seeds": []}, "empty"),
        ({"seeds": [0, -2]}, "-2"),
        ({"seeds": "4:1"}, "4:1"),
        ({"jobs": 0}, "jobs"),
        ({"jobs": 2, "dask_workers": 2}, "choose one"),
    ],
)
def test_evaluate_rejects_bad_input_before_any_work(tmp_path, monkeypatch, kwargs, match):
    monkeypatch.setattr(evaluation, "_episode_task", None)  # nothing may run
    args = {"agents": ["nominal"], "seeds": [0], **kwargs}
    with pytest.raises(ValueError, match=match):
        evaluate(config=TINY, out=tmp_path / "out", progress=False, **args)
    assert not (tmp_path / "out").exists()


def test_killed_run_resumes_to_a_complete_table(tmp_path):
    config = write_tiny_yaml(tmp_path, max_steps=30)
    out = tmp_path / "out"
    cmd = [
        sys.executable,
        "-c",
        EVALUATE_MAIN,
        *("--config", str(config), "--agents", "nominal,pf", "--seeds", "0:6"),
        *("--jobs", "1", "--out", str(out), "--no-report", "--quiet"),
    ]
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + 120
        while not episode_files(out, "json"):
            assert proc.poll() is None, "the run ended before its first episode was saved"
            assert time.monotonic() < deadline, "no episode saved within 120 s"
            time.sleep(0.02)
        proc.send_signal(signal.SIGKILL)
    finally:
        proc.kill()
        proc.wait()
    assert 1 <= len(episode_files(out, "json")) < 12, "the kill came too late to test resuming"

    done = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stdout + done.stderr
    assert str(out / "episodes.csv") in done.stdout

    import csv

    with (out / "episodes.csv").open() as fh:
        table = [(r["agent"], int(r["seed"]), r["error"]) for r in csv.DictReader(fh)]
    expected = [(a, s, "") for a in ("nominal", "pf") for s in range(6)]
    assert table == expected  # every (agent, seed) exactly once, none failed
    assert not list(out.rglob("*.tmp"))
    assert len(episode_files(out, "json")) == len(episode_files(out, "npz")) == 12
    for a, s, _ in expected:
        row = json.loads((out / "episodes" / f"{a}__seed{s}.json").read_text())
        traj = load_trajectory(out, a, s)
        assert traj["action"].shape == (row["steps"], 2)


@pytest.mark.slow
def test_quick_config_sweep_with_local_dask_cluster(tmp_path):
    """All agents over 10 seeds of the quick config on a local Dask cluster."""
    config = REPO / "configs" / "quick.yaml"
    agents = ["nominal", "pf", "scenario", "oracle"]
    rows = evaluate(agents, range(10), config, out=tmp_path, dask_workers=2, progress=False)
    assert len(rows) == 40
    assert all(r["error"] == "" for r in rows), [r["error"] for r in rows if r["error"]]
    assert comparable(saved_rows(tmp_path)) == comparable(rows)
