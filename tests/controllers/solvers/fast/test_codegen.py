"""The C library of the condensed model against its NumPy reference.

:class:`CondensedModel` evaluates the rollout, sensitivities, gradient and exact Lagrangian
Hessian either with a C library generated from the system's CasADi expressions
(``"compiled-c"``) or with NumPy (``"numpy-lanes"``, ``"casadi-vm"``). Checked here: the
backends agree to 1e-12 on the recorded paper problems and on the point mass of
``test_second_system.py``; without a working compiler the model really falls back to NumPy
(the compiler is hidden, not mocked); two processes compiling the same library at once leave
a valid library; the model and the solver pickle. The cache's checks (a damaged, foreign or
planted library, the key, failed builds) are test_codegen_cache.py's.
"""

from __future__ import annotations

import ctypes.util
import os
import pickle
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from controllers.problem import ScenarioProblem
from controllers.solvers import make_solver
from controllers.solvers.fast.codegen import build as compiled
from controllers.solvers.fast.codegen import inline as codegen_inline
from controllers.solvers.fast.codegen import source as codegen_source
from controllers.solvers.fast.codegen.build import CodegenUnavailable, forget_loaded
from controllers.solvers.fast.condensed import CondensedModel
from experiments.benchmark.problems import problem_from_config
from lfm_env.cost import QuadraticCost
from tests.controllers.solvers.recorded import DATA_DIR, load_problems
from tests.controllers.test_second_system import (
    COST,
    NS,
    STARTS,
    VARIANTS,
    N,
    point_mass,
    point_mass_model,
    sample_forces,
)

ROOT = Path(__file__).resolve().parents[4]
DATA = load_problems()
IDS = [f"seed{s}-step{k}" for s, k in zip(DATA["seed"], DATA["step"], strict=True)]
RTOL = 1e-12  # relative to the largest entry of each compared array


@pytest.fixture(scope="module")
def paper_models(paper: ScenarioProblem) -> dict[str, CondensedModel]:
    return {k: CondensedModel(paper, backend=k) for k in ("numpy", "c")}


def _layouts(problem: ScenarioProblem, x0: np.ndarray, W: np.ndarray) -> tuple:
    x0, W = problem.check_data(x0, W)
    x0T = np.ascontiguousarray(x0.T)
    W_steps = np.ascontiguousarray(W.transpose(1, 0, 2))
    W_lanes = np.ascontiguousarray(W.transpose(2, 1, 0))
    return x0, x0T, W_steps, W_lanes


def _everything(model: CondensedModel, problem, x0, W, u, mu, backoff=None) -> dict:
    """Every output of one SQP iteration of ``model`` at ``u``, with multipliers ``mu``."""
    x0, x0T, W_steps, W_lanes = _layouts(problem, x0, W)
    ro = model.evaluate(x0T, W_steps, u, model.state_cost0(x0), backoff)
    lin = model.linearise(ro, W_lanes)
    d = np.linspace(-0.1, 0.1, u.size)
    pos = np.array([[j % max(problem.ng, 1), j % problem.horizon, 3 * j] for j in range(5)])
    out = {
        "merit": np.array([ro.merit]),
        "X": ro.X,
        "G": ro.G,
        "S": lin.sensitivities(),
        "Jg": lin.constraint_jacobians(),
        "grad": lin.grad,
        "H0": model.hessian(lin, np.zeros_like(mu), W_lanes),
        "H": model.hessian(lin, mu, W_lanes),
    }
    # The C library stores no step Jacobians A (it uses each where it computes it: S
    # and the Hessians check them); the other backends do.
    assert (lin.A is None) == (model.backend == "compiled-c"), model.backend
    if lin.A is not None:
        out["A"] = lin.A
    if problem.ng:
        out["rows"] = model.rows(lin, pos)[0]
        out["linearised"] = model.linearised_values(lin, d)
    return out


