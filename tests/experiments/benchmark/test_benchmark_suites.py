"""The benchmark's suites (``experiments.benchmark.suites``)."""

from __future__ import annotations

import math

import pytest

from experiments.benchmark import suites as benchmark_suites


def test_objective_agreement_counts_problems_within_the_tolerance() -> None:
    def rec(step: int, objective: float, success: bool = True) -> dict:
        return {"seed": 0, "step": step, "objective": objective, "success": success}

    reference = [rec(0, 100.0), rec(1, 100.0), rec(2, 100.0), rec(3, 100.0, success=False)]
    records = [rec(0, 100.005), rec(1, 90.0), rec(2, 100.0, success=False), rec(3, 50.0)]
    out = benchmark_suites.objective_agreement(records, reference)
    # within: 5e-5 above, and 10% lower (at least as good); a failed solve never is; the
    # problem the reference did not solve is not compared.
    assert (out["n_compared"], out["n_within"], out["n_within_abs"]) == (3, 2, 1)
    assert out["share_within_pct"] == pytest.approx(200.0 / 3.0)
    assert [g["step"] for g in out["gaps"]] == [0, 1, 2]
    assert math.isnan(out["gaps"][2]["rel_gap"])
