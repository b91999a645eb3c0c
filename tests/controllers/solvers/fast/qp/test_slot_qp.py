"""The fast SQP's dense QP: persistent row slots, sizes that follow the rows in use."""

from __future__ import annotations

import sys

import numpy as np
import pytest

from controllers.solvers.fast.qp import slot_qp
from controllers.solvers.fast.qp.slot_qp import (
    AUTO_IPM_VARIABLES,
    AUTO_PIQP_VARIABLES,
    MAX_SPENT_MEMORIES,
    QP_SOLVERS,
    SlotQP,
    resolve_qp_solver,
)


def _qp(rows: int = 8, groups: int = 4, solver: str = "qpoases") -> SlotQP:
    return SlotQP(2, 0, rows, groups, solver, slack_penalty=100.0, slack_reg=1e-8)


def test_rows_and_groups_keep_their_slots_while_they_stay() -> None:
    qp = _qp()
    row, col = qp.assign(np.array([10, 11, 20]), np.array([1, 1, 2]))
    assert row.tolist() == [0, 1, 2] and col.tolist() == [0, 0, 1]
    # 11 leaves, 30 (a new group) and 12 come: the others keep their slots, the new ones
    # take the freed and the next free slots.
    row2, col2 = qp.assign(np.array([20, 10, 30, 12]), np.array([2, 1, 3, 1]))
    assert row2[0] == 2 and row2[1] == 0
    assert sorted(row2.tolist()) == [0, 1, 2, 3]
    assert col2[0] == 1 and col2[1] == 0 and col2[3] == 0 and col2[2] == 2


def test_reset_forgets_the_assignment() -> None:
    qp = _qp()
    qp.assign(np.array([5, 6]), np.array([0, 0]))
    qp.reset()
    row, col = qp.assign(np.array([6]), np.array([0]))
    assert row.tolist() == [0] and col.tolist() == [0]


def test_too_many_rows_is_an_error_naming_the_sizes() -> None:
    qp = _qp(rows=8)
    with pytest.raises(ValueError, match="9 keys do not fit 8 slots"):
        qp.assign(np.arange(9), np.zeros(9, dtype=int))


@pytest.mark.parametrize("solver", QP_SOLVERS)
def test_the_qp_of_two_groups_has_the_exact_penalty_solution(solver: str) -> None:
    """min 1/2 |d - (3, 0)|^2 s.t. d0 <= 1 (group a) and d0 + d1 <= 5 (group b), with the
    L1 penalty 100 on each group's slack: the first row binds, no slack is used, and
    unused slots and slack columns stay at zero."""
    qp = _qp(solver=solver)
    H = np.eye(2)
    qp.set_problem(
        H, np.array([-3.0, 0.0]), np.full(2, -10.0), np.full(2, 10.0), np.empty((0, 2)), np.empty(0)
    )
    row, col = qp.assign(np.array([1, 2]), np.array([7, 9]))
    qp.set_position_rows(row, col, np.array([[1.0, 0.0], [1.0, 1.0]]), np.array([-1.0, -5.0]))
    z, lam, ok = qp.solve()
    assert ok
    np.testing.assert_allclose(z[:2], [1.0, 0.0], atol=1e-8)
    np.testing.assert_allclose(z[2:], 0.0, atol=1e-8)
    assert lam[row[0]] == pytest.approx(2.0, abs=1e-8)
    assert lam[row[1]] == pytest.approx(0.0, abs=1e-8)
    # A row beyond what the penalty pays for: d0 <= -20 costs more than 100 per unit of
    # slack only up to the penalty, so the slack takes it.
    row, col = qp.assign(np.array([1, 2]), np.array([7, 9]))
    qp.set_position_rows(row, col, np.array([[1.0, 0.0], [1.0, 1.0]]), np.array([20.0, -5.0]))
    z, lam, ok = qp.solve()
    assert ok
    assert z[:2] == pytest.approx([-10.0, 0.0], abs=1e-7)  # the step's bound
    assert z[2 + col[0]] == pytest.approx(10.0, abs=1e-7)  # the rest is slack
    assert lam[row[0]] == pytest.approx(100.0, rel=1e-6)


