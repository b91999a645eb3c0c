"""``lfm-sweep`` (``experiments.cli.sweep``): its help and its one-line errors."""

from __future__ import annotations

import pytest

from experiments.cli import sweep_main

SETTING = "agents.backoff=0,2"


def test_cli_help_and_bad_agents(tmp_path, capsys):
    with pytest.raises(SystemExit) as code:
        sweep_main(["--help"])
    assert code.value.code == 0
    text = capsys.readouterr().out
    for word in ("--set", "--baseline", "agents.robust.backoff", "sweep.png", "paired"):
        assert word in text
    for argv, word in (
        (["--agent", "robot"], "robot"),
        (["--baseline", "pff"], "pff"),
        (["--seeds", "3:1"], "3:1"),
    ):
        with pytest.raises(SystemExit) as code:
            sweep_main([*argv, "--set", SETTING, "--out", str(tmp_path / "o"), "--quiet"])
        assert code.value.code == 2
        assert word in capsys.readouterr().err.strip().splitlines()[-1]
    assert not (tmp_path / "o").exists()
