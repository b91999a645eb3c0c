"""Limits of issue 15, cases 5, 6 and 8: runaway settings, hostile YAML, one-line errors.

Each command line runs as a real subprocess; the hostile-YAML cases run in a subprocess
with a memory limit and a generous timeout, since the old code took minutes and gigabytes.
"""

from __future__ import annotations

import json
import os
import resource
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
import yaml

import controllers.config as agents_config
import lfm_env.config as env_config
from controllers.config import load_config
from experiments.evaluation.run import _error_row, evaluate, row_columns, save_episode, write_table
from experiments.report import write_report
from lfm_env.config import ConfigError, from_dict
from lfm_env.worlds.registry import load_env_config
from lfm_env.worlds.sine_track.config import SineTrackConfig

REPO = Path(__file__).resolve().parents[2]
ENV = {**os.environ, "OPENBLAS_NUM_THREADS": "1", "PYTHONPATH": str(REPO)}
TINY = {"env": {"max_steps": 6}, "agents": {"n_particles": 200, "n_scenarios": 3, "horizon": 4}}


def run_interpreter(args: list[str], timeout: float, preexec_fn=None, **kw):
    """``python *args`` from the repository in the tests' environment, output captured."""
    return subprocess.run(
        [sys.executable, *args],
        capture_output=True,
        text=True,
        timeout=timeout,
        env=ENV,
        cwd=REPO,
        preexec_fn=preexec_fn,
        **kw,
    )


def run_python(code: str, timeout: float = 60.0, memory: int | None = None, **kw):
    """Run ``code`` in a fresh interpreter (optionally under an address-space limit)."""

    def limit() -> None:
        # As in a terminal: a suite started in the background (nohup ... &) ignores SIGINT,
        # and an ignored SIGINT is inherited, so Python would not turn Ctrl-C into
        # KeyboardInterrupt in the child.
        signal.signal(signal.SIGINT, signal.SIG_DFL)
        if memory is not None:
            resource.setrlimit(resource.RLIMIT_AS, (memory, memory))

    return run_interpreter(["-c", textwrap.dedent(code)], timeout, limit, **kw)


def run_cli(module_main: str, *args: str, timeout: float = 120.0, preexec=None):
    """A command line's ``main`` in a real subprocess: (returncode, stdout, stderr)."""
    module, main = module_main.split(":")
    code = f"import sys; from {module} import {main}; sys.exit({main}(sys.argv[1:]))"
    proc = run_interpreter(["-c", code, *args], timeout, preexec)
    return proc.returncode, proc.stdout, proc.stderr


def one_line(stderr: str) -> str:
    """The one message line of stderr (argparse's usage lines before it are allowed)."""
    assert "Traceback" not in stderr
    lines = stderr.splitlines()
    if lines and lines[0].startswith("usage:"):  # parser.error: usage, then the message
        lines = lines[1:]
        while lines and lines[0].startswith(" "):
            lines = lines[1:]
    lines = [line for line in lines if line.strip()]
    assert len(lines) == 1, stderr
    return lines[0]


# --------------------------------------------------------------------------- case 6: YAML


def alias_bomb(levels: int = 9) -> str:
    """A "billion laughs" list (9 ** levels items once expanded) as the value of env.dt."""
    anchors = ["&a0 [" + ", ".join(['"lol"'] * 9) + "]"]
    for i in range(1, levels):
        anchors.append(f"&a{i} [" + ", ".join([f"*a{i - 1}"] * 9) + "]")
    return "env:\n  dt: [" + ", ".join(anchors) + "]\n"


