"""The fast SQP's loop compiled (``fast_c``) against the Python loop it was written from.

The C loop (``codegen/c/sqp.c``) runs the algorithm of
:class:`~controllers.solvers.fast.solver.FastScenarioSolver` with the project's own QP
solvers; the Python loop with ``qp_solver="elastic_ipm"`` uses the same elastic interior
point for the QPs with slacks and DAQP for those without, where the C loop has its dual
active-set method (``dense.c``): both solve those QPs exactly, so the plans agree to rounding.
Compared on the recorded problems (N = 7, 15, 30), the quadrotor, with a back-off and with the
options that change the algorithm's path; and the pieces (the dense QP against DAQP, the
eigen-decomposition against LAPACK), the fallback without a compiler, the time limit.
"""

from __future__ import annotations

import ctypes
import pickle
import warnings
from pathlib import Path

import numpy as np
import pytest

from controllers.config import load_config
from controllers.problem import ScenarioProblem
from controllers.solvers import make_solver
from controllers.solvers.fast.codegen import build
from controllers.solvers.fast.compiled import (
    FALLBACK_NOTICE,
    CompiledScenarioSolver,
    sqp_library,
)
from controllers.solvers.fast.solver import FastScenarioSolver
from experiments.benchmark.problems import problem_from_config

DATA_DIR = Path(__file__).resolve().parents[3] / "data"
RECORDED = dict(np.load(DATA_DIR / "recorded_problems.npz"))
LONG = dict(np.load(DATA_DIR / "long_horizon_problems.npz"))
SAME_QP = {"qp_solver": "elastic_ipm"}  # the Python loop's closest QP choice
PLAN_TOL = 1e-9  # [m/s^2, rad] plans of the two loops
# N = 30: every problem is infeasible for every input, and the merit is flat along some
# directions; rounding (the eigen-decompositions are LAPACK's and dense.c's) moves the plan
# along them by up to 3.4e-8 on problem 0 (the same iterations, objective to 1e-12 relative).
PLAN_TOL_FLAT = 1e-6
PLAN_TOL_OPTIONS = 1e-3  # [m/s^2, rad] with other options (test_the_options_change_...)


def _compare(
    problem: ScenarioProblem, cases, plan_tol: float = PLAN_TOL, exact: bool = True, **options
) -> list[float]:
    """Both loops from scratch on each (x0, W[, backoff]) case: the same statuses, objectives
    to 1e-9 relative, plans within plan_tol; with exact, also the same iterations, QP calls
    and extra starts. Returns the plan differences."""
    python = FastScenarioSolver(problem, **{**SAME_QP, **options})
    compiled = CompiledScenarioSolver(problem, **{**SAME_QP, **options})
    assert compiled.loop == "c"
    diffs = []
    for case in cases:
        python.reset()
        compiled.reset()
        a = python.solve(*case[:2], backoff=case[2] if len(case) > 2 else None)
        b = compiled.solve(*case[:2], backoff=case[2] if len(case) > 2 else None)
        assert b.status == a.status
        if exact:
            assert b.iterations == a.iterations
            assert b.extra["qp_solves"] == a.extra["qp_solves"]
            assert b.extra["qp_hard"] == a.extra["qp_hard"]
            assert b.extra["restarts"] == a.extra["restarts"]
        assert b.objective == pytest.approx(a.objective, rel=1e-9)
        assert b.slack == pytest.approx(a.slack, rel=1e-7, abs=1e-9)
        diffs.append(float(np.max(np.abs(b.u - a.u))))
        assert diffs[-1] <= plan_tol
        np.testing.assert_allclose(b.predicted, problem.rollout(case[0], case[1], b.u), atol=1e-12)
    return diffs


def _long(n: int) -> tuple[ScenarioProblem, list]:
    problem = problem_from_config(n_scenarios=LONG[f"W_{n}"].shape[1], horizon=n)
    return problem, list(zip(LONG[f"x0_{n}"], LONG[f"W_{n}"], strict=True))


def test_the_recorded_paper_problems_give_the_python_loops_plans() -> None:
    problem = problem_from_config(n_scenarios=150)
    diffs = _compare(problem, list(zip(RECORDED["x0"], RECORDED["W"], strict=True)))
    assert max(diffs) < PLAN_TOL


@pytest.mark.parametrize("n", [15, 30])
def test_the_long_horizons_give_the_python_loops_plans(n: int) -> None:
    problem, cases = _long(n)
    _compare(problem, cases, PLAN_TOL if n == 15 else PLAN_TOL_FLAT)