def _multipliers(problem: ScenarioProblem, ns: int, seed: int) -> np.ndarray:
    """Multipliers ``(ng, N, Ns)`` on a few scenario rows, as the QP gives them."""
    rng = np.random.default_rng(seed)
    mu = np.zeros((problem.ng, problem.horizon, ns))
    if problem.ng:
        k = 12
        where = (rng.integers(0, problem.ng, k), rng.integers(0, problem.horizon, k))
        mu[where + (rng.integers(0, ns, k),)] = rng.uniform(0.0, 50.0, k)
    return mu


def _assert_same(ref: dict, got: dict) -> None:
    assert set(got) | {"A"} == set(ref) | {"A"}, (sorted(ref), sorted(got))
    for key, a in ref.items():
        if key not in got:  # A, from one backend only
            continue
        b = got[key]
        assert b.shape == a.shape, key
        scale = max(float(np.max(np.abs(a), initial=0.0)), 1e-300)
        err = float(np.max(np.abs(b - a), initial=0.0)) / scale
        assert err <= RTOL, f"{key}: relative difference {err:.2e}"


def test_the_c_library_is_used_when_a_compiler_is_there(paper_models) -> None:
    model = paper_models["c"]
    assert model.backend == "compiled-c"
    assert model.backend_error is None and model.compile_time > 0.0
    assert paper_models["numpy"].backend == "numpy-lanes"


@pytest.mark.parametrize("i", range(len(IDS)), ids=IDS)
def test_compiled_equals_numpy_on_the_recorded_problems(i, paper, paper_models) -> None:
    x0, W = DATA["x0"][i], DATA["W"][i]
    mu = _multipliers(paper, W.shape[0], i)
    backoff = None if i % 2 else np.full((paper.ng, paper.horizon, 1), 0.05)
    for u in (DATA["reference_u"][i].ravel(), DATA["u_guess"][i].ravel()):
        ref = _everything(paper_models["numpy"], paper, x0, W, u, mu, backoff)
        _assert_same(ref, _everything(paper_models["c"], paper, x0, W, u, mu, backoff))


def test_array_addresses_are_numpys_for_views_read_only_and_empty_arrays() -> None:
    base = np.arange(24.0)
    read_only = base.copy()
    read_only.setflags(write=False)
    cases = [base, base[5:], base.reshape(4, 6)[1:], read_only, np.empty(0), np.empty((3, 0))]
    for a in cases:
        assert compiled.ptr(a) == a.ctypes.data
    pos = np.arange(9, dtype=np.int64).reshape(3, 3)[1:]
    assert compiled.address(pos) == pos.ctypes.data
    with pytest.raises(ValueError, match="C-contiguous float64"):
        compiled.ptr(base[::2])
    with pytest.raises(ValueError, match="C-contiguous float64"):
        compiled.ptr(pos)


def test_a_recycled_linearisation_equals_a_fresh_one(paper, paper_models) -> None:
    """``linearise(..., recycle=old)`` writes into ``old``'s arrays, bit for bit as anew."""
    model = paper_models["c"]
    _, x0T, W_steps, W_lanes = _layouts(paper, DATA["x0"][0], DATA["W"][0])
    u_a, u_b = DATA["reference_u"][0].ravel(), DATA["u_guess"][0].ravel()
    ro_a = model.evaluate(x0T, W_steps, u_a, 0.0, None)
    ro_b = model.evaluate(x0T, W_steps, u_b, 0.0, None)
    fresh = model.linearise(ro_b, W_lanes)
    old = model.linearise(ro_a, W_lanes)
    arrays = (old.S, old.Jg)
    new = model.linearise(ro_b, W_lanes, recycle=old)
    assert new.packed and all(a is b for a, b in zip((new.S, new.Jg), arrays, strict=True))
    assert new.A is None and fresh.A is None
    for key in ("S", "Jg", "grad"):
        assert np.array_equal(getattr(new, key), getattr(fresh, key)), key
    n = paper.horizon  # packed: N (N + 1) / 2 of the N^2 input columns
    assert new.S.size * 2 * n == new.sensitivities().size * (n + 1)


