"""Which scenario rows enter the fast solver's QP: the compiled selection against its reference.

:meth:`CondensedModel.screen` (the rows a QP starts with) and
:meth:`CondensedModel.violated_rows` (the rows a QP step violates, added by check-and-add)
run in the C library (``lfm_screen``, ``lfm_violated``) when there is one, else as
:mod:`controllers.solvers.fast.screening`. Checked here: both give the same rows, in the same
order, on the recorded paper problems and on the point mass of ``test_second_system.py``;
the rule on ties (larger value, then lower scenario) and on NaN groups; the selection's
own promises (at most ``keep`` per group by value, nothing already in the QP, nothing at
or below the tolerance, every group with a row within the margin represented).
"""

from __future__ import annotations

import numpy as np
import pytest

from controllers.problem import ScenarioProblem
from controllers.solvers.fast.condensed import CondensedModel
from controllers.solvers.fast.screening import screen_rows, worst_rows
from tests.controllers.solvers.recorded import load_problems
from tests.controllers.test_second_system import (
    COST,
    NS,
    STARTS,
    N,
    point_mass,
    point_mass_model,
    sample_forces,
)

DATA = load_problems()
KEEP = 4


@pytest.fixture(scope="module")
def paper_c(paper) -> CondensedModel:
    model = CondensedModel(paper, backend="c")
    assert model.backend == "compiled-c"
    return model


def _rollout(model: CondensedModel, x0, W, u):
    x0, W = model.problem.check_data(x0, W)
    ro = model.evaluate(
        np.ascontiguousarray(x0.T),
        np.ascontiguousarray(W.transpose(1, 0, 2)),
        u,
        model.state_cost0(x0),
    )
    return ro, np.ascontiguousarray(W.transpose(2, 1, 0))


def _reference_violated(model, lin, d, s_pos, pos, tol, keep) -> np.ndarray:
    viol = model.linearised_values(lin, d)
    viol -= s_pos[model.screened][:, :, None]
    return worst_rows(viol, model.screened, pos, tol, keep)


def _check_both(model: CondensedModel, ro, lin, rng) -> int:
    """The compiled selections equal the reference at ``ro`` / ``lin``; rows compared."""
    count = 0
    for margin in (0.0, 0.5, 5.0):
        got = model.screen(ro, margin, KEEP)
        ref = screen_rows(ro.G, ro.X, model.screened, model.depends, margin, KEEP)
        assert got.shape[1] == 3 and np.array_equal(got, ref), margin
        count += got.shape[0]
    p = model.problem
    pos = model.screen(ro, 0.5, KEEP)[::3]  # some rows already in the QP
    # (in any order, some twice: the QP's rows come in the order they were added)
    pos = rng.permutation(np.concatenate([pos, pos[: pos.shape[0] // 2]]))
    for scale in (0.05, 0.5):
        d = rng.uniform(-scale, scale, p.horizon * p.nu)
        s_pos = rng.uniform(0.0, 0.1, (p.ng, p.horizon))
        for tol in (1e-9, 0.05):
            got = model.violated_rows(lin, d, s_pos, pos, tol, KEEP)
            ref = _reference_violated(model, lin, d, s_pos, pos, tol, KEEP)
            assert np.array_equal(got, ref), (scale, tol)
            count += got.shape[0]
    return count


@pytest.mark.parametrize("i", range(len(DATA["seed"])))
def test_compiled_selection_equals_the_reference_on_the_recorded_problems(i, paper_c) -> None:
    rng = np.random.default_rng(i)
    total = 0
    for u in (DATA["reference_u"][i].ravel(), DATA["u_guess"][i].ravel()):
        ro, W_lanes = _rollout(paper_c, DATA["x0"][i], DATA["W"][i], u)
        total += _check_both(paper_c, ro, paper_c.linearise(ro, W_lanes), rng)
    assert total > 0  # the comparison saw rows, not only empty selections


def test_compiled_selection_equals_the_reference_on_the_second_system() -> None:
    model = point_mass_model(point_mass())
    problem = ScenarioProblem(model, COST, horizon=N, n_scenarios=NS, slack_penalty=1.0e3)
    c = CondensedModel(problem, backend="c")
    assert c.backend == "compiled-c" and c.screened.size > 0
    rng = np.random.default_rng(5)
    total = 0
    for seed, x0 in enumerate(STARTS.values()):
        u = rng.uniform(-2.0, 2.0, N * problem.nu)
        ro, W_lanes = _rollout(c, x0, sample_forces(model, seed), u)
        total += _check_both(c, ro, c.linearise(ro, W_lanes), rng)
    assert total > 0


def _crafted(paper_c, paper):
    """A rollout and linearisation of the first recorded problem whose constraint values
    are then replaced (the selection reads only ``G`` and ``X``; with ``d = 0`` the
    linearised values are ``G`` exactly)."""
    ro, W_lanes = _rollout(paper_c, DATA["x0"][0], DATA["W"][0], DATA["u_guess"][0].ravel())
    lin = paper_c.linearise(ro, W_lanes)
    ro.G[:] = -10.0  # every group far from activity
    return ro, lin, np.zeros(paper.horizon * paper.nu), np.zeros((paper.ng, paper.horizon))


@pytest.mark.parametrize("backend", ["c", "numpy"])
def test_ties_go_to_the_lower_scenario_and_nan_groups_are_left_out(backend, paper, paper_c):
    model = paper_c if backend == "c" else CondensedModel(paper, backend="numpy")
    ro, lin, d, s_pos = _crafted(paper_c, paper)
    j = int(model.screened[0])
    ro.G[j, 2, [3, 7, 20, 40, 41, 90]] = [0.2, 0.2, 0.2, 0.3, 0.2, 0.2]  # ties at 0.2
    ro.G[j, 4, [5, 6]] = [0.1, np.nan]  # a group with a NaN
    empty = np.empty((0, 3), dtype=int)
    got_v = model.violated_rows(lin, d, s_pos, empty, 1e-9, KEEP)
    got_s = model.screen(ro, 0.0, KEEP)
    # the four largest: 0.3 (scenario 40), then the ties 0.2 by scenario 3, 7, 20
    assert got_v.tolist() == [[j, 2, 3], [j, 2, 7], [j, 2, 20], [j, 2, 40]]
    group = got_s[(got_s[:, 0] == j) & (got_s[:, 1] == 2)]
    assert {3, 7, 20, 40} <= set(group[:, 2].tolist())
    assert not ((got_s[:, 0] == j) & (got_s[:, 1] == 4)).any()  # the NaN group
    assert set(got_s[:, 1].tolist()) == {2}  # no other group is within the margin


def test_violated_rows_leave_out_the_qp_rows_and_rows_at_the_tolerance(paper, paper_c):
    ro, lin, d, s_pos = _crafted(paper_c, paper)
    j = int(paper_c.screened[-1])
    ro.G[j, 0, [1, 2, 3, 4, 5, 6]] = [0.5, 0.4, 0.3, 1e-9, 0.2, 0.1]
    s_pos[j, 0] = 0.05  # the QP's slack of that group lowers every value
    pos = np.array([[j, 0, 1]])  # already in the QP
    got = paper_c.violated_rows(lin, d, s_pos, pos, 0.1, KEEP)
    # 0.4, 0.3, 0.2 minus the slack exceed 0.1; 0.1 - 0.05 and 1e-9 - 0.05 do not
    assert got.tolist() == [[j, 0, 2], [j, 0, 3], [j, 0, 5]]
    assert np.array_equal(got, _reference_violated(paper_c, lin, d, s_pos, pos, 0.1, KEEP))
