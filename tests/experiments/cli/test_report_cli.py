"""``lfm-report`` (``experiments.cli.report``), and the --help of ``lfm-report`` and
``lfm-render`` and their scripts."""

from __future__ import annotations

import pytest

from experiments.cli import render_main, report_main


@pytest.mark.parametrize("main", [report_main, render_main])
def test_cli_help(main, capsys):
    with pytest.raises(SystemExit) as exc:
        main(["--help"])
    assert exc.value.code == 0
    text = capsys.readouterr().out
    assert "usage:" in text and "examples:" in text
    if main is report_main:
        assert "--no-gif" in text and "--seed" in text
    else:
        assert all(opt in text for opt in ("--config", "--agent", "--seed", "--out", "--steps"))


def test_report_main_writes_report(results_copy, capsys):
    assert report_main([str(results_copy), "--seed", "1", "--no-gif"]) == 0
    assert (results_copy / "report.html").is_file()
    assert (results_copy / "figures" / "seed1_scenario_trajectory.png").is_file()
    assert not (results_copy / "figures" / "episode.gif").exists()
    assert "report:" in capsys.readouterr().out


def test_report_main_missing_folder_exits_2(tmp_path, capsys):
    with pytest.raises(SystemExit) as exc:
        report_main([str(tmp_path / "nowhere")])
    assert exc.value.code == 2
    assert "nowhere" in capsys.readouterr().err


def test_report_main_checks_its_files_before_drawing(results_copy, capsys):
    """Every command checks its outputs before it works (issue 35, item 8)."""
    (results_copy / "figures").write_text("not a folder")
    with pytest.raises(SystemExit) as exc:
        report_main([str(results_copy), "--no-gif"])
    assert exc.value.code == 2
    assert "is a file, expected the report's figures folder" in capsys.readouterr().err
    assert not (results_copy / "report.md").exists()


def test_a_report_in_a_runs_first_seconds_says_one_thing_and_exits_cleanly(tmp_path, capsys):
    """``lfm-report`` on a folder whose run has taken it but finished no episode yet warned
    that the folder is still being written, then failed (no episodes table, exit 2). Now it
    says in one line that there is nothing to report yet, and exits 0."""
    from controllers.config import load_config
    from experiments.evaluation.storage import FolderLock, _prepare_folder

    out = tmp_path / "run"
    out.mkdir()
    with FolderLock(out):  # as the run holds it, with its config written
        _prepare_folder(out, load_config("quick"))
        assert report_main([str(out), "--no-gif"]) == 0
    captured = capsys.readouterr()
    lines = captured.err.strip().splitlines()
    assert len(lines) == 1, captured.err
    assert "is being written by process" in lines[0] and "no finished episode" in lines[0]
    assert str(out) in lines[0]
    assert not (out / "report.md").exists() and captured.out == ""