def test_rollout_arrays_are_reused_only_once_nothing_refers_to_them(paper) -> None:
    """The compiled rollout takes its X and G from a pool, and an array goes back into use
    only when no rollout, view or caller holds it any more."""
    model = CondensedModel(paper, backend="c")  # (an empty pool)
    _, x0T, W_steps, _ = _layouts(paper, DATA["x0"][0], DATA["W"][0])
    u_a, u_b = DATA["reference_u"][0].ravel(), DATA["u_guess"][0].ravel()
    first = model.evaluate(x0T, W_steps, u_a, 0.0, None)
    kept_X, kept_G = first.X.copy(), first.G.copy()
    second = model.evaluate(x0T, W_steps, u_b, 0.0, None)
    assert not np.shares_memory(first.X, second.X) and not np.shares_memory(first.G, second.G)
    assert np.array_equal(first.X, kept_X) and np.array_equal(first.G, kept_G)
    # A view of X holds it; G alone free does not free the pair.
    view, address = first.X[1:], first.X.ctypes.data
    del first
    third = model.evaluate(x0T, W_steps, u_b, 0.0, None)
    assert not np.shares_memory(third.X, view) and np.array_equal(view, kept_X[1:])
    # Once nothing refers to the pair, the next rollout writes into it, with the same result
    # as into fresh arrays.
    del view
    fourth = model.evaluate(x0T, W_steps, u_a, 0.0, None)
    assert fourth.X.ctypes.data == address
    assert np.array_equal(fourth.X, kept_X) and np.array_equal(fourth.G, kept_G)
    assert np.array_equal(third.X, second.X)


@pytest.mark.parametrize("variant", sorted(VARIANTS))
def test_compiled_equals_numpy_on_the_second_system(variant) -> None:
    model = point_mass_model(point_mass(**VARIANTS[variant]))
    problem = ScenarioProblem(model, COST, horizon=N, n_scenarios=NS, slack_penalty=1.0e3)
    models = {k: CondensedModel(problem, backend=k) for k in ("numpy", "vm", "c")}
    assert models["c"].backend == "compiled-c"
    assert models["vm"].backend == "casadi-vm"
    rng = np.random.default_rng(3)
    for seed, x0 in enumerate(STARTS.values()):
        W = sample_forces(model, seed)
        u = rng.uniform(-2.0, 2.0, N * problem.nu)
        mu = _multipliers(problem, NS, seed)
        ref = _everything(models["numpy"], problem, x0, W, u, mu)
        for name in ("vm", "c"):
            _assert_same(ref, _everything(models[name], problem, x0, W, u, mu))


def test_the_c_library_stores_only_the_constraint_jacobian_entries_that_can_be_nonzero(
    paper, paper_models
) -> None:
    """Per point the C library keeps the structurally nonzero entries of ``dg/dx`` (the
    bicycle: 8 of 24); NumPy's dense Jacobians are zero everywhere else, and the packed ones
    expand to them."""
    _, x0T, W_steps, W_lanes = _layouts(paper, DATA["x0"][0], DATA["W"][0])
    lins = {}
    for name, model in paper_models.items():
        ro = model.evaluate(x0T, W_steps, DATA["u_guess"][0].ravel(), 0.0, None)
        lins[name] = model.linearise(ro, W_lanes)
    pattern = paper_models["c"].depends
    assert pattern.shape == (paper.ng, paper.nx) and pattern.sum() == 8
    packed, dense = lins["c"], lins["numpy"]
    n, ns = paper.horizon, x0T.shape[1]
    assert packed.Jg.shape == (n, ns, 8) and dense.Jg.shape == (n, ns, paper.ng, paper.nx)
    assert not np.any(dense.Jg[:, :, ~pattern])
    assert np.all(np.any(dense.Jg[:, :, pattern] != 0.0, axis=(0, 1)))  # each entry is used
    full = packed.constraint_jacobians()
    assert np.allclose(full, dense.Jg, rtol=0.0, atol=RTOL * np.abs(dense.Jg).max())
    assert not np.any(full[:, :, ~pattern])


