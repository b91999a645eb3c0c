"""Tests of the Campi-Garatti scenario count (:mod:`controllers.scenario_count`)."""

from __future__ import annotations

import math

import pytest

from controllers.scenario_count import campi_garatti_scenarios


def cg_tail(n_scenarios: int, epsilon: float, d: int) -> float:
    return sum(
        math.comb(n_scenarios, i) * epsilon**i * (1.0 - epsilon) ** (n_scenarios - i)
        for i in range(d)
    )


@pytest.mark.parametrize(("epsilon", "beta"), [(0.05, 1e-3), (0.1, 1e-6), (0.01, 0.05), (0.3, 0.5)])
def test_campi_garatti_single_decision_variable(epsilon: float, beta: float) -> None:
    expected = math.ceil(math.log(beta) / math.log(1.0 - epsilon))
    assert campi_garatti_scenarios(epsilon, beta, 1) == expected


def test_campi_garatti_known_value() -> None:
    assert campi_garatti_scenarios(0.05, 1e-3, 1) == 135


@pytest.mark.parametrize(
    ("epsilon", "beta", "d"),
    [(0.1, 1e-6, 14), (0.05, 1e-3, 56), (0.2, 0.01, 3), (0.02, 1e-9, 20), (0.5, 0.1, 2)],
)
def test_campi_garatti_is_smallest_satisfying_count(epsilon: float, beta: float, d: int) -> None:
    ns = campi_garatti_scenarios(epsilon, beta, d)
    assert ns >= d
    assert cg_tail(ns, epsilon, d) <= beta
    assert cg_tail(ns - 1, epsilon, d) > beta


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [
        ({"epsilon": 0.0}, "epsilon"),
        ({"epsilon": 1.0}, "epsilon"),
        ({"epsilon": float("nan")}, "epsilon"),
        ({"beta": 0.0}, "beta"),
        ({"beta": 1.5}, "beta"),
        ({"n_decision": 0}, "n_decision"),
        ({"n_decision": 2.5}, "n_decision"),
        ({"n_decision": True}, "n_decision"),
    ],
)
def test_campi_garatti_rejects_bad_arguments(kwargs: dict, field: str) -> None:
    args = {"epsilon": 0.05, "beta": 1e-3, "n_decision": 3, **kwargs}
    with pytest.raises(ValueError, match=field):
        campi_garatti_scenarios(**args)