@pytest.mark.parametrize(
    "options",
    [
        {"trust_radius": 0.0},  # Levenberg-Marquardt damping instead of the trust region
        {"hessian_modification": "abs"},
        {"hessian_modification": "augmented"},
        {"elastic_qp": "always"},
        {"restarts": (), "max_expand": 0, "second_order_correction": False},
        {"soc_below_ratio": 0.0, "screen_rows": 2, "max_qp_rounds": 2},
    ],
    ids=lambda o: ",".join(f"{k}={v}" for k, v in o.items()),
)
def test_the_options_change_both_loops_alike(options) -> None:
    """Options that send more steps through an eigen-decomposition (LAPACK's in Python,
    dense.c's here) or end where the interior point's stopping test is loose (its duality
    gap relative to the objective's terms, ~1e5 when slack is needed): the same statuses and
    objectives, and plans within what those tolerances allow (measured: up to 2.2e-4 with
    trust_radius=0 on one problem, 1.3e-6 with "augmented"; the rest within 1e-9)."""
    problem = problem_from_config(n_scenarios=150)
    cases = list(zip(RECORDED["x0"][::3], RECORDED["W"][::3], strict=True))
    diffs = _compare(problem, cases, PLAN_TOL_OPTIONS, exact=False, **options)
    assert sum(d <= PLAN_TOL for d in diffs) >= len(diffs) - 1


def test_a_backoff_tightens_both_loops_alike() -> None:
    problem = problem_from_config(n_scenarios=150)
    rng = np.random.default_rng(3)
    cases = [
        (x0, W, rng.uniform(0.0, 0.3, (problem.horizon, problem.ng)))
        for x0, W in zip(RECORDED["x0"][::4], RECORDED["W"][::4], strict=True)
    ]
    _compare(problem, cases)


def test_the_quadrotor_gives_the_python_loops_plans() -> None:
    """A second system: six states, two inputs, no mirrored input, no shared row. (The force
    drawn with QuadrotorGust-v0's variance: at v1's, two of these four draws need slack and the
    loops then take 47 and 50, 19 and 20 QP solves for the same iterations and plans within
    4.3e-8, rounding in the check-and-add rounds, which this exact comparison does not allow.)"""
    config = load_config({"base": "quadrotor", "env": {"latent_force": {"variance": 6.25}}})
    problem = config.make_problem()
    model, rng = problem.model, np.random.default_rng(0)
    x0 = np.array([0.0, 1.0, 0.0, 0.0, 0.0, 0.0])  # the env's start [m, m, rad, m/s, m/s, rad/s]
    cases = []
    for i in range(4):
        z0 = rng.standard_normal((problem.n_scenarios, model.latent_dim)) * 0.5
        W = model.sample_latent_forecasts(z0, problem.horizon, rng)
        cases.append((x0 + 0.3 * i * np.array([1.0, 0.1, 0.0, 0.5, 0.0, 0.0]), W))
    _compare(problem, cases)


def test_warm_starts_follow_the_previous_plan_as_in_python() -> None:
    problem = problem_from_config(n_scenarios=150)
    python = FastScenarioSolver(problem, **SAME_QP)
    compiled = make_solver(problem, "fast_c")
    for x0, W in zip(RECORDED["x0"][:4], RECORDED["W"][:4], strict=True):
        a, b = python.solve(x0, W), compiled.solve(x0, W)
        assert b.iterations == a.iterations
        np.testing.assert_allclose(b.u, a.u, rtol=0, atol=PLAN_TOL)
    guess = RECORDED["u_guess"][5]
    a = python.solve(RECORDED["x0"][5], RECORDED["W"][5], u_guess=guess)
    b = compiled.solve(RECORDED["x0"][5], RECORDED["W"][5], u_guess=guess)
    np.testing.assert_allclose(b.u, a.u, rtol=0, atol=PLAN_TOL)
    assert b.extra["loop"] == "c" and b.extra["backend"] == "compiled-c"
    restored = pickle.loads(pickle.dumps(compiled))
    c = restored.solve(RECORDED["x0"][5], RECORDED["W"][5], u_guess=guess)
    np.testing.assert_array_equal(c.u, b.u)