def _random_qp(solver: str, seed: int = 0) -> tuple[SlotQP, np.ndarray]:
    """A strictly convex QP with 40 inputs and 64 group slack columns (104 variables)."""
    rng = np.random.default_rng(seed)
    n_u, groups, rows = 40, 64, 120
    qp = SlotQP(n_u, 0, 128, groups, solver, slack_penalty=50.0, slack_reg=1e-8)
    root = rng.normal(size=(n_u, n_u))
    H = root @ root.T / n_u + 0.1 * np.eye(n_u)
    qp.set_problem(
        H,
        rng.normal(size=n_u),
        np.full(n_u, -1.0),
        np.full(n_u, 1.0),
        np.empty((0, n_u)),
        np.empty(0),
    )
    row, col = qp.assign(np.arange(rows), rng.integers(0, groups, size=rows))
    qp.set_position_rows(row, col, rng.normal(size=(rows, n_u)), rng.normal(size=rows))
    return qp, H


def test_auto_resolves_by_the_qp_size() -> None:
    # (a C compiler is there: the elastic interior point builds)
    assert AUTO_IPM_VARIABLES < AUTO_PIQP_VARIABLES
    assert resolve_qp_solver("auto", AUTO_IPM_VARIABLES - 1) == "qpoases"
    assert resolve_qp_solver("auto", AUTO_IPM_VARIABLES) == "elastic_ipm"
    assert resolve_qp_solver("auto", 10 * AUTO_PIQP_VARIABLES) == "elastic_ipm"
    assert resolve_qp_solver("elastic_ipm", 2) == "elastic_ipm"
    assert resolve_qp_solver("daqp", 10_000) == "daqp"
    assert _qp(solver="auto").solver == "qpoases"
    assert _random_qp("auto")[0].solver == "elastic_ipm"
    # QPs without slacks: DAQP at any size; a solver named is used for them too, except
    # the elastic interior point, which is for QPs with slacks only.
    for n_var in (2, 10 * AUTO_PIQP_VARIABLES):
        assert resolve_qp_solver("auto", n_var, elastic=False) == "daqp"
        assert resolve_qp_solver("elastic_ipm", n_var, elastic=False) == "daqp"
    assert resolve_qp_solver("qpoases", 10, elastic=False) == "qpoases"
    hard = SlotQP(2, 0, 8, 4, "auto", slack_penalty=1.0, slack_reg=1e-8, elastic=False)
    assert hard.solver == "daqp"


@pytest.mark.parametrize("solver", ["piqp", "elastic_ipm"])
def test_the_interior_points_agree_with_qpoases_on_a_large_qp(solver: str) -> None:
    """The interior points' step, slacks and multipliers equal the active set's (a QP
    whose rows partly need slack)."""
    results = {}
    for name in ("qpoases", solver):
        qp, H = _random_qp(name)
        z, lam, ok = qp.solve()
        assert ok, name
        results[name] = (z, lam, 0.5 * z @ qp.H @ z + qp.g @ z)
    (z0, lam0, f0), (z1, lam1, f1) = results["qpoases"], results[solver]
    assert f1 == pytest.approx(f0, rel=1e-9)
    np.testing.assert_allclose(z1, z0, atol=1e-6)
    np.testing.assert_allclose(lam1, lam0, atol=1e-5 * max(1.0, float(np.max(lam0))))
    assert np.max(z0[40:]) > 1e-3  # some rows really need slack


def test_cold_started_solvers_take_the_rows_in_order() -> None:
    """DAQP, PIQP and the elastic interior point keep nothing between calls: rows go to
    the slots in the order given and the groups to the columns in ascending order."""
    for solver in ("piqp", "elastic_ipm"):
        qp = _qp(solver=solver)
        qp.assign(np.array([10, 11, 20]), np.array([1, 1, 2]))
        row, col = qp.assign(np.array([20, 10, 30, 12]), np.array([2, 1, 3, 1]))
        assert row.tolist() == [0, 1, 2, 3] and col.tolist() == [1, 0, 2, 0]
        with pytest.raises(ValueError, match="9 keys do not fit 8 slots"):
            qp.assign(np.arange(9), np.zeros(9, dtype=int))
        with pytest.raises(ValueError, match="5 keys do not fit 4 slots"):
            qp.assign(np.arange(5), np.arange(5))


