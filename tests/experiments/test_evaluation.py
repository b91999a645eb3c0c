"""Tests of the evaluation library (``experiments.evaluation.run``) and its command line."""

from __future__ import annotations

import json
import math
import signal
import subprocess
import sys
import time
import types
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import yaml

from controllers.config import load_config
from experiments.cli import evaluate_main
from experiments.evaluation import episode
from experiments.evaluation import run as evaluation
from experiments.evaluation.run import (
    HEAD_COLUMNS,
    TAIL_COLUMNS,
    TIMING_COLUMNS,
    ResultsFolderError,
    agent_seed,
    evaluate,
    group_columns,
    load_trajectory,
    parse_seeds,
    row_columns,
    run_episode,
    saved_rows,
    tolerance_column,
    tolerance_columns,
    violation_counts,
    write_table,
)
from lfm_env import gp
from lfm_env.env import LatentForceEnv
from lfm_env.model import LatentForceModel
from lfm_env.system import ControlSystem, QuadraticCost, xp

REPO = Path(__file__).resolve().parents[2]
# The quick world with short episodes and small agents: about 0.3 s per episode.
TINY = {
    "env": {"max_steps": 15},
    "agents": {"horizon": 5, "n_scenarios": 5, "n_particles": 300},
}
TIMING_ARRAYS = ("solve_time",)
#: The sine track's row: its constraint groups (track, x, speed), each with its raw
#: violation steps and largest excess, then the steps beyond each of its tolerances
#: (1 and 5 cm for track and x, 5 cm/s for the speed).
SINE_TRACK_COLUMNS = (
    *("agent", "seed", "success", "steps", "time_to_goal", "cost"),
    *("track_violation_steps", "max_track_excess"),
    *("track_violation_steps_over_0.01", "track_violation_steps_over_0.05"),
    *("x_violation_steps", "max_x_excess"),
    *("x_violation_steps_over_0.01", "x_violation_steps_over_0.05"),
    *("speed_violation_steps", "max_speed_excess", "speed_violation_steps_over_0.05"),
    *("failure", "latent_rmse", "latent_coverage"),
    *("solve_time_median", "solve_time_p95", "solve_time_max", "solver_failures"),
    *("fallback_steps", "filter_resets", "slack_total", "wall_time", "error"),
)
#: The columns of the group names alone (no system, so no tolerances).
RAW_GROUP_COLUMNS = tuple(c for c in SINE_TRACK_COLUMNS if "_over_" not in c)


def comparable(rows: list[dict]) -> list[dict]:
    """Rows without timing columns, NaN replaced so that equal rows compare equal."""
    return [
        {
            k: ("NaN" if isinstance(v, float) and math.isnan(v) else v)
            for k, v in r.items()
            if k not in TIMING_COLUMNS
        }
        for r in rows
    ]


def assert_same_trajectory(a: dict, b: dict) -> None:
    assert a.keys() == b.keys()
    for k in a:
        if k not in TIMING_ARRAYS:
            np.testing.assert_array_equal(a[k], b[k], err_msg=k)


def write_tiny_yaml(tmp_path: Path, max_steps: int = 15) -> Path:
    cfg = {"env": {**TINY["env"], "max_steps": max_steps}, "agents": TINY["agents"]}
    path = tmp_path / "tiny.yaml"
    path.write_text(yaml.safe_dump(cfg))
    return path


def episode_files(out: Path, suffix: str) -> list[Path]:
    return sorted((out / "episodes").glob(f"*.{suffix}"))


# ----------------------------------------------------------------------------- seeds


@pytest.mark.parametrize(
    "text, seeds",
    [
        ("0:20", list(range(20))),
        ("3", [3]),
        ("1,5,9", [1, 5, 9]),
        ("0:10,20:25", [*range(10), *range(20, 25)]),
        (" 2 : 4 , 7 ", [2, 3, 7]),
        ("1,1,0:2", [1, 0]),
    ],
)
def test_parse_seeds(text, seeds):
    assert parse_seeds(text) == seeds


@pytest.mark.parametrize("text", ["5:2", "3:3", "-1", "0:-3", "a", "", "1,,2", "1.5", "0:5:1"])
def test_parse_seeds_rejects_bad_text_naming_it(text):
    with pytest.raises(ValueError) as exc:
        parse_seeds(text)
    assert repr(text) in str(exc.value)


