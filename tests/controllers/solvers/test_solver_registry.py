"""The solver registry (``controllers.solvers``): one record per solver, looked up by name,
the common options adapted to each, and the capabilities the config checks."""

from __future__ import annotations

import importlib

import pytest

from controllers.config import ConfigError, load_config
from controllers.solvers import (
    SOLVER_SPECS,
    SOLVERS,
    SolverSpec,
    make_solver,
    solver_spec,
)
from experiments.benchmark.problems import problem_from_config


def test_the_names_are_the_registrys_and_each_entry_point_is_a_solver_class():
    assert (
        SOLVERS
        == tuple(SOLVER_SPECS)
        == (
            "fast",
            "fast_c",
            "ipopt",
            "ipopt_multiple_shooting",
            "sqpmethod",
            "csnlp",
        )
    )
    for name, spec in SOLVER_SPECS.items():
        assert spec.name == name and spec.description
        module, _, cls = spec.entry_point.partition(":")
        solver_class = getattr(importlib.import_module(module), cls)
        assert callable(solver_class.solve) and callable(solver_class.reset)


@pytest.mark.parametrize("name", ["textbook", "", None, ["fast"]])
def test_an_unknown_name_is_one_line_listing_the_choices(name):
    with pytest.raises(ValueError) as err:
        solver_spec(name)
    message = str(err.value)
    assert "\n" not in message and f"unknown solver {name!r}" in message
    assert all(choice in message for choice in SOLVERS)
    with pytest.raises(ValueError, match="unknown solver"):
        make_solver(problem_from_config(n_scenarios=2), name)


def test_max_iter_reaches_every_solver_its_own_way():
    problem = problem_from_config(n_scenarios=2)
    assert make_solver(problem, "fast", max_iter=7).options.max_iter == 7
    ipopt = make_solver(problem, "ipopt_multiple_shooting", max_iter=7, ipopt_options={"tol": 1})
    assert ipopt.formulation == "multiple_shooting"
    assert ipopt.ipopt_options["max_iter"] == 7 and ipopt.ipopt_options["tol"] == 1
    # An explicit ipopt_options["max_iter"] wins over max_iter=.
    ipopt = make_solver(problem, "ipopt", max_iter=7, ipopt_options={"max_iter": 3})
    assert ipopt.formulation == "condensed" and ipopt.ipopt_options["max_iter"] == 3


def test_a_spec_builds_its_class_with_its_fixed_arguments():
    spec = SolverSpec(
        "ms",
        "controllers.solvers.casadi.ipopt:IpoptScenarioSolver",
        "IPOPT, multiple shooting",
        {"formulation": "multiple_shooting"},
        max_iter_option="ipopt_options",
    )
    solver = spec.build(problem_from_config(n_scenarios=2), max_iter=5)
    assert type(solver).__name__ == "IpoptScenarioSolver"
    assert solver.formulation == "multiple_shooting" and solver.ipopt_options["max_iter"] == 5


def test_the_config_checks_the_capabilities_of_the_records():
    """agents.horizon against the solver's max_horizon, agents.solver_threads against
    threaded: from the records, before any solver is built."""
    limited = [name for name, spec in SOLVER_SPECS.items() if spec.max_horizon is not None]
    threaded = [name for name, spec in SOLVER_SPECS.items() if spec.threaded]
    assert limited == threaded == ["fast", "fast_c"]
    longest = SOLVER_SPECS["fast"].max_horizon
    with pytest.raises(ConfigError, match=rf"agents.horizon={longest + 1}: must be <= {longest}"):
        load_config({"agents": {"horizon": longest + 1}})
    assert load_config({"agents": {"horizon": longest + 1, "solver": "ipopt"}})
    assert load_config({"agents": {"solver_threads": 2}}).agents.solver_threads == 2
    with pytest.raises(ConfigError, match="solver_threads=2: must be 1 with solver 'csnlp'"):
        load_config({"agents": {"solver_threads": 2, "solver": "csnlp"}})
