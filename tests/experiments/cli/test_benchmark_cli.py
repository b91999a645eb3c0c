"""``lfm-benchmark`` (``experiments.cli.benchmark``): --check's exit code, its one-line
errors and its seeds."""

from __future__ import annotations

import json

import pytest

from experiments.benchmark import checks as benchmark_checks
from experiments.cli import benchmark as benchmark_cli

# A threshold no run can meet: the quick run must still exit 0 (no --check) and say FAIL.
IMPOSSIBLE = "fast_median_ms=1e-9"
# Bounds every measured figure meets: with --check such a run exits 0.
LOOSE = [f"{c.key}={-1e9 if c.op == '>=' else 1e9}" for c in benchmark_checks.CHECKS]


def test_check_exits_1_when_a_check_fails_and_0_when_all_pass(tmp_path) -> None:
    """--check on a small real run: an impossible threshold fails it, loose ones pass."""
    small = ["--quick", "--solvers", "fast", "--horizons", "7", "--max-steps", "2", "--no-compiled"]
    small += ["--no-progress", "--out", str(tmp_path / "c.json")]
    assert benchmark_cli.benchmark_main([*small, "--check", "--threshold", IMPOSSIBLE]) == 1
    data = json.loads((tmp_path / "c.json").read_text())
    assert "fast_median_ms" in [c["key"] for c in data["checks"] if c["passed"] is False]
    loose = [a for kv in LOOSE for a in ("--threshold", kv)]
    assert benchmark_cli.benchmark_main([*small, "--check", *loose]) == 0
    data = json.loads((tmp_path / "c.json").read_text())
    assert not [c for c in data["checks"] if c["passed"] is False]
    assert any(c["passed"] for c in data["checks"])


@pytest.mark.parametrize(
    ("argv", "match"),
    [
        (["--threshold", "no_such_key=1"], "no_such_key"),
        (["--threshold", "pf_step_ms=fast"], "pf_step_ms"),
        (["--threshold", "pf_step_ms"], "KEY=VALUE"),
        (["--horizons", "7,0"], "horizons"),
        (["--solvers", "fast,gurobi"], "gurobi"),
    ],
)
def test_bad_options_name_the_field(argv: list[str], match: str, capsys) -> None:
    with pytest.raises(SystemExit) as exc:
        benchmark_cli.benchmark_main([*argv, "--no-progress"])
    assert exc.value.code == 2
    assert match in capsys.readouterr().err


def test_parse_seeds() -> None:
    assert benchmark_cli.parse_seeds("0:3") == [0, 1, 2]
    assert benchmark_cli.parse_seeds("5") == [5]
    assert benchmark_cli.parse_seeds("1,4,1,0:2") == [1, 4, 0]
    for bad in ("", "3:1", "-1", "a"):
        with pytest.raises(ValueError, match="seeds="):
            benchmark_cli.parse_seeds(bad)


def test_outputs_and_config_are_checked_before_the_benchmark_runs(tmp_path, capsys) -> None:
    """Issue 35, item 8: --out DIR given an existing folder ran the whole benchmark (15
    minutes) and then failed with "Is a directory"; --config took a path only."""
    folder = tmp_path / "a_folder"
    folder.mkdir()
    with pytest.raises(SystemExit) as exc:
        benchmark_cli.benchmark_main(["--out", str(folder), "--no-progress"])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert f"--out {folder}: is a folder, expected a file name" in err
    assert "wrote" not in err and not any(folder.iterdir())
    with pytest.raises(SystemExit) as exc:
        benchmark_cli.benchmark_main(["--config", "nope", "--out", str(tmp_path / "b.json")])
    assert exc.value.code == 2
    assert "presets: matlab_reference, paper, quadrotor, quick" in capsys.readouterr().err
    assert "a preset's name (" in benchmark_cli.build_parser().format_help()
