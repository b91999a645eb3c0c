"""``experiments.cli.COMMAND_PARSERS``: one parser per console script, as its main() builds it."""

from __future__ import annotations

from pathlib import Path

import pytest

from experiments.cli import COMMAND_PARSERS

REPO = Path(__file__).resolve().parents[3]


def test_one_parser_per_console_script():
    tomllib = pytest.importorskip("tomllib")  # Python >= 3.11
    scripts = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]["scripts"]
    assert set(COMMAND_PARSERS) == set(scripts)


@pytest.mark.parametrize("command", sorted(COMMAND_PARSERS))
def test_each_parser_is_its_command(command):
    parser = COMMAND_PARSERS[command]()
    assert parser.prog == command
    assert parser.format_help().startswith(f"usage: {command}")