def test_agent_seed_is_stable_and_distinct():
    # A fixed value: the derivation must not depend on the process (hash randomisation).
    assert agent_seed(0, "pf") == 11201204833369463469
    seeds = {agent_seed(s, a) for s in range(3) for a in ("nominal", "pf", "scenario", "oracle")}
    assert len(seeds) == 12


# ----------------------------------------------------------------------------- one episode


# ----------------------------------------------------------------------------- columns


def test_row_columns_follow_the_systems_constraint_groups():
    system = load_config(TINY).make_system()
    assert row_columns(system) == SINE_TRACK_COLUMNS
    assert row_columns(["track", "x", "speed"]) == RAW_GROUP_COLUMNS
    assert group_columns(system) == SINE_TRACK_COLUMNS[6:17]
    assert row_columns(corridor_system()) == (
        *HEAD_COLUMNS,
        *("corridor_violation_steps", "max_corridor_excess"),
        *("corridor_violation_steps_over_0.01", "corridor_violation_steps_over_0.1"),
        *("speed_violation_steps", "max_speed_excess"),
        *TAIL_COLUMNS,
    )
    assert tolerance_columns(system) == (
        ("track", 0.01, "track_violation_steps_over_0.01"),
        ("track", 0.05, "track_violation_steps_over_0.05"),
        ("x", 0.01, "x_violation_steps_over_0.01"),
        ("x", 0.05, "x_violation_steps_over_0.05"),
        ("speed", 0.05, "speed_violation_steps_over_0.05"),
    )
    assert tolerance_column("track", 0.010) == "track_violation_steps_over_0.01"
    assert row_columns(()) == HEAD_COLUMNS + TAIL_COLUMNS
    with pytest.raises(ValueError, match="constraint-group names"):
        row_columns("track")


def corridor_system() -> ControlSystem:
    """A 1-D double integrator between a floor and a ceiling [m], with speed bounds [m/s]."""

    def rhs(x, u, w):
        _, v = xp.unstack(x)
        (a,) = xp.unstack(u)
        (force,) = xp.unstack(w)
        return xp.stack([v, a + force])

    def constraints(x):
        p, v = xp.unstack(x)
        return xp.stack([-0.2 - p, p - 0.2, v - 1.0, -1.0 - v])

    return ControlSystem(
        name="corridor_1d",
        state_names=("p [m]", "v [m/s]"),
        input_names=("a [m/s^2]",),
        rhs=rhs,
        input_lower=[-1.0],
        input_upper=[1.0],
        constraints=constraints,
        constraint_names=("floor [m]", "ceiling [m]", "v_max [m/s]", "v_min [m/s]"),
        constraint_groups={"corridor": (0, 1), "speed": (2, 3)},
        violation_tolerances={"corridor": (0.01, 0.1)},  # none for the speed
    )


def test_recorder_and_metrics_of_any_system_come_from_its_groups():
    """An episode of a system the evaluation knows nothing about, driven through the
    generic env: the group columns are its own and agree with the env's info."""
    system = corridor_system()
    model = LatentForceModel(system, gp.matern(1.5, 0.5, 1.0), dt=0.1, process_noise_std=[0, 0])
    env = LatentForceEnv(
        model, QuadraticCost(Q=[1, 0], R=[1]), [0.0, 0.5], [0.01, 0.01], max_steps=12
    )
    env = gym.wrappers.TimeLimit(env, env.max_steps)  # a built env never truncates itself
    config = types.SimpleNamespace(
        make_system=lambda: system, agents=types.SimpleNamespace(horizon=3)
    )
    rec = episode._EpisodeRecorder(config)
    obs, info = env.reset(seed=0)
    rec.start(obs, info)
    infos, done = [], False
    while not done:  # push up at full throttle: through the ceiling, beyond the speed bound
        agent_info = {"estimate": obs, "estimate_std": np.zeros(2), "success": True}
        obs, reward, terminated, truncated, info = env.step([1.0])
        rec.step(agent_info, obs, reward, info)
        infos.append(info)
        done = terminated or truncated
    arrays = rec.arrays()
    row = episode._episode_metrics(rec, arrays)
    assert list(row)[4:10] == list(row_columns(system))[6:12]
    corridor = np.array([i["corridor_excess"] for i in infos])
    speed = np.array([i["speed_excess"] for i in infos])
    np.testing.assert_array_equal(arrays["corridor_excess"], corridor)
    np.testing.assert_array_equal(arrays["speed_excess"], speed)
    assert 0 < row["corridor_violation_steps"] == np.sum(corridor > 0) < len(infos)
    # The tolerance-aware counts drop the crossings up to each tolerance, here some.
    over = row["corridor_violation_steps_over_0.1"]
    assert over == np.sum(corridor > 0.1) < row["corridor_violation_steps"]
    assert row["corridor_violation_steps_over_0.01"] == np.sum(corridor > 0.01) >= over
    assert 0 < row["speed_violation_steps"] == np.sum(speed > 0) < len(infos)
    assert row["max_corridor_excess"] == corridor.max() > 0.0
    assert row["max_speed_excess"] == speed.max()
    assert "track_excess" not in arrays and math.isnan(row["latent_rmse"])
    # A failed episode of this system gets the same columns, with NaN metrics.
    failed = episode._error_row("nominal", 0, "boom", 1.0, row_columns(system))
    assert tuple(failed) == row_columns(system) and math.isnan(failed["max_corridor_excess"])


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
    import csv

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