def test_without_daqp_auto_takes_qpoases_for_the_qps_without_slacks(monkeypatch) -> None:
    monkeypatch.setitem(sys.modules, "daqp", None)  # the package is not installed
    assert resolve_qp_solver("auto", 14, elastic=False) == "qpoases"
    with pytest.raises(ValueError, match="qp_solver='daqp' needs the daqp package"):
        _qp(solver="daqp")


def test_without_piqp_auto_falls_back_and_piqp_is_an_error(monkeypatch) -> None:
    monkeypatch.setitem(sys.modules, "piqp", None)  # the package is not installed
    assert resolve_qp_solver("auto", 10 * AUTO_PIQP_VARIABLES) == "elastic_ipm"
    monkeypatch.setattr(slot_qp, "AUTO_IPM_VARIABLES", 10**9)  # (the interior point not taken)
    assert resolve_qp_solver("auto", 10 * AUTO_PIQP_VARIABLES) == "qpoases"
    with pytest.raises(ValueError, match="qp_solver='piqp' needs the piqp package"):
        _qp(solver="piqp")


def _small_random_qp(qp: SlotQP, rng: np.random.Generator) -> None:
    """A random strictly convex QP with two active-ish rows in two groups on ``qp``."""
    M = rng.normal(size=(2, 2))
    lo = np.full(2, -1.0)
    qp.set_problem(M @ M.T + np.eye(2), rng.normal(size=2), lo, -lo, np.empty((0, 2)), np.empty(0))
    row, col = qp.assign(np.array([1, 2]), np.array([7, 9]))
    qp.set_position_rows(row, col, rng.normal(size=(2, 2)), rng.normal(size=2) - 0.5)


def test_after_reset_qpoases_starts_cold_however_many_problems_came_before() -> None:
    """A reset QP object solves like a new one, bit for bit, also after more resets than it
    keeps spent qpOASES memories (then it builds a new conic), and it keeps no more."""
    rng = np.random.default_rng(3)
    target = _qp()
    _small_random_qp(target, np.random.default_rng(99))
    expected = target.solve()
    used = _qp()
    assert used.max_spent == MAX_SPENT_MEMORIES  # (a small QP)
    for _ in range(MAX_SPENT_MEMORIES + 5):
        _small_random_qp(used, rng)  # a hot-started history on this object
        assert used.solve()[2]
        _small_random_qp(used, rng)
        assert used.solve()[2]
        used.reset()
        _small_random_qp(used, np.random.default_rng(99))
        z, lam, ok = used.solve()
        assert ok
        np.testing.assert_array_equal(z, expected[0])
        np.testing.assert_array_equal(lam, expected[1])
        assert len(used._spent) <= MAX_SPENT_MEMORIES
        used.reset()


@pytest.mark.parametrize("solver", QP_SOLVERS)
def test_the_qp_without_slacks_has_the_elastic_qps_step_or_fails(solver: str) -> None:
    """``elastic=False``: only the inputs are variables. Where the rows can be met it gives
    the elastic QP's step and multipliers; where they cannot, it fails at once (no retries:
    the SQP then takes the elastic QP)."""
    hard = SlotQP(2, 0, 8, 4, solver, slack_penalty=100.0, slack_reg=1e-8, elastic=False)
    assert hard.n_var == 2 and not hard.elastic
    box = (np.full(2, -10.0), np.full(2, 10.0))
    hard.set_problem(np.eye(2), np.array([-3.0, 0.0]), *box, np.empty((0, 2)), np.empty(0))
    row, col = hard.assign(np.array([1, 2]), np.array([7, 9]))
    assert (col == -1).all()  # no slack columns
    hard.set_position_rows(row, col, np.array([[1.0, 0.0], [1.0, 1.0]]), np.array([-1.0, -5.0]))
    z, lam, ok = hard.solve()
    assert ok and z.shape == (2,)
    np.testing.assert_allclose(z, [1.0, 0.0], atol=1e-8)
    assert lam[row[0]] == pytest.approx(2.0, abs=1e-7)
    assert lam[row[1]] == pytest.approx(0.0, abs=1e-7)
    # d0 <= -20 cannot be met inside the box |d| <= 10.
    hard.set_position_rows(row, col, np.array([[1.0, 0.0], [1.0, 1.0]]), np.array([20.0, -5.0]))
    _, _, ok = hard.solve()
    assert not ok and hard.failures == 0
