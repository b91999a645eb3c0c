"""One bad episode costs one episode: a crash, a hang or an exit of an agent is its own row.

Real agents misbehave on one env seed (:mod:`tests.experiments.crashing_agents`: a SIGSEGV in
native code, a SIGKILL, an endless loop, a call that never returns to Python, a
``SystemExit``) next to a healthy agent, in real executors (serial, a process pool, a local
Dask cluster): every other episode runs and equals the same episode run alone, the bad one
is an error row naming the agent, the seed and the signal or the limit, and every run ends.
The runs with a time limit are ``lfm-evaluate`` processes, so a run that never ends fails
its test instead of stopping the suite.
"""

from __future__ import annotations

import csv
import os
import subprocess
import sys
from pathlib import Path

import pytest

from experiments.evaluation.run import evaluate
from tests.experiments.crashing_agents import BAD_SEED
from tests.experiments.evaluation.tiny_runs import TINY, comparable, write_tiny_yaml

REPO = Path(__file__).resolve().parents[3]
LFM_EVALUATE = Path(sys.executable).with_name("lfm-evaluate")
MODULE = "tests.experiments.crashing_agents"
HEALTHY = "tests.experiments.own_agents:ProportionalAgent"
SEEDS = list(range(8))


def agent(name: str) -> str:
    return f"{MODULE}:{name}"


@pytest.fixture(scope="module")
def reference() -> dict[tuple[str, int], dict]:
    """Every episode of the healthy agent, and the bad agents' good ones, run alone."""
    names = ["SegfaultAgent", "KilledAgent", "LoopingAgent", "StuckAgent", "ExitingAgent"]
    names += ["AbortingAgent", "QuittingAgent"]
    good = [s for s in SEEDS if s != BAD_SEED]
    rows = evaluate([HEALTHY], SEEDS, TINY, progress=False)
    rows += evaluate([agent(n) for n in names], good, TINY, progress=False)
    return {(r["agent"], r["seed"]): r for r in rows}


def assert_one_bad_row(rows: list[dict], bad: str, reference: dict, *texts: str) -> None:
    """One error row, ``bad``'s on BAD_SEED naming ``texts``; every other row as run alone."""
    errors = [r for r in rows if r["error"]]
    assert [(r["agent"], r["seed"]) for r in errors] == [(bad, BAD_SEED)], [
        r["error"] for r in errors
    ]
    for text in texts:
        assert text in errors[0]["error"], errors[0]["error"]
    others = [r for r in rows if not r["error"]]
    assert len(others) == 2 * len(SEEDS) - 1
    expected = [reference[(r["agent"], r["seed"])] for r in others]
    assert comparable(others) == comparable(expected)


@pytest.mark.parametrize("name, bad, signal_name", [
    ("SegfaultAgent", "segfault", "SIGSEGV"),
    ("KilledAgent", "killed", "SIGKILL"),
])  # fmt: skip
def test_a_worker_that_dies_costs_only_its_own_episode(
    name, bad, signal_name, reference, tmp_path, capfd
) -> None:
    """Case 6: an agent that crashes its worker on one seed, 2 agents x 8 seeds, jobs=2:
    12 of 16 rows were BrokenProcessPool errors, 6 of the healthy agent's, none naming the
    crash. Now one row, naming the agent, the seed and the signal."""
    out = tmp_path / "out"
    rows = evaluate([agent(name), HEALTHY], SEEDS, TINY, out=out, jobs=2, progress=False)
    assert_one_bad_row(rows, bad, reference, f"'{bad}'", f"seed {BAD_SEED}", signal_name)
    warnings = [line for line in capfd.readouterr().err.splitlines() if "worker" in line]
    assert warnings and all(f"seed {BAD_SEED}" in line for line in warnings)
    assert all(signal_name in line for line in warnings)


@pytest.mark.parametrize("name, bad, how", [
    ("SegfaultAgent", "segfault", "killed by SIGSEGV"),
    ("AbortingAgent", "aborting", "killed by SIGABRT"),
    ("QuittingAgent", "quitting", "exited with code 3"),
])  # fmt: skip
def test_a_native_crash_in_a_serial_run_costs_only_its_own_episode(
    name, bad, how, reference, tmp_path
) -> None:
    """A serial run (no --jobs) ended at an agent's segfault, abort or os._exit on one seed
    with exit code 139, 134 or 3, nothing printed, no table, and the episodes after it never
    run, on every rerun. Now its episodes run in a child process as on a pool: the crash is
    one error row naming the agent, the seed and the signal, every other episode runs, and
    a rerun retries only that one."""
    out = tmp_path / "out"
    cmd = [str(LFM_EVALUATE), "--config", str(write_tiny_yaml(tmp_path))]
    cmd += ["--agents", f"{agent(name)},{HEALTHY}", "--seeds", f"0:{len(SEEDS)}"]
    cmd += ["--out", str(out), "--no-report", "--quiet"]
    env = {**os.environ, "OPENBLAS_NUM_THREADS": "1"}
    for attempt in range(2):
        proc = subprocess.run(cmd, cwd=REPO, env=env, capture_output=True, text=True, timeout=600)
        assert proc.returncode == 1, (proc.returncode, proc.stderr[-3000:])
        warnings = [line for line in proc.stderr.splitlines() if line.startswith("warning:")]
        assert warnings and all(f"'{bad}', seed {BAD_SEED}" in w and how in w for w in warnings)
        with open(out / "episodes.csv", newline="") as fh:
            rows = list(csv.DictReader(fh))
        assert len(rows) == 2 * len(SEEDS), attempt
        assert errors_of(rows).keys() == {(bad, BAD_SEED)}
        assert how in errors_of(rows)[(bad, BAD_SEED)]
    saved = evaluate([agent(name), HEALTHY], SEEDS, TINY, out=out, retry_failed=False)
    good = [r for r in saved if r["error"] == ""]
    assert comparable(good) == comparable([reference[(r["agent"], r["seed"])] for r in good])