def test_alias_bomb_as_a_value_is_refused_promptly(tmp_path):
    """Case 6: a 1.3 KB file whose env.dt expands to 9^9 items took 68 s and 3.2 GB
    (MemoryError) while the refusal repr()ed it; now a bounded one-line ConfigError."""
    path = tmp_path / "bomb.yaml"
    path.write_text(alias_bomb())
    assert path.stat().st_size < 2000
    proc = run_python(
        f"""
        from lfm_env.config import ConfigError
        from lfm_env.worlds.registry import load_env_config
        try:
            load_env_config({str(path)!r})
        except ConfigError as exc:
            print(len(str(exc)), exc)
        """,
        timeout=30.0,
        memory=1024**3,
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    length, message = proc.stdout.split(" ", 1)
    assert int(length) < 400 and "aliases" in message and str(path) in message


def test_show_of_a_shared_huge_value_is_bounded():
    """Case 6: the refusal of a dict config whose value is a huge shared structure (no
    YAML involved) shows a short repr instead of expanding it."""
    proc = run_python(
        """
        from lfm_env.config import ConfigError, from_dict
        from lfm_env.worlds.sine_track.config import SineTrackConfig
        v = ["lol"] * 9
        for _ in range(8):
            v = [v] * 9
        try:
            from_dict(SineTrackConfig, {"dt": v})
        except ConfigError as exc:
            print(len(str(exc)), str(exc)[:40])
        """,
        timeout=30.0,
        memory=1024**3,
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert int(proc.stdout.split()[0]) < 200 and "dt=" in proc.stdout


def test_deep_nesting_is_a_config_error(tmp_path):
    """Case 6: 100k nested '[' gave a RecursionError traceback (60k here: the file stays
    under the size limit, so the nesting itself is refused)."""
    path = tmp_path / "deep.yaml"
    path.write_text("env:\n  dt: " + "[" * 60_000 + "\n")
    with pytest.raises(ConfigError, match=r"deeper than \d+ levels") as exc:
        load_env_config(path)
    assert str(path) in str(exc.value)


def test_moderately_deep_nesting_is_refused_by_the_depth_limit(tmp_path):
    path = tmp_path / "deep.yaml"
    path.write_text("env:\n  dt: " + "[" * 60 + "]" * 60 + "\n")
    with pytest.raises(ConfigError, match=r"deeper than 50 levels \(line 2\)"):
        load_env_config(path)


def test_oversized_config_file_is_refused_before_parsing(tmp_path):
    """Case 6: a 32 MB list took more than 300 s; any file over the limit is refused."""
    path = tmp_path / "big.yaml"
    limit = env_config.MAX_CONFIG_BYTES
    path.write_text("# " + "x" * limit + "\nenv: {}\n")
    with pytest.raises(ConfigError, match=rf"must be <= {limit}") as exc:
        load_env_config(path)
    assert str(path) in str(exc.value)


def test_unreadable_config_is_a_config_error(tmp_path):
    path = tmp_path / "config.yaml"
    path.mkdir()
    (tmp_path / "link.yaml").symlink_to(tmp_path / "link.yaml")  # a symlink loop
    for bad in (path, tmp_path / "link.yaml"):
        with pytest.raises(ConfigError, match=str(bad)):
            load_env_config(bad)


def test_real_configs_are_within_the_limits():
    for path in sorted((REPO / "configs").glob("*.yaml")):
        load_config(path)


def test_float_hint_names_the_exponent_sign(tmp_path):
    """Case 8: PyYAML reads 1.0e6 as a string; the hint blamed a missing dot."""
    path = tmp_path / "c.yaml"
    path.write_text("env:\n  dt: 1.0e6\n")
    with pytest.raises(ConfigError, match=r"env\.dt='1\.0e6'.*signed exponent, e\.g\. 1\.0e\+6"):
        load_env_config(path)
    assert yaml.safe_load("v: 1.0e+6")["v"] == 1.0e6  # the advice works
    with pytest.raises(ConfigError, match=r"with a dot") as exc:
        from_dict(SineTrackConfig, {"dt": "fast"})
    assert "exponent" not in str(exc.value)


# --------------------------------------------------------------------------- case 5: settings


@pytest.mark.parametrize("env_id", ["lfm_env/SineTrack-v0", "lfm_env/QuadrotorGust-v1"])
def test_max_steps_has_an_upper_bound(env_id):
    """Case 5: max_steps had no upper bound."""
    with pytest.raises(ConfigError, match=r"env\.max_steps=1000000000: .*\[1, 100000\]"):
        load_env_config({"env_id": env_id, "env": {"max_steps": 10**9}})
    assert load_env_config({"env_id": env_id, "env": {"max_steps": env_config.MAX_STEPS}})


def test_particle_count_over_the_memory_budget_is_refused_up_front():
    """Case 5: n_particles 1e7 took 3.7 GB; refused when the config is read."""
    with pytest.raises(ConfigError, match=r"agents\.n_particles=10000000: .* GB.*must be <= "):
        load_config({"agents": {"n_particles": 10_000_000}})
    with pytest.raises(ConfigError, match=r"agents\.robust\.n_particles=10000000"):
        load_config({"agents": {"robust": {"n_particles": 10_000_000, "estimator": "bootstrap"}}})
    load_config({"agents": {"n_particles": 1_000_000}})  # 0.45 GB measured: allowed


def test_largest_allowed_particle_count_builds_within_budget():
    """The refusal's bound is the estimate's: the message's largest count is accepted."""
    with pytest.raises(ConfigError) as exc:
        load_config({"agents": {"n_particles": 10_000_000}})
    largest = int(str(exc.value).rsplit("<= ", 1)[1])
    assert 1_000_000 < largest < 10_000_000
    load_config({"agents": {"n_particles": largest}})


def test_scenario_problem_over_the_memory_budget_is_refused_up_front():
    with pytest.raises(ConfigError, match=r"agents\.horizon=200 with 100000 scenarios"):
        load_config({"agents": {"horizon": 200, "n_scenarios": 100_000, "solver": "ipopt"}})
    assert agents_config.MEMORY_BUDGET == 2 * 1024**3


def test_agent_built_from_settings_checks_its_filter_memory():
    """An agent built directly (not through load_config) refuses too, before its filter."""
    from controllers.agents.mpc import ScenarioMPCAgent
    from controllers.config import AgentConfig

    cfg = load_config(None)
    settings = AgentConfig(n_particles=10_000_000)
    with pytest.raises(ConfigError, match=r"agents\.n_particles"):
        ScenarioMPCAgent(cfg.make_model(), cfg.make_cost(), settings, cfg.measurement_std)


def test_render_size_is_bounded(tmp_path):
    """Case 5/8: lfm-render --size 8000x4000 allocated 5 GB then failed."""
    out = tmp_path / "x.gif"
    rc, _, err = run_cli(
        "experiments.cli:render_main",
        "--config",
        "configs/quick.yaml",
        "--size",
        "8000x4000",
        "--steps",
        "2",
        "--out",
        str(out),
    )
    assert rc == 2 and "--size 8000x4000" in one_line(err)
    assert not out.exists()
    rc, _, err = run_cli(
        "experiments.cli:render_main",
        "--config",
        "configs/quick.yaml",
        "--size",
        "4000x4000",
        "--out",
        str(out),
    )
    assert rc == 2 and "GB" in one_line(err) and "fewer --steps" in err


# --------------------------------------------------------------------------- case 8: one line


def test_evaluate_impossible_out_is_one_line_and_exit_2(tmp_path):
    """Case 8: an impossible --out (below a regular file) gave a traceback."""
    blocker = tmp_path / "file"
    blocker.write_text("x")
    rc, _, err = run_cli(
        "experiments.cli:evaluate_main",
        "--config",
        "configs/quick.yaml",
        "--agents",
        "nominal",
        "--seeds",
        "0",
        "--quiet",
        "--out",
        str(blocker / "results"),
    )
    assert rc == 2, err
    line = one_line(err)
    assert str(blocker) in line and "lfm-evaluate" in line


def test_disk_full_is_one_line_and_exit_2(tmp_path):
    """Case 8: disk full gave a traceback. RLIMIT_FSIZE makes every write beyond 2 kB fail
    with EFBIG, as a full disk fails with ENOSPC."""
    config = tmp_path / "tiny.yaml"
    config.write_text(yaml.safe_dump(TINY))

    def small_files() -> None:
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (2048, 2048))

    rc, _, err = run_cli(
        "experiments.cli:evaluate_main",
        "--config",
        str(config),
        "--agents",
        "nominal",
        "--seeds",
        "0",
        "--quiet",
        "--no-report",
        "--out",
        str(tmp_path / "out"),
        preexec=small_files,
    )
    assert rc == 2, err
    assert "File too large" in one_line(err)


def test_calibrate_out_is_checked_before_the_episodes(tmp_path):
    """Case 8: lfm-calibrate --out DIR failed with a traceback after all episodes ran."""
    folder = tmp_path / "a_folder"
    folder.mkdir()
    rc, out, err = run_cli(
        "experiments.cli:calibrate_main",
        "--config",
        "configs/quick.yaml",
        "--seeds",
        "0:3",
        "--out",
        str(folder),
        timeout=60.0,
    )
    assert rc == 2
    assert "--out" in one_line(err) and "is a folder" in err
    assert "calibration:" not in out  # no episode ran


def test_ctrl_c_during_report_is_one_line(tmp_path):
    """Case 8: Ctrl-C during lfm-report printed a traceback. A real SIGINT arrives while
    the report is being written."""
    out = tmp_path / "results"
    evaluate(["nominal", "scenario"], [0, 1], config=TINY, out=out, progress=False)
    code = f"""
        import os, signal, sys, threading
        from experiments.cli import report_main
        threading.Timer(0.5, lambda: os.kill(os.getpid(), signal.SIGINT)).start()
        sys.exit(report_main([{str(out)!r}]))
    """
    proc = run_python(code, timeout=120.0)
    assert proc.returncode == 130, proc.stderr[-2000:]
    assert one_line(proc.stderr) == "lfm-report: interrupted"


def test_report_figure_seed_skips_a_failed_zero_step_episode(tmp_path):
    """Case 8: the report's figure seed could be a failed 0-step episode (empty figures,
    no note); now the smallest seed that ran, and the report says which and why."""
    out = tmp_path / "results"
    evaluate(["scenario"], [0, 1], config=TINY, out=out, progress=False)
    columns = row_columns(load_config(TINY).make_system())
    digest = json.loads((out / "episodes" / "scenario__seed1.json").read_text())["config_hash"]
    row = _error_row("scenario", 0, "RuntimeError: the agent failed at step 0", 0.1, columns)
    save_episode(out, row, {}, "Traceback: ...", digest)  # what a failed episode writes
    write_table(out)
    report = write_report(out, gif=False).read_text()
    figures = out / "figures"
    assert (figures / "seed1_scenario_trajectory.png").is_file()
    assert not list(figures.glob("seed0_*"))
    assert "Env seed 1 (the smallest seed whose `scenario` episode ran without error" in report
    assert "seeds 0 skipped" in report
    assert np.isfinite(
        float(json.loads((out / "episodes/scenario__seed1.json").read_text())["steps"])
    )


def test_a_huge_seed_range_is_refused_at_once():
    from experiments.evaluation.episode import MAX_SEEDS, parse_seeds

    with pytest.raises(ValueError, match=f"at most {MAX_SEEDS} seeds"):
        parse_seeds("0:1000000000000")
    assert len(parse_seeds(f"0:{MAX_SEEDS}")) == MAX_SEEDS
