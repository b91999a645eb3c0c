"""Fixtures of the fast solver's tests."""

from __future__ import annotations

import pytest

from controllers.problem import ScenarioProblem
from experiments.benchmark.problems import problem_from_config


@pytest.fixture(scope="module")
def paper() -> ScenarioProblem:
    """The paper's scenario problem at the size the problems were recorded (Ns = 150)."""
    return problem_from_config(n_scenarios=150)