# ----------------------------------------------------------------------------- one episode


def test_run_episode_row_trajectory_and_time_alignment():
    row, traj = run_episode("pf", TINY, seed=3)
    assert tuple(row) == SINE_TRACK_COLUMNS
    assert row["agent"] == "pf" and row["seed"] == 3 and row["error"] == ""
    assert isinstance(row["success"], bool) and isinstance(row["failure"], bool)
    for c in ("steps", "track_violation_steps", "x_violation_steps", "speed_violation_steps"):
        assert isinstance(row[c], int)
    for c in ("cost", "max_track_excess", "latent_rmse", "latent_coverage", "wall_time"):
        assert isinstance(row[c], float)

    T = row["steps"]
    assert 1 <= T <= TINY["env"]["max_steps"]
    shapes = {
        "true_state": (T + 1, 4),
        "obs": (T + 1, 4),
        "action": (T, 2),
        "disturbance": (T,),
        "estimate": (T, 7),
        "estimate_std": (T, 7),
        "latent_force_est": (T,),
        "latent_force_std": (T,),
        "predicted": (T, TINY["agents"]["horizon"] + 1, 4),
        "solve_time": (T,),
        "slack": (T,),
        "solver_success": (T,),
        "reward": (T,),
    }
    for k, shape in shapes.items():
        assert traj[k].shape == shape, k
    assert traj["solver_success"].dtype == bool

    # The row's metrics are those of the trajectory.
    assert row["cost"] == pytest.approx(-traj["reward"].sum())
    err = traj["latent_force_est"] - traj["disturbance"]
    assert row["latent_rmse"] == pytest.approx(np.sqrt(np.mean(err**2)))
    assert row["slack_total"] == pytest.approx(traj["slack"].sum())
    for g in ("track", "x", "speed"):
        assert traj[f"{g}_excess"].shape == (T,)
        assert row[f"{g}_violation_steps"] == np.sum(traj[f"{g}_excess"] > 0)
        assert row[f"max_{g}_excess"] == traj[f"{g}_excess"].max()

    # Alignment with the env: obs[0] measures true_state[0], and disturbance[0] is the
    # force that the env announces at reset as acting in the first step.
    env = gym.make("lfm_env/SineTrack-v0", config=TINY)
    obs0, info0 = env.reset(seed=3)
    np.testing.assert_array_equal(traj["obs"][0], obs0)
    np.testing.assert_array_equal(traj["true_state"][0], info0["true_state"])
    assert traj["disturbance"][0] == info0["disturbance"]
    # ...and the first action was computed from obs[0] alone: replaying it reproduces step 1.
    _, _, _, _, info1 = env.step(traj["action"][0])
    np.testing.assert_array_equal(traj["true_state"][1], info1["true_state"])
    env.close()