def test_compiled_equals_numpy_with_coupled_state_weights() -> None:
    """The C library skips the zeros of diagonal state weights; a full ``Q`` (with a diagonal
    ``Qf``: every step's matrix counts) takes the general path, equal to NumPy's."""
    model = point_mass_model(point_mass(**VARIANTS[sorted(VARIANTS)[0]]))
    q = np.diag([1.0, 1.0, 0.1, 0.1])
    q[0, 2] = q[2, 0] = 0.2  # position and velocity coupled (still positive definite)
    cost = QuadraticCost(Q=q, Qf=COST.Qf, R=COST.R, x_goal=COST.x_goal)
    assert not cost.diagonal
    problem = ScenarioProblem(model, cost, horizon=N, n_scenarios=NS, slack_penalty=1.0e3)
    models = {k: CondensedModel(problem, backend=k) for k in ("numpy", "c")}
    assert models["c"].backend == "compiled-c"
    x0 = next(iter(STARTS.values()))
    W = sample_forces(model, 0)
    u = np.random.default_rng(4).uniform(-2.0, 2.0, N * problem.nu)
    mu = _multipliers(problem, NS, 0)
    ref = _everything(models["numpy"], problem, x0, W, u, mu)
    _assert_same(ref, _everything(models["c"], problem, x0, W, u, mu))


# ----------------------------------------------------------------------------- fallback


@pytest.fixture
def fresh_cache(tmp_path, monkeypatch) -> Path:
    """An empty C library cache, and no library loaded in this process (restored after)."""
    monkeypatch.setenv("LFM_CACHE_DIR", str(tmp_path / "cache"))
    forget_loaded()
    yield tmp_path / "cache"
    forget_loaded()


@pytest.mark.parametrize("hide", ["missing_cc", "failing_cc", "empty_path"])
def test_without_a_compiler_the_model_falls_back_to_numpy(
    hide, paper, paper_models, fresh_cache, tmp_path, monkeypatch
) -> None:
    if hide == "missing_cc":
        monkeypatch.setenv("CC", str(tmp_path / "no-such-compiler"))
    elif hide == "failing_cc":  # a real program that fails on every input
        monkeypatch.setenv("CC", "false")
    else:
        monkeypatch.delenv("CC", raising=False)
        monkeypatch.setenv("PATH", str(tmp_path))  # neither cc nor gcc on it
    model = CondensedModel(paper)
    assert model.backend == "numpy-lanes"
    assert "compil" in model.backend_error
    assert not list(fresh_cache.glob("*.so"))
    i = 2
    mu = _multipliers(paper, 150, i)
    u = DATA["reference_u"][i].ravel()
    ref = _everything(paper_models["c"], paper, DATA["x0"][i], DATA["W"][i], u, mu)
    _assert_same(ref, _everything(model, paper, DATA["x0"][i], DATA["W"][i], u, mu))
    with pytest.raises(CodegenUnavailable, match="compil"):
        CondensedModel(paper, backend="c")


def test_an_unknown_backend_is_named(paper, monkeypatch) -> None:
    with pytest.raises(ValueError, match="backend='fortran'"):
        CondensedModel(paper, backend="fortran")
    monkeypatch.setenv("LFM_BACKEND", "gpu")
    with pytest.raises(ValueError, match=r"\$LFM_BACKEND='gpu'.*one of"):
        CondensedModel(paper)
    monkeypatch.setenv("LFM_BACKEND", "numpy")
    assert CondensedModel(paper).backend == "numpy-lanes"


# ----------------------------------------------------------------------------- cache