def test_the_time_limit_stops_the_c_loop() -> None:
    problem = problem_from_config(n_scenarios=150)
    solver = CompiledScenarioSolver(problem, max_time=1e-7)
    sol = solver.solve(RECORDED["x0"][1], RECORDED["W"][1])
    assert sol.status == "Maximum_WallTime_Exceeded" and not sol.success
    assert np.all(np.isfinite(sol.u))


def test_a_plan_stopped_early_is_usable_as_in_python() -> None:
    """MPCSolution.usable: a solve stopped before convergence (here after one iteration)
    gives a plan the agents apply when its merit is below the warm start's. The C loop
    reports the warm start's merit as the Python loop does, so both call the same plans
    usable; a plan stopped before any iteration (no time) is not usable."""
    problem = problem_from_config(n_scenarios=150)
    python = FastScenarioSolver(problem, max_iter=1, **SAME_QP)
    compiled = CompiledScenarioSolver(problem, max_iter=1, **SAME_QP)
    seen_usable = 0
    for x0, W in zip(RECORDED["x0"][:6], RECORDED["W"][:6], strict=True):
        python.reset()
        compiled.reset()
        a, b = python.solve(x0, W), compiled.solve(x0, W)
        assert b.status == a.status and not b.success
        assert b.extra["start_merit"] == pytest.approx(a.extra["start_merit"], rel=1e-12)
        assert b.usable == a.usable and b.usable == (b.objective < b.extra["start_merit"])
        seen_usable += b.usable
    assert seen_usable > 0  # one iteration does lower the merit on these problems
    late = CompiledScenarioSolver(problem, max_time=1e-7).solve(RECORDED["x0"][1], RECORDED["W"][1])
    assert not late.usable and late.objective == late.extra["start_merit"]


def test_other_qp_solvers_are_refused() -> None:
    problem = problem_from_config(n_scenarios=2)
    with pytest.raises(ValueError, match="qp_solver='qpoases'"):
        CompiledScenarioSolver(problem, qp_solver="qpoases")
    with pytest.raises(ValueError, match="unknown CompiledScenarioSolver options"):
        CompiledScenarioSolver(problem, speed=1)


@pytest.mark.parametrize("how", ["CC missing", "PATH without cc"])
def test_without_a_compiler_the_python_loop_runs_after_a_one_line_notice(
    how: str, monkeypatch, tmp_path
) -> None:
    problem = problem_from_config(n_scenarios=150)
    x0, W = RECORDED["x0"][0], RECORDED["W"][0]
    if how == "CC missing":
        monkeypatch.setenv("CC", "/nonexistent/lfm-no-cc")
    else:
        monkeypatch.delenv("CC", raising=False)
        monkeypatch.setenv("PATH", str(tmp_path))  # an empty folder: no cc, no gcc
    with build.fresh_cache(), warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        solver = make_solver(problem, "fast_c")
        python = FastScenarioSolver(problem)  # the Python loop, also without a compiler
    expected = python.solve(x0, W)
    assert python.backend == solver.backend == "numpy-lanes"
    notices = [w for w in caught if issubclass(w.category, RuntimeWarning)]
    assert len(notices) == 1
    text = str(notices[0].message)
    assert "\n" not in text and text.startswith(FALLBACK_NOTICE.split("{")[0])
    assert "no C compiler found" in text
    assert solver.loop == "python" and solver.fallback_reason
    sol = solver.solve(x0, W)
    assert sol.extra["loop"] == "python"
    np.testing.assert_array_equal(sol.u, expected.u)


# --------------------------------------------------------------------------- the pieces


def _lib():
    problem = problem_from_config(n_scenarios=2)
    lib = sqp_library(problem.system, problem.dt)
    P, L = ctypes.c_void_p, ctypes.c_long
    lib.lfm_dense_qp.argtypes = [L, L, P, P, P, P, P, P, ctypes.c_double, L, P, P, P]
    lib.lfm_dense_qp.restype = ctypes.c_int
    lib.lfm_dense_eigh.argtypes = [L, P, P, P]
    lib.lfm_dense_eigh.restype = ctypes.c_int
    return lib


def _dense_qp(lib, H, g, lo, hi, A, b):
    n, m = g.size, b.size
    x, lam, steps = np.zeros(n), np.zeros(m), np.zeros(1, dtype=np.int64)
    arrays = [np.ascontiguousarray(a, dtype=float) for a in (H, g, lo, hi, A, b)]
    code = lib.lfm_dense_qp(
        n,
        m,
        *(a.ctypes.data for a in arrays),
        1e-10,
        10_000,
        x.ctypes.data,
        lam.ctypes.data,
        steps.ctypes.data,
    )
    return code, x, lam


