"""The QP without slacks on DAQP straight from the caller's rows
(controllers.solvers.fast.qp.hard_qp): the same QP as through the row slots of SlotQP, so the
same step bit for bit."""

from __future__ import annotations

import sys

import numpy as np
import pytest

from controllers.solvers.fast.qp.hard_qp import DaqpHardQP
from controllers.solvers.fast.qp.slot_qp import SlotQP
from controllers.solvers.fast.solver import FastScenarioSolver
from experiments.benchmark.problems import problem_from_config

pytest.importorskip("daqp")

NU, NS = 6, 3  # inputs, shared rows


def _random_qp(rng: np.random.Generator, rows: int, feasible: bool = True) -> dict:
    """A strictly convex QP with ``NS`` shared rows and ``rows`` scenario rows, met at d = 0
    with some margin unless ``feasible`` is False."""
    M = rng.normal(size=(NU, NU))
    b = -rng.uniform(0.1, 1.0, rows)  # rows a d <= -g: g < 0, so d = 0 is feasible
    if not feasible:
        b[0] = 50.0  # a_0 d <= -50 with a_0 = e_0 and |d| <= 1: impossible
    a_pos = rng.normal(size=(rows, NU))
    if not feasible:
        a_pos[0] = np.eye(NU)[0]
    return {
        "H": M @ M.T + 0.5 * np.eye(NU),
        "grad": rng.normal(size=NU) * 3.0,
        "lo": np.full(NU, -1.0),
        "hi": np.full(NU, 1.0),
        "a_shared": rng.normal(size=(NS, NU)),
        "g_shared": -rng.uniform(0.1, 1.0, NS),
        "a_pos": a_pos,
        "g_pos": b,
    }


def _load(qp, d: dict) -> np.ndarray:
    qp.set_problem(d["H"], d["grad"], d["lo"], d["hi"], d["a_shared"], d["g_shared"])
    k = d["a_pos"].shape[0]
    row, col = qp.assign(np.arange(k) * 7 + 3, np.arange(k) // 2)
    qp.set_position_rows(row, col, d["a_pos"], d["g_pos"])
    return row


def _slot(rows: int) -> SlotQP:
    return SlotQP(NU, NS, rows, 0, "daqp", slack_penalty=1e4, slack_reg=1e-8, elastic=False)


@pytest.mark.parametrize("seed", range(12))
def test_the_same_step_and_multipliers_as_through_the_row_slots(seed: int) -> None:
    rng = np.random.default_rng(seed)
    d = _random_qp(rng, rows=int(rng.integers(1, 12)))
    if seed % 3 == 0:
        d["g_shared"][1] = -np.inf  # a shared row without a bound: left out by both
    slot, hard = _slot(16), DaqpHardQP(NU, NS)
    row_s, row_h = _load(slot, d), _load(hard, d)
    z_s, lam_s, ok_s = slot.solve()
    z_h, lam_h, ok_h = hard.solve()
    assert ok_s and ok_h
    np.testing.assert_array_equal(z_h, z_s)
    np.testing.assert_array_equal(lam_h[:NS], lam_s[:NS])
    np.testing.assert_array_equal(lam_h[row_h], lam_s[row_s])
    assert lam_h.size == NS + d["a_pos"].shape[0]
    if seed % 3 == 0:
        assert lam_h[1] == 0.0
    # a second-order correction changes only the rows' constant terms, in both
    shifted = d["g_pos"] + rng.uniform(0.0, 0.05, d["g_pos"].size)
    slot.set_position_bounds(row_s, shifted)
    hard.set_position_bounds(row_h, shifted)
    np.testing.assert_array_equal(hard.solve()[0], slot.solve()[0])
    assert d["g_pos"] is not shifted and np.all(d["g_pos"] < 0.0)  # the caller's rows kept


def test_an_infeasible_qp_fails_with_nan_step_and_zero_multipliers() -> None:
    d = _random_qp(np.random.default_rng(3), rows=4, feasible=False)
    hard = DaqpHardQP(NU, NS)
    _load(hard, d)
    z, lam, ok = hard.solve()
    assert not ok and np.isnan(z).all() and not lam.any()
    assert hard.failures == 0 and not hard.elastic and hard.solver == "daqp"


def test_without_daqp_it_is_an_error_naming_the_package(monkeypatch) -> None:
    monkeypatch.setitem(sys.modules, "daqp", None)  # the package is not installed
    with pytest.raises(ValueError, match="qp_solver='daqp' needs the daqp package"):
        DaqpHardQP(NU, NS)


def test_the_fast_solver_takes_it_for_the_qps_without_slacks_only_on_daqp() -> None:
    problem = problem_from_config(n_scenarios=20, horizon=5)
    auto = FastScenarioSolver(problem)
    assert isinstance(auto._qp(5, 1, elastic=False), DaqpHardQP)
    assert isinstance(auto._qp(5, 2, elastic=True), SlotQP)
    qpoases = FastScenarioSolver(problem, qp_solver="qpoases")
    assert isinstance(qpoases._qp(5, 1, elastic=False), SlotQP)