def test_a_fresh_cache_compiles_anew_and_leaves_the_real_one(paper, paper_models) -> None:
    """Inside ``compiled.fresh_cache()`` the C library is compiled again into a temporary
    directory (the benchmark's cold first build); afterwards the configured cache and the
    libraries loaded before are back, and a solver built inside still solves."""
    before = compiled.cache_dir()
    assert CondensedModel(paper).cache_hit  # loaded in this process (paper_models)
    with compiled.fresh_cache() as tmp:
        assert compiled.cache_dir() == tmp
        model = CondensedModel(paper, backend="c")
        assert not model.cache_hit and model.compile_time > 0
        assert len(list(tmp.glob("lfm_codegen_*.so"))) == 1
        solver = make_solver(paper, "fast")
    assert compiled.cache_dir() == before and not tmp.exists()
    assert CondensedModel(paper).cache_hit
    x0, W = DATA["x0"][0], DATA["W"][0]
    sol = solver.solve(x0, W, u_guess=DATA["reference_u"][0])
    reference = make_solver(paper, "fast").solve(x0, W, u_guess=DATA["reference_u"][0])
    assert sol.success and sol.extra["backend"] == "compiled-c"
    np.testing.assert_array_equal(sol.u, reference.u)


_BUILD = """
import sys
import numpy as np
from controllers.solvers.fast.condensed import CondensedModel
from experiments.benchmark.problems import problem_from_config
data = dict(np.load(sys.argv[1]))
p = problem_from_config(n_scenarios=150)
m = CondensedModel(p, backend="c")
x0, W = p.check_data(data["x0"][0], data["W"][0])
ro = m.evaluate(np.ascontiguousarray(x0.T), np.ascontiguousarray(W.transpose(1, 0, 2)),
                data["reference_u"][0].ravel(), m.state_cost0(x0))
lin = m.linearise(ro, np.ascontiguousarray(W.transpose(2, 1, 0)))
H = m.hessian(lin, np.zeros((p.ng, p.horizon, 150)), np.ascontiguousarray(W.transpose(2, 1, 0)))
print(m.backend, m.cache_hit, repr(float(ro.merit)), repr(float(np.abs(H).sum())))
"""


def test_two_processes_compiling_at_once_leave_a_valid_library(paper, paper_models, tmp_path):
    env = {**os.environ, "LFM_CACHE_DIR": str(tmp_path / "cache"), "PYTHONPATH": str(ROOT)}
    env.pop("LFM_BACKEND", None)
    cmd = [sys.executable, "-c", _BUILD, str(DATA_DIR / "recorded_problems.npz")]
    procs = [
        subprocess.Popen(cmd, env=env, cwd=ROOT, stdout=subprocess.PIPE, text=True)
        for _ in range(2)
    ]
    outputs = [p.communicate(timeout=600)[0].split() for p in procs]
    assert all(p.returncode == 0 for p in procs)
    x0, x0T, W_steps, W_lanes = _layouts(paper, DATA["x0"][0], DATA["W"][0])
    m = paper_models["numpy"]
    ro = m.evaluate(x0T, W_steps, DATA["reference_u"][0].ravel(), m.state_cost0(x0))
    H = m.hessian(m.linearise(ro, W_lanes), np.zeros((paper.ng, paper.horizon, 150)), W_lanes)
    for backend, _, merit, h_sum in outputs:
        assert backend == "compiled-c"
        assert float(merit) == pytest.approx(ro.merit, rel=RTOL)
        assert float(h_sum) == pytest.approx(float(np.abs(H).sum()), rel=1e-12)
    files = sorted(p.name for p in (tmp_path / "cache").iterdir())
    assert len([f for f in files if f.endswith(".so")]) == 1, files  # no temporary left
    third = subprocess.run(cmd, env=env, cwd=ROOT, capture_output=True, text=True, check=True)
    assert third.stdout.split()[:2] == ["compiled-c", "True"]  # loads what they left


