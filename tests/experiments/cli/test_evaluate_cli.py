"""``lfm-evaluate`` (``experiments.cli.evaluate``): help, one-line errors, the default
folder, and the report after the run."""

from __future__ import annotations

import math
import os
import subprocess
import sys
from pathlib import Path

import pytest

from experiments.cli import evaluate_main
from experiments.evaluation.run import saved_rows
from tests.experiments.evaluation.tiny_runs import write_tiny_yaml

REPO = Path(__file__).resolve().parents[3]
OWN = "tests.experiments.own_agents"


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
        (["--agents", "nominal,pf", "--baseline", "robust"], "--baseline 'robust'"),
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

    def write_report(directory, baseline=None):
        reported.append((Path(directory), baseline))
        return Path(directory) / "report.md"

    monkeypatch.setattr(experiments.report, "write_report", write_report)
    argv = ["--config", str(config), "--agents", "nominal", "--seeds", "0,1", "--out", str(out)]
    assert evaluate_main([*argv, "--quiet"]) == 0
    text = capsys.readouterr().out
    assert str(out / "episodes.csv") in text and str(out / "report.md") in text
    assert reported == [(out, None)]
    assert evaluate_main([*argv, "--quiet", "--baseline", "nominal"]) == 0  # (resumed: no run)
    assert reported[-1] == (out, "nominal")
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


def _command_line() -> list[str]:
    script = Path(sys.executable).with_name("lfm-evaluate")
    if script.is_file():
        return [str(script)]
    return [
        sys.executable,
        "-c",
        "import sys; from experiments.cli import evaluate_main; sys.exit(evaluate_main())",
    ]


def _run_cli(tmp_path: Path, agents: str) -> subprocess.CompletedProcess:
    config = tmp_path / "tiny.yaml"
    config.write_text(
        "env:\n  max_steps: 15\nagents:\n  horizon: 5\n  n_scenarios: 5\n  n_particles: 300\n"
    )
    cmd = _command_line() + [
        *("--config", str(config), "--agents", agents, "--seeds", "0:2"),
        *("--jobs", "2", "--out", str(tmp_path / "out"), "--no-report", "--quiet"),
    ]
    env = {**os.environ, "OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1"}
    env.pop("PYTHONPATH", None)  # the module must be found from the current folder
    return subprocess.run(cmd, cwd=REPO, env=env, capture_output=True, text=True, timeout=600)


def test_cli_runs_a_module_attribute_agent_from_the_repo_root(tmp_path):
    done = _run_cli(tmp_path, f"nominal,{OWN}:ProportionalAgent")
    assert done.returncode == 0, done.stdout + done.stderr
    rows = saved_rows(tmp_path / "out")
    assert [(r["agent"], r["seed"], r["error"]) for r in rows] == [
        (a, s, "") for a in ("nominal", "proportional") for s in (0, 1)
    ]
    assert rows[2]["solver_failures"] == 0 and math.isnan(rows[2]["latent_rmse"])


def test_cli_exits_2_with_one_line_naming_a_bad_agent(tmp_path):
    done = _run_cli(tmp_path, f"{OWN}:not_an_agent_factory")
    assert done.returncode == 2
    last = done.stderr.strip().splitlines()[-1]
    assert last.startswith("lfm-evaluate: error: agent ")
    assert f"{OWN}:not_an_agent_factory" in last and "no reset(seed=None) and act(obs)" in last
    assert not (tmp_path / "out").exists()


def test_a_failed_report_is_one_line_on_stderr_with_exit_2(tmp_path, capsys):
    """The report's failure was printed on stdout with exit code 1 (the code of episodes
    that raised); the command lines' errors are one line on stderr with exit code 2. The
    results stay."""
    config = write_tiny_yaml(tmp_path)
    out = tmp_path / "res"
    out.mkdir()
    (out / "figures").write_text("a file where the report's figures folder goes")
    argv = ["--config", str(config), "--agents", "nominal", "--seeds", "0", "--out", str(out)]
    assert evaluate_main([*argv, "--quiet"]) == 2
    captured = capsys.readouterr()
    assert "report" not in captured.out.replace(str(out), "").replace("results:", "")
    (line,) = [x for x in captured.err.splitlines() if "report" in x]
    assert line.startswith("lfm-evaluate: error: the report failed") and str(out) in line
    assert [r["seed"] for r in saved_rows(out)] == [0]
