"""Fixtures of the experiment layer's tests: a small saved evaluation, its report, and a
private copy of it."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

from experiments.evaluation import evaluate
from experiments.report.write import write_report
from tests.experiments.saved_results import AGENTS, SEEDS, TINY


@pytest.fixture(scope="session")
def results_dir(tmp_path_factory) -> Path:
    """A small results folder written by the evaluation: 4 agents x 3 seeds x 20 steps."""
    out = tmp_path_factory.mktemp("results") / "tiny"
    evaluate(AGENTS, SEEDS, config=TINY, out=out, progress=False)
    return out


@pytest.fixture(scope="session")
def report_path(results_dir) -> Path:
    return write_report(results_dir)


@pytest.fixture
def results_copy(results_dir, tmp_path) -> Path:
    """A private copy of the results folder that a test may alter."""
    dst = tmp_path / "copy"
    shutil.copytree(results_dir, dst, ignore=shutil.ignore_patterns("figures", "report.*"))
    return dst