# ----------------------------------------------------------------------------- pickling


def test_the_model_and_the_solver_pickle_with_their_c_library(paper, paper_models) -> None:
    model = pickle.loads(pickle.dumps(paper_models["c"]))
    assert model.backend == "compiled-c" and model.cache_hit
    i = 4
    mu = _multipliers(paper, 150, i)
    u = DATA["reference_u"][i].ravel()
    ref = _everything(paper_models["c"], paper, DATA["x0"][i], DATA["W"][i], u, mu)
    _assert_same(ref, _everything(model, paper, DATA["x0"][i], DATA["W"][i], u, mu))
    solver = pickle.loads(pickle.dumps(make_solver(paper, "fast")))
    sol = solver.solve(DATA["x0"][i], DATA["W"][i], u_guess=DATA["u_guess"][i])
    assert sol.extra["backend"] == "compiled-c"


def test_the_fast_solver_reaches_the_same_plan_with_either_backend(paper, monkeypatch) -> None:
    plans = {}
    for backend in ("numpy", "c"):
        monkeypatch.setenv("LFM_BACKEND", backend)
        solver = make_solver(paper, "fast")
        plans[backend] = [
            solver.solve(DATA["x0"][i], DATA["W"][i], u_guess=DATA["u_guess"][i])
            for i in range(0, len(IDS), 3)
        ]
    assert {s.extra["backend"] for s in plans["c"]} == {"compiled-c"}
    for a, b in zip(plans["numpy"], plans["c"], strict=True):
        assert b.status == a.status
        assert b.objective == pytest.approx(a.objective, rel=1e-9)
        np.testing.assert_allclose(b.u, a.u, atol=1e-6)


@pytest.mark.parametrize("horizon", [1, 2, 15, 30])
def test_the_compiled_hessian_equals_numpys_at_every_horizon(horizon) -> None:
    """The C library's Hessian (a backward recursion per scenario) against the NumPy reference
    (sum_j S_j' Mxx_j S_j and the cross terms) from one step (no off-diagonal blocks) to
    N = 30, with multipliers on scenario rows and inputs that drive the car hard."""
    problem = problem_from_config(horizon=horizon, n_scenarios=40)
    models = {k: CondensedModel(problem, backend=k) for k in ("numpy", "c")}
    rng = np.random.default_rng(horizon)
    x0 = DATA["x0"][0]
    W = DATA["W"][0][:40, :1].repeat(horizon, axis=1) * rng.uniform(0.5, 1.5, (40, horizon, 1))
    u = rng.uniform(problem.input_lower, problem.input_upper, (horizon, problem.nu)).ravel()
    mu = _multipliers(problem, 40, horizon)
    ref = _everything(models["numpy"], problem, x0, W, u, mu)
    _assert_same(ref, _everything(models["c"], problem, x0, W, u, mu))


# --------------------------------------------------------------------------- threads


@pytest.mark.parametrize("threads", [2, 3, 200])
def test_threaded_chunks_equal_the_serial_sweep(threads, paper, paper_models) -> None:
    """The scenarios in 2, 3 (uneven) or more chunks than scenarios (one each): every output
    equals the serial C library's to rounding."""
    model = CondensedModel(paper, backend="c")
    assert model.openmp  # the test machines' compilers have OpenMP
    model.threads = threads
    for i in (0, 5):
        x0, W = DATA["x0"][i], DATA["W"][i]
        mu = _multipliers(paper, W.shape[0], i)
        u = DATA["reference_u"][i].ravel()
        ref = _everything(paper_models["c"], paper, x0, W, u, mu)
        _assert_same(ref, _everything(model, paper, x0, W, u, mu))