def test_paired_design_and_determinism():
    nominal, traj_n = run_episode("nominal", TINY, seed=5)
    pf, traj_pf = run_episode("pf", TINY, seed=5)
    # Same env seed: the hidden force does not depend on the agent.
    n = min(nominal["steps"], pf["steps"])
    np.testing.assert_array_equal(traj_n["disturbance"][:n], traj_pf["disturbance"][:n])
    np.testing.assert_array_equal(traj_n["obs"][0], traj_pf["obs"][0])
    # Filter metrics exist only for filter agents.
    assert math.isnan(nominal["latent_rmse"]) and math.isnan(nominal["latent_coverage"])
    assert np.isnan(traj_n["latent_force_est"]).all()
    assert set(traj_n["estimator"]) == {""}  # no estimator to name
    assert 0.0 <= pf["latent_coverage"] <= 1.0

    again, traj_again = run_episode("pf", TINY, seed=5)
    assert comparable([again]) == comparable([pf])
    assert_same_trajectory(traj_again, traj_pf)

    _, traj_other = run_episode("nominal", TINY, seed=6)
    assert traj_other["disturbance"][0] != traj_n["disturbance"][0]


def test_run_episode_rejects_unknown_agent_and_negative_seed():
    with pytest.raises(ValueError, match="unknown agent"):
        run_episode("random", TINY, 0)
    with pytest.raises(ValueError, match="-1"):
        run_episode("nominal", TINY, -1)


# ----------------------------------------------------------------------------- evaluate


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


def test_csv_holds_every_row_sorted(tmp_path):
    import csv

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


def test_rerun_skips_finished_episodes_and_redoes_lost_ones(tmp_path, monkeypatch):
    first = evaluate(["nominal"], range(3), TINY, out=tmp_path, progress=False)
    (tmp_path / "episodes" / "nominal__seed1.json").unlink()  # an episode that was lost
    (tmp_path / "episodes" / ".nominal__seed1.npz.123.abcd.tmp").write_bytes(b"torn")

    calls = []
    task = evaluation._episode_task

    def counting(agent_name, config, seed, out, record, digest=""):
        calls.append((agent_name, seed))
        return task(agent_name, config, seed, out, record, digest)

    monkeypatch.setattr(evaluation, "_episode_task", counting)
    second = evaluate(["nominal"], range(3), TINY, out=tmp_path, progress=False)
    assert calls == [("nominal", 1)]
    assert comparable(second) == comparable(first)
    assert not list(tmp_path.rglob("*.tmp"))

    calls.clear()
    assert comparable(evaluate(["nominal"], [2], TINY, out=tmp_path, progress=False)) == (
        comparable(first[2:])
    )
    assert calls == []


def test_other_config_in_same_folder_is_refused(tmp_path, monkeypatch):
    evaluate(["nominal"], [0], TINY, out=tmp_path, progress=False)
    other = {"env": {"max_steps": 16}, "agents": TINY["agents"]}
    monkeypatch.setattr(evaluation, "_episode_task", None)  # nothing may run
    with pytest.raises(ResultsFolderError, match=r"env\.max_steps"):
        evaluate(["nominal"], [1], other, out=tmp_path, progress=False)


def test_failing_episode_is_recorded_and_retried(tmp_path, monkeypatch):
    real_make_agent = episode.make_agent

    def make_flaky_agent(name, config=None, env=None):
        agent = real_make_agent(name, config, env=env)
        if name == "pf":
            act, n = agent.act, []

            def act_then_fail(obs):
                n.append(1)
                if len(n) == 3:
                    raise RuntimeError("solver exploded\non step 3")
                return act(obs)

            agent.act = act_then_fail
        return agent

    monkeypatch.setattr(episode, "make_agent", make_flaky_agent)  # where episodes build agents
    rows = evaluate(["nominal", "pf"], [0, 1], TINY, out=tmp_path, progress=False)
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
    monkeypatch.setattr(episode, "make_agent", real_make_agent)
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


# ----------------------------------------------------------------------------- interruption