def test_the_dense_qp_solves_what_daqp_solves() -> None:
    """Random strictly convex QPs with bounds and rows (some infeasible, some degenerate:
    repeated rows): the same step as DAQP where DAQP solves, KKT conditions, and
    infeasibility where DAQP finds it."""
    daqp = pytest.importorskip("daqp")
    lib, rng = _lib(), np.random.default_rng(7)
    solved = infeasible = 0
    for trial in range(300):
        n, m = int(rng.integers(1, 16)), int(rng.integers(0, 30))
        M = rng.standard_normal((n, n))
        H = M @ M.T + 0.1 * np.eye(n)
        g = rng.standard_normal(n) * 3
        lo, hi = -rng.uniform(0.1, 2, n), rng.uniform(0.1, 2, n)
        if trial % 5 == 0:
            lo[0], hi[-1] = -np.inf, np.inf
        A = rng.standard_normal((m, n))
        if m > 2 and trial % 4 == 0:
            A[1] = A[0]  # a repeated row
        b = rng.standard_normal(m) * (3.0 if trial % 3 else 0.3)
        code, x, lam = _dense_qp(lib, H, g, lo, hi, A, b)
        bu = np.concatenate([np.minimum(hi, 1e30), b])
        bl = np.concatenate([np.maximum(lo, -1e30), np.full(m, -1e30)])
        xd, _, flag, info = daqp.solve(H, g, A, bu, bl, primal_tol=1e-10)
        if flag in (1, 2):
            assert code == 0, trial
            np.testing.assert_allclose(x, xd, rtol=0, atol=1e-8)
            assert np.all(A @ x <= b + 1e-9) and np.all(x <= hi + 1e-9) and np.all(x >= lo - 1e-9)
            assert np.all(lam >= 0) and np.all(lam * (b - A @ x) <= 1e-8)
            # stationarity: H x + g + A' lam is balanced by the bounds' multipliers only
            r = H @ x + g + A.T @ lam
            free = (x < hi - 1e-9) & (x > lo + 1e-9)
            assert np.max(np.abs(r[free]), initial=0.0) <= 1e-8
            solved += 1
        elif flag == -1:
            assert code == 1, trial
            infeasible += 1
    assert solved >= 100 and infeasible >= 10


def test_the_eigen_decomposition_matches_lapack() -> None:
    lib, rng = _lib(), np.random.default_rng(1)
    for n in (1, 2, 5, 14, 30, 60):
        for kind in ("random", "repeated", "zero", "rank one"):
            M = rng.standard_normal((n, n))
            M = {
                "random": M + M.T,
                "repeated": np.diag(rng.choice([1.0, 2.0], n)),
                "zero": np.zeros((n, n)),
                "rank one": np.outer(M[0], M[0]),
            }[kind]
            w, V = np.empty(n), np.empty((n, n))
            assert lib.lfm_dense_eigh(n, M.ctypes.data, w.ctypes.data, V.ctypes.data) == 0
            scale = max(1.0, float(np.abs(M).max()))
            np.testing.assert_allclose(w, np.linalg.eigvalsh(M), rtol=0, atol=1e-13 * scale)
            np.testing.assert_allclose(V @ np.diag(w) @ V.T, M, rtol=0, atol=1e-13 * scale)
            np.testing.assert_allclose(V.T @ V, np.eye(n), rtol=0, atol=1e-13)


def test_the_c_loop_solves_a_feedback_problem_itself():
    """make_solver gives the C loop of the feedback library (no rewrite); a law for an
    open-loop problem is refused by name."""
    problem = load_config("paper").make_problem(n_scenarios=10, prediction="feedback")
    solver = make_solver(problem, "fast_c", qp_solver="elastic_ipm")
    assert isinstance(solver, CompiledScenarioSolver) and solver.loop == "c" and solver.feedback
    x0 = np.array([0.0, 0.0, 1.0, np.pi / 4])
    W = np.zeros((10, problem.horizon))
    sol = solver.solve(x0, W)
    assert sol.success and sol.law is not None and sol.extra["reference"] == "open_loop_solve"
    open_loop = make_solver(load_config("paper").make_problem(n_scenarios=10), "fast_c")
    with pytest.raises(ValueError, match="law given for a problem with prediction='open_loop'"):
        open_loop.solve(x0, W, law=sol.law)
