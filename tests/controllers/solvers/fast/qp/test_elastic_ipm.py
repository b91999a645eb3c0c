"""The compiled interior point for the elastic QP: its solutions against PIQP and the
optimality conditions, its errors, and the fall-back of ``qp_solver="auto"`` without it."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from controllers.solvers.fast.codegen import build as compiled
from controllers.solvers.fast.qp import elastic_ipm, slot_qp
from controllers.solvers.fast.qp.elastic_ipm import solve_elastic_qp
from controllers.solvers.fast.solver import FastScenarioSolver
from experiments.benchmark.problems import problem_from_config

piqp = pytest.importorskip("piqp")


def _qp(seed: int, n: int = 6, m: int = 15, groups: int = 4, box: float = 1.0) -> dict:
    """A random elastic QP; some rows cannot hold without slack, some bounds are missing."""
    rng = np.random.default_rng(seed)
    R = rng.normal(size=(n, n))
    A = rng.normal(size=(m, n))
    qp = dict(
        H=R.T @ R + 0.1 * np.eye(n),
        g=rng.normal(size=n) * 5.0,
        lo=np.full(n, -box),
        hi=np.full(n, box),
        A=A,
        b=rng.normal(size=m) - 1.0,
        col=rng.integers(0, groups, size=m),
        rho=rng.uniform(10.0, 100.0, size=groups),
        reg=np.full(groups, 1e-8),
    )
    qp["lo"][0], qp["hi"][-1] = -np.inf, np.inf
    return qp


def _objective(qp: dict, d: np.ndarray, s: np.ndarray) -> float:
    return float(0.5 * d @ qp["H"] @ d + qp["g"] @ d + qp["rho"] @ s + 0.5 * (qp["reg"] * s) @ s)


def _piqp(qp: dict) -> tuple[np.ndarray, np.ndarray, float]:
    """The same QP in all variables (d, s), solved by PIQP."""
    n, G, m = qp["H"].shape[0], qp["rho"].size, qp["A"].shape[0]
    H = np.zeros((n + G, n + G))
    H[:n, :n] = qp["H"]
    H[n:, n:] = np.diag(qp["reg"])
    A = np.zeros((m, n + G))
    A[:, :n] = qp["A"]
    A[np.arange(m), n + qp["col"]] = -1.0
    lo = np.concatenate([np.maximum(qp["lo"], -1e30), np.zeros(G)])
    hi = np.concatenate([np.minimum(qp["hi"], 1e30), np.full(G, 1e30)])
    solver = piqp.DenseSolver()
    solver.settings.eps_abs, solver.settings.eps_rel = 1e-10, 1e-12
    g = np.concatenate([qp["g"], qp["rho"]])
    solver.setup(H, g, None, None, A, None, qp["b"], lo, hi)
    assert solver.solve() == piqp.PIQP_SOLVED
    x = solver.result.x
    return x[:n], x[n:], _objective(qp, x[:n], x[n:])


def _assert_optimal(qp: dict, res, tol: float = 1e-7) -> None:
    """The optimality conditions, checked on their own (no other solver)."""
    H, g, A, b, col = qp["H"], qp["g"], qp["A"], qp["b"], qp["col"]
    d, s, z = res.d, res.s, res.z
    slack_of_row = s[col] if col.size else np.zeros(0)
    row_gap = b - A @ d + slack_of_row
    assert np.all(row_gap >= -tol) and np.all(s >= -tol)
    assert np.all(d >= qp["lo"] - tol) and np.all(d <= qp["hi"] + tol)
    assert np.all(z >= -tol)
    assert np.max(np.abs(z * row_gap), initial=0.0) <= tol * max(1.0, float(np.max(z, initial=0)))
    # stationarity in d: zero off the bounds, the bound's sign on them
    r = H @ d + g + A.T @ z
    free = (d > qp["lo"] + 1e-6) & (d < qp["hi"] - 1e-6)
    scale = 1.0 + float(np.max(np.abs(A.T * z), initial=0.0)) + float(np.max(np.abs(H @ d)))
    assert np.max(np.abs(r[free]), initial=0.0) <= tol * scale
    assert np.all(r[d >= qp["hi"] - 1e-6] <= tol * scale)
    assert np.all(r[d <= qp["lo"] + 1e-6] >= -tol * scale)
    # in s: rho + reg s - (sum of the group's multipliers) is the bound's multiplier
    rs = qp["rho"] + qp["reg"] * s - np.bincount(col, z, minlength=s.size)
    assert np.all(rs >= -tol * (1.0 + qp["rho"].max()))
    assert np.all(np.abs(rs[s > 1e-6]) <= tol * (1.0 + qp["rho"].max()))


@pytest.mark.parametrize("seed", range(8))
def test_random_elastic_qps_are_solved_to_optimality_and_match_piqp(seed: int) -> None:
    qp = _qp(seed)
    res = solve_elastic_qp(**qp)
    assert res.solved, res.status
    _assert_optimal(qp, res)
    d, s, f = _piqp(qp)
    assert _objective(qp, res.d, res.s) == pytest.approx(f, rel=1e-9, abs=1e-9)
    np.testing.assert_allclose(res.d, d, atol=1e-6)
    assert np.max(res.s) > 1e-3  # some rows need slack


def test_degenerate_rows_and_a_strongly_active_group() -> None:
    """Duplicate rows, a zero row, every row in one group and a row that stays active with
    a large multiplier: the cases where the eliminated form could lose accuracy."""
    qp = _qp(3, m=12, groups=1)
    qp["A"][5] = qp["A"][4]
    qp["b"][5] = qp["b"][4]
    qp["A"][6] = 0.0
    qp["b"][6] = 0.5
    qp["rho"][:] = 1e4  # multipliers up to 1e4: rows strongly active
    res = solve_elastic_qp(**qp)
    assert res.solved, res.status
    _assert_optimal(qp, res, tol=1e-6)
    assert _objective(qp, res.d, res.s) == pytest.approx(_piqp(qp)[2], rel=1e-9)


def test_without_rows_it_is_the_box_qp() -> None:
    qp = _qp(1, m=0)
    res = solve_elastic_qp(**qp)
    assert res.solved and res.z.shape == (0,)
    _assert_optimal(qp, res)
    assert _objective(qp, res.d, res.s) == pytest.approx(_piqp(qp)[2], rel=1e-9)
    np.testing.assert_allclose(res.s, 0.0, atol=1e-9)  # no rows: the slacks only cost


def test_the_iteration_limit_is_reported_not_hidden() -> None:
    res = solve_elastic_qp(**_qp(0), max_iter=2)
    assert not res.solved and res.status == "iteration limit" and res.iterations == 2


@pytest.mark.parametrize(
    ("field", "value", "message"),
    [
        ("g", np.zeros(5), r"g has shape \(5,\): must be \(6,\)"),
        ("hi", np.zeros((6, 1)), r"hi has shape \(6, 1\): must be \(6,\)"),
        ("H", np.zeros((6, 5)), "H: expected a square matrix"),
        ("col", np.full(15, 4), r"col: expected 15 slack columns in \[0, 4\)"),
        ("reg", np.zeros(3), r"reg has shape \(3,\): must be \(4,\)"),
    ],
)
def test_bad_arrays_are_errors_naming_the_field(field, value, message) -> None:
    qp = _qp(0)
    qp[field] = value
    with pytest.raises(ValueError, match=message):
        solve_elastic_qp(**qp)


def test_without_a_compiler_auto_falls_back_and_elastic_ipm_is_an_error(
    tmp_path, monkeypatch
) -> None:
    """No C compiler (``$CC`` names none) and nothing cached: ``"auto"`` takes PIQP and
    qpOASES as before, ``"elastic_ipm"`` is an error naming what it needs."""
    monkeypatch.setenv("CC", str(tmp_path / "no-such-compiler"))
    elastic_ipm._library.cache_clear()
    compiled.forget_loaded()
    try:
        with compiled.fresh_cache():
            assert not elastic_ipm.available()
            n_big = max(slot_qp.AUTO_PIQP_VARIABLES, slot_qp.AUTO_IPM_VARIABLES)
            assert slot_qp.resolve_qp_solver("auto", n_big) == "piqp"
            with pytest.raises(ValueError, match="needs a working C compiler"):
                slot_qp.SlotQP(2, 0, 8, 4, "elastic_ipm", slack_penalty=1.0, slack_reg=1e-8)
            with pytest.raises(compiled.CodegenUnavailable, match="needs a C compiler"):
                solve_elastic_qp(**_qp(0))
    finally:
        elastic_ipm._library.cache_clear()
        compiled.forget_loaded()
    monkeypatch.delenv("CC")
    assert elastic_ipm.available()  # (from the real cache again)


@pytest.mark.parametrize("n", [15, 30])
def test_the_recorded_long_horizon_qps_solve_without_a_retry(n: int) -> None:
    """On the recorded long-horizon problems every elastic QP is solved by the interior
    point itself: none falls back to qpOASES (``qp_retries``). (Without the dual
    regularisation or the multiplier steps from the complementarity equation some stall.)"""
    long = np.load(Path(__file__).resolve().parents[4] / "data" / "long_horizon_problems.npz")
    problem = problem_from_config(n_scenarios=long[f"W_{n}"].shape[1], horizon=n)
    solver = FastScenarioSolver(problem, qp_solver="elastic_ipm")
    calls = retries = 0
    for i in range(long[f"seed_{n}"].size):
        sol = solver.solve(long[f"x0_{n}"][i], long[f"W_{n}"][i], u_guess=long[f"u_guess_{n}"][i])
        calls += sol.extra["qp_calls"].get("elastic_ipm", 0)
        retries += sol.extra["qp_retries"]
    assert calls > 10
    assert retries == 0


def test_auto_gives_the_long_horizons_qps_to_it_and_keeps_qpoases_at_the_papers() -> None:
    """``qp_solver="auto"``: the QPs with slacks of the paper's N = 7 (at most 53 variables)
    stay with hot-started qpOASES, those of N = 15 (76 and more) go to the interior point."""
    data = Path(__file__).resolve().parents[4] / "data"
    calls = {}
    for n, name in ((7, "recorded_problems.npz"), (15, "long_horizon_problems.npz")):
        rec = np.load(data / name)
        suffix = "" if n == 7 else f"_{n}"
        W = rec[f"W{suffix}"]
        solver = FastScenarioSolver(problem_from_config(n_scenarios=W.shape[1], horizon=n))
        calls[n] = {}
        for i in range(W.shape[0]):
            guess = rec[f"u_guess{suffix}"][i]
            sol = solver.solve(rec[f"x0{suffix}"][i], W[i], u_guess=guess)
            for key, count in sol.extra["qp_calls"].items():
                calls[n][key] = calls[n].get(key, 0) + count
    assert calls[7].get("qpoases", 0) > 0 and "elastic_ipm" not in calls[7]
    assert calls[15].get("elastic_ipm", 0) > 0 and "piqp" not in calls[15]