def test_without_openmp_the_chunks_run_one_after_another(
    paper, paper_models, fresh_cache, tmp_path, monkeypatch
) -> None:
    """A compiler that refuses -fopenmp (a real cc behind a script) still builds the C library,
    without threads; more chunks than one give the same outputs."""
    cc = tmp_path / "cc-without-openmp"
    cc.write_text(
        '#!/bin/sh\nfor a in "$@"; do [ "$a" = -fopenmp ] && exit 1; done\nexec cc "$@"\n'
    )
    cc.chmod(0o755)
    monkeypatch.setenv("CC", str(cc))
    model = CondensedModel(paper, backend="c")
    assert model.backend == "compiled-c" and not model.openmp
    model.threads = 3
    i = 1
    x0, W, u = DATA["x0"][i], DATA["W"][i], DATA["reference_u"][i].ravel()
    mu = _multipliers(paper, W.shape[0], i)
    ref = _everything(paper_models["c"], paper, x0, W, u, mu)
    _assert_same(ref, _everything(model, paper, x0, W, u, mu))
    solver = make_solver(paper, "fast", threads=2)
    assert solver.solve(x0, W).extra["threads"] == 1  # (this process's C library now)


def test_the_fast_solver_with_threads_reaches_the_same_plan(paper) -> None:
    i = 3
    x0, W = DATA["x0"][i], DATA["W"][i]
    one = make_solver(paper, "fast").solve(x0, W)
    two = make_solver(paper, "fast", threads=2).solve(x0, W)
    assert one.extra["threads"] == 1 and two.extra["threads"] == 2
    assert two.objective == pytest.approx(one.objective, rel=1e-9)
    np.testing.assert_allclose(two.u, one.u, atol=1e-6)
    clone = pickle.loads(pickle.dumps(make_solver(paper, "fast", threads=2)))
    assert clone.condensed.threads == 2


# --------------------------------------------------------------------------- vectorised rollout


def test_the_rollout_is_vectorised_with_vector_math_where_glibc_has_it(paper_models) -> None:
    """The bicycle's step (and the Hessian's recursion step) are inlined into the scenario
    loops; with glibc's libmvec on the machine (as on the test machines) their sines and
    cosines are the vector ones."""
    model = paper_models["c"]
    expected = 2 if ctypes.util.find_library("mvec") else 1
    assert model.vector_math == expected
    source = codegen_source.library_source(model.problem.system, model.problem.dt)
    assert "lfm_vsin(" in source and "lfm_vcos(" in source  # the inlined body's names


def test_without_libmvec_the_rollout_is_vectorisable_and_the_same(
    paper, paper_models, fresh_cache, tmp_path, monkeypatch
) -> None:
    """A system without libmvec (a real cc behind a script that refuses -lmvec) still builds
    the C library with the inlined rollout and plain math; every output equals the reference."""
    cc = tmp_path / "cc-without-libmvec"
    cc.write_text('#!/bin/sh\nfor a in "$@"; do [ "$a" = -lmvec ] && exit 1; done\nexec cc "$@"\n')
    cc.chmod(0o755)
    monkeypatch.setenv("CC", str(cc))
    model = CondensedModel(paper, backend="c")
    assert model.backend == "compiled-c" and model.vector_math == 1
    for i in (0, 4):
        x0, W, u = DATA["x0"][i], DATA["W"][i], DATA["reference_u"][i].ravel()
        mu = _multipliers(paper, W.shape[0], i)
        ref = _everything(paper_models["numpy"], paper, x0, W, u, mu)
        _assert_same(ref, _everything(model, paper, x0, W, u, mu))