def test_an_agents_system_exit_is_an_error_row(reference, tmp_path) -> None:
    """Case 8: an agent's SystemExit(5) ended the whole evaluation with exit code 5, no
    message and no rows. Now it is the episode's error row, serial and on a pool."""
    for jobs in (1, 2):
        out = tmp_path / f"jobs{jobs}"
        rows = evaluate([agent("ExitingAgent"), HEALTHY], SEEDS, TINY, out=out, jobs=jobs)
        assert_one_bad_row(rows, "exiting", reference, "SystemExit: 5")


def test_ctrl_c_stays_ctrl_c_in_the_runs_own_process_and_is_a_row_in_a_worker(tmp_path):
    """A KeyboardInterrupt in the run's own process is Ctrl-C: the run stops (the episodes
    before it are kept): a serial run in this process (``isolate=False``). Workers, a serial
    run's own child included, ignore Ctrl-C, so one raised there is the agent's: a row."""
    out = tmp_path / "serial"
    with pytest.raises(KeyboardInterrupt):
        evaluate([agent("InterruptedAgent")], SEEDS, TINY, out=out, progress=False, isolate=False)
    assert len(list((out / "episodes").glob("*.json"))) == BAD_SEED
    for jobs in (1, 2):
        rows = evaluate([agent("InterruptedAgent")], SEEDS[:5], TINY, jobs=jobs, progress=False)
        assert [r["seed"] for r in rows if r["error"]] == [BAD_SEED]


# ----------------------------------------------------------------------------- time limits