def test_killed_run_resumes_to_a_complete_table(tmp_path):
    config = write_tiny_yaml(tmp_path, max_steps=30)
    out = tmp_path / "out"
    cmd = [
        sys.executable,
        str(REPO / "scripts" / "evaluate.py"),
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


# ----------------------------------------------------------------------------- command line


def run_cli(argv, capsys):
    with pytest.raises(SystemExit) as exc:
        evaluate_main(argv)
    captured = capsys.readouterr()
    return exc.value.code, captured.out + captured.err


def test_cli_help(capsys):
    code, text = run_cli(["--help"], capsys)
    assert code == 0
    for word in ("--seeds", "--dask-workers", "examples:", "end exclusive", "[s]", "oracle"):
        assert word in text


@pytest.mark.parametrize(
    "argv, message",
    [
        (["--agents", "nominal,robot"], "robot"),
        (["--seeds", "9:3"], "9:3"),
        (["--seeds", "x"], "'x'"),
        (["--jobs", "0"], "--jobs"),
        (["--config", "no/such.yaml"], "no/such.yaml"),
        (["--scheduler", "tcp://127.0.0.1:1", "--dask-workers", "2"], "exclude"),
    ],
)
def test_cli_bad_arguments_exit_2(tmp_path, capsys, argv, message):
    code, text = run_cli([*argv, "--out", str(tmp_path / "out")], capsys)
    assert code == 2
    assert message in text.strip().splitlines()[-1]
    assert not (tmp_path / "out").exists()


def test_cli_unreachable_scheduler_exits_2_naming_it(tmp_path, capsys):
    config = write_tiny_yaml(tmp_path)
    argv = ["--config", str(config), "--scheduler", "tcp://127.0.0.1:1", "--out", str(tmp_path)]
    code, text = run_cli(argv, capsys)
    assert code == 2
    assert "tcp://127.0.0.1:1" in text.strip().splitlines()[-1]


def test_cli_runs_and_calls_the_report(tmp_path, capsys, monkeypatch):
    config = write_tiny_yaml(tmp_path)
    out = tmp_path / "res"
    reported = []
    import experiments.report

    def write_report(directory):
        reported.append(Path(directory))
        return Path(directory) / "report.md"

    monkeypatch.setattr(experiments.report, "write_report", write_report)
    argv = ["--config", str(config), "--agents", "nominal", "--seeds", "0,1", "--out", str(out)]
    assert evaluate_main([*argv, "--quiet"]) == 0
    text = capsys.readouterr().out
    assert str(out / "episodes.csv") in text and str(out / "report.md") in text
    assert reported == [out]
    assert [(r["agent"], r["seed"]) for r in saved_rows(out)] == [("nominal", 0), ("nominal", 1)]

    # Without the report module the run still succeeds, saying why there is no report.
    monkeypatch.setitem(sys.modules, "experiments.report", None)
    assert evaluate_main(argv) == 0
    assert "report: skipped" in capsys.readouterr().out


def test_cli_default_out_is_named_after_the_config(tmp_path, capsys, monkeypatch):
    config = write_tiny_yaml(tmp_path)
    monkeypatch.chdir(tmp_path)
    argv = ["--config", str(config), "--agents", "nominal", "--seeds", "0"]
    assert evaluate_main([*argv, "--quiet", "--no-report"]) == 0
    assert (tmp_path / "results" / "tiny" / "episodes.csv").is_file()


# ----------------------------------------------------------------------------- slow


@pytest.mark.slow
def test_quick_config_sweep_with_local_dask_cluster(tmp_path):
    """All agents over 10 seeds of the quick config on a local Dask cluster."""
    config = REPO / "configs" / "quick.yaml"
    agents = ["nominal", "pf", "scenario", "oracle"]
    rows = evaluate(agents, range(10), config, out=tmp_path, dask_workers=2, progress=False)
    assert len(rows) == 40
    assert all(r["error"] == "" for r in rows), [r["error"] for r in rows if r["error"]]
    assert comparable(saved_rows(tmp_path)) == comparable(rows)


# ----------------------------------------------------------------------------- tolerances


def test_violation_counts_of_a_made_up_trajectory():
    """Steps count beyond a tolerance only when the excess is strictly above it."""
    system = corridor_system()
    trajectory = {
        "corridor_excess": np.array([0.0, 0.004, 0.01, 0.02, 0.1, 0.3, 0.0]),
        "speed_excess": np.array([0.0, 0.0, 0.5, 0.0, 0.0, 0.0, 0.0]),
    }
    assert violation_counts(trajectory, system) == {
        "corridor_violation_steps": 5,
        "speed_violation_steps": 1,
        "corridor_violation_steps_over_0.01": 3,  # 0.01 itself is not beyond 0.01
        "corridor_violation_steps_over_0.1": 1,
    }
    # A group the trajectory does not hold is left out, its tolerances too.
    assert violation_counts({"speed_excess": np.zeros(3)}, system) == {"speed_violation_steps": 0}


def test_rows_without_tolerance_columns_read_as_written(tmp_path):
    """A folder written before the tolerance-aware columns: its rows read without them,
    and the table writes them as nan (the report counts them from the trajectories)."""
    import csv

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