def test_the_baseline_version_of_the_vectorised_rollout_is_the_same(
    paper, paper_models, fresh_cache, tmp_path, monkeypatch
) -> None:
    """The vectorised rollout also has an x86-64-v3 (AVX2, FMA) version that the CPU picks
    at load time where it can (the test machines): built without it (-DLFM_NO_CLONES, a real
    cc behind a script), the baseline version's outputs equal the reference too."""
    cc = tmp_path / "cc-without-clones"
    cc.write_text('#!/bin/sh\nexec cc -DLFM_NO_CLONES "$@"\n')
    cc.chmod(0o755)
    monkeypatch.setenv("CC", str(cc))
    model = CondensedModel(paper, backend="c")
    assert model.backend == "compiled-c" and model.vector_math >= 1
    for i in (1, 3):
        x0, W, u = DATA["x0"][i], DATA["W"][i], DATA["reference_u"][i].ravel()
        mu = _multipliers(paper, W.shape[0], i)
        ref = _everything(paper_models["numpy"], paper, x0, W, u, mu)
        _assert_same(ref, _everything(model, paper, x0, W, u, mu))


INLINERS = ("inline_step", "inline_step_curv", "inline_step_jac", "inline_con_jac")


@pytest.mark.parametrize("refused", [*INLINERS, "all"])
def test_a_step_that_cannot_be_inlined_keeps_the_call_per_scenario(
    refused, paper, paper_models, fresh_cache, monkeypatch
) -> None:
    """When the rewrite of a generated point function fails (codegen_inline.NotInlinable),
    the C library calls it once per scenario (the rollout's step, the Hessian's recursion step,
    the linearisation's step or constraint Jacobian, or all), with the same outputs."""

    def refuse(*_args, **_kwargs):
        raise codegen_inline.NotInlinable("refused by the test")

    names = list(INLINERS) if refused == "all" else [refused]
    for name in names:
        monkeypatch.setattr(codegen_source, name, refuse)
    source = codegen_source.library_source(paper.system, paper.dt)
    for name in INLINERS:
        define = "#define LFM_" + name.removeprefix("inline_").upper() + "_INLINE"
        assert (define in source) == (name not in names), define
    model = CondensedModel(paper, backend="c")
    assert model.backend == "compiled-c"
    assert (model.vector_math == 0) == (refused == "all")
    i = 2
    x0, W, u = DATA["x0"][i], DATA["W"][i], DATA["reference_u"][i].ravel()
    mu = _multipliers(paper, W.shape[0], i)
    ref = _everything(paper_models["numpy"], paper, x0, W, u, mu)
    _assert_same(ref, _everything(model, paper, x0, W, u, mu))


def test_the_inline_rewrite_reads_and_writes_plain_strided_pointers(paper) -> None:
    """The rewritten step has no pointer-array access left and renames the vector-math
    functions; a function of another shape is refused."""
    fns = codegen_source.pointwise_functions(paper.system, paper.dt)
    code = codegen_source.library_source(paper.system, paper.dt)
    step = next(f for f in fns if f.name() == "lfm_step")
    text = codegen_inline.inline_step(code, step, paper.system.nx)
    assert "arg[" not in text and "res[" not in text and "return" not in text
    assert "lfm_vsin(" in text and " sin(" not in text
    nx, ng = paper.system.nx, paper.system.ng
    assert all(f"xo_[{j}*xs]=" in text for j in range(nx))
    assert all(f"go_[{j}*gs]=" in text for j in range(ng))
    curv = next(f for f in fns if f.name() == "lfm_step_curv")  # six inputs
    with pytest.raises(codegen_inline.NotInlinable, match="4 inputs"):
        codegen_inline.inline_step(code, curv, nx)
    text = codegen_inline.inline_step_curv(code, curv)
    assert "arg[" not in text and "res[" not in text and "l_[0*bs]" in text
    jac = next(f for f in fns if f.name() == "lfm_step_jac")
    text = codegen_inline.inline_step_jac(code, jac)
    assert all(f"o_[{j}*bs]=" in text for j in range(nx * (nx + paper.system.nu)))
    con = next(f for f in fns if f.name() == "lfm_con_jac")
    text = codegen_inline.inline_con_jac(code, con)
    assert "arg[" not in text and all(f"o_[{j}*bs]=" in text for j in range(ng * nx))
    with pytest.raises(codegen_inline.NotInlinable, match="1 inputs"):
        codegen_inline.inline_con_jac(code, jac)