def run_evaluate(tmp_path: Path, out: Path, agents: list[str], *options: str):
    """``lfm-evaluate`` on the tiny config with a 1 s episode limit; the finished process
    (it must end within 4 minutes) and the rows of its table."""
    config = write_tiny_yaml(tmp_path)
    cmd = [str(LFM_EVALUATE), "--config", str(config), "--agents", ",".join(agents)]
    cmd += ["--seeds", f"0:{len(SEEDS)}", "--out", str(out), "--episode-timeout", "1"]
    cmd += ["--no-report", "--quiet", *options]
    env = {**os.environ, "OPENBLAS_NUM_THREADS": "1"}
    proc = subprocess.run(cmd, cwd=REPO, env=env, capture_output=True, text=True, timeout=240)
    with open(out / "episodes.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    return proc, rows


def errors_of(rows: list[dict]) -> dict[tuple[str, int], str]:
    return {(r["agent"], int(r["seed"])): r["error"] for r in rows if r["error"]}


LIMIT = "ran longer than its limit of 1 s (--episode-timeout, evaluation.episode_timeout)"


@pytest.mark.parametrize("executor", ["pool", "dask"])
def test_an_episode_past_its_limit_is_an_error_row_on_workers(executor, tmp_path) -> None:
    """Case 7: an agent whose act never returns stopped the run for ever. Now, on a pool or
    a Dask cluster, an endless loop and a call that never returns to Python (a blocked
    signal and a sleep: as in native code) each end as an error row naming the limit, and
    every other episode runs."""
    options = ["--jobs", "2"] if executor == "pool" else ["--dask-workers", "2"]
    agents = [agent("LoopingAgent"), agent("StuckAgent"), HEALTHY]
    proc, rows = run_evaluate(tmp_path, tmp_path / "out", agents, *options)
    assert proc.returncode == 1, proc.stderr[-3000:]
    assert len(rows) == 3 * len(SEEDS)
    errors = errors_of(rows)
    assert set(errors) == {("looping", BAD_SEED), ("stuck", BAD_SEED)}, errors
    assert all(LIMIT in text for text in errors.values()), errors


def test_an_episode_past_its_limit_is_an_error_row_in_a_serial_run(tmp_path) -> None:
    """Case 7, serial: an endless loop in act ends at the limit as an error row and the run
    goes on (the same process: SIGALRM)."""
    proc, rows = run_evaluate(tmp_path, tmp_path / "out", [agent("LoopingAgent"), HEALTHY])
    assert proc.returncode == 1, proc.stderr[-3000:]
    assert len(rows) == 2 * len(SEEDS)
    errors = errors_of(rows)
    assert list(errors) == [("looping", BAD_SEED)] and LIMIT in errors[("looping", BAD_SEED)]


def test_a_serial_episode_stuck_outside_python_is_stopped_and_the_run_goes_on(tmp_path):
    """Case 7, serial: an episode that never returns to Python ran in the run's own process,
    which had to end (exit 1) to stop it. Now a serial run's episodes run in a child
    process: it is stopped past its limit, the episode is an error row naming the limit,
    and every other episode runs."""
    proc, rows = run_evaluate(tmp_path, tmp_path / "out", [agent("StuckAgent"), HEALTHY])
    assert proc.returncode == 1, proc.stderr[-3000:]
    assert not [x for x in proc.stderr.splitlines() if x.startswith("error:")]
    assert len(rows) == 2 * len(SEEDS)
    errors = errors_of(rows)
    assert list(errors) == [("stuck", BAD_SEED)] and LIMIT in errors[("stuck", BAD_SEED)]
    assert "did not return and was stopped" in errors[("stuck", BAD_SEED)]


def test_an_in_process_episode_stuck_outside_python_ends_the_run_with_its_row_saved(tmp_path):
    """Case 7, in the run's own process (``isolate=False``): an episode that never returns to
    Python cannot be stopped inside the process; the run saves its error row and the table,
    says so in one line and ends (exit 1). The rerun runs the other episodes first, so two
    runs leave every row."""
    out = tmp_path / "out"
    script = (
        "import sys; from experiments.evaluation import evaluate; "
        f"evaluate([{agent('StuckAgent')!r}, {HEALTHY!r}], range({len(SEEDS)}), "
        f"{str(write_tiny_yaml(tmp_path))!r}, out={str(out)!r}, episode_timeout=1, "
        "progress=False, isolate=False)"
    )
    env = {**os.environ, "OPENBLAS_NUM_THREADS": "1"}

    def run():
        proc = subprocess.run(
            [sys.executable, "-c", script], cwd=REPO, env=env, capture_output=True, text=True,
            timeout=240,
        )  # fmt: skip
        with open(out / "episodes.csv", newline="") as fh:
            return proc, list(csv.DictReader(fh))

    proc, rows = run()
    assert proc.returncode == 1
    (line,) = [x for x in proc.stderr.splitlines() if x.startswith("error:")]
    assert f"agent 'stuck', seed {BAD_SEED}" in line and "limit of 1 s" in line
    assert "its error row is saved" in line and "rerun" in line
    assert list(errors_of(rows)) == [("stuck", BAD_SEED)]
    assert LIMIT in errors_of(rows)[("stuck", BAD_SEED)]
    assert len(rows) < 2 * len(SEEDS)  # the episodes after it did not run
    proc, rows = run()
    assert proc.returncode == 1
    assert len(rows) == 2 * len(SEEDS)
    assert list(errors_of(rows)) == [("stuck", BAD_SEED)]


# ----------------------------------------------------------------------------- the setting


def test_the_limit_comes_from_the_config_and_binds_no_folder(tmp_path) -> None:
    """``evaluation.episode_timeout`` in the config sets the limit (``episode_timeout=``
    overrides it, 0: none); it is a run setting, not part of the folder's config: neither
    its config.yaml nor its config hash change, so a folder resumes under another limit."""
    from controllers.config import ConfigError, load_config
    from experiments.evaluation.storage import config_hash

    limited = {**TINY, "evaluation": {"episode_timeout": 1}}
    assert load_config(limited).evaluation.episode_timeout == 1.0
    assert load_config(None).evaluation.episode_timeout == 600.0
    assert config_hash(load_config(limited)) == config_hash(load_config(TINY))
    assert "evaluation" not in load_config(limited).to_dict()
    out = tmp_path / "out"
    rows = evaluate([agent("LoopingAgent")], [BAD_SEED], limited, out=out, progress=False)
    assert LIMIT in rows[0]["error"]
    assert "evaluation" not in (out / "config.yaml").read_text()
    rows = evaluate([HEALTHY], [0], TINY, out=out, episode_timeout=0, progress=False)
    assert rows[0]["error"] == ""
    for bad, match in ((-1, "evaluation.episode_timeout=-1.0: must be null"), ("x", "number")):
        with pytest.raises(ConfigError, match=match):
            load_config({"evaluation": {"episode_timeout": bad}})
    with pytest.raises(ValueError, match="episode_timeout=-2: must be a number of seconds"):
        evaluate([HEALTHY], [0], TINY, episode_timeout=-2, progress=False)


@pytest.mark.parametrize("command", ["lfm-evaluate", "lfm-sweep"])
def test_a_bad_episode_timeout_option_is_one_line_exit_2(command, tmp_path, capsys) -> None:
    from experiments.cli import evaluate_main, sweep_main

    main = evaluate_main if command == "lfm-evaluate" else sweep_main
    extra = [] if command == "lfm-evaluate" else ["--set", "agents.backoff=0,1"]
    with pytest.raises(SystemExit) as exc:
        main(["--episode-timeout", "-5", "--out", str(tmp_path / "out"), *extra])
    assert exc.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert err.startswith(f"{command}: error: argument --episode-timeout")
