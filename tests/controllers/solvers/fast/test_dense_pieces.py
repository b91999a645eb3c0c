"""The compiled loop's dense pieces (``codegen/c/dense.c``) at the sizes of long horizons.

The dual active-set QP and the eigen-decomposition work on ``N nu`` inputs: 60 at N = 30, 100
at N = 50. Their loops run four independent sums side by side and keep the QP's ``J`` and the
eigenvectors transposed (the blocked and the remainder paths are taken at every size below),
each sum in the order of the plain loop, and are cloned for x86-64-v3 without fused
multiply-adds: the baseline build (``-DLFM_NO_CLONES``) rounds exactly as the running one.
"""

from __future__ import annotations

import ctypes

import numpy as np
import pytest

from controllers.solvers.fast.codegen.build import forget_loaded
from controllers.solvers.fast.compiled import sqp_library
from experiments.benchmark.problems import problem_from_config


def _lib():
    problem = problem_from_config(n_scenarios=2)
    lib = sqp_library(problem.system, problem.dt)
    P, L = ctypes.c_void_p, ctypes.c_long
    lib.lfm_dense_qp.argtypes = [L, L, P, P, P, P, P, P, ctypes.c_double, L, P, P, P]
    lib.lfm_dense_qp.restype = ctypes.c_int
    lib.lfm_dense_eigh.argtypes = [L, P, P, P]
    lib.lfm_dense_eigh.restype = ctypes.c_int
    return lib


def _qp(rng: np.random.Generator, n: int, m: int):
    """A QP shaped like the SQP's: H with eigenvalues over six decades, causal rows (row i
    zero beyond a width, as the inputs' sensitivities), bounds and rows that bind; x = 0 is
    feasible."""
    Q, _ = np.linalg.qr(rng.standard_normal((n, n)))
    H = (Q * np.logspace(-3, 3, n)) @ Q.T
    H = 0.5 * (H + H.T)
    g = rng.standard_normal(n) * 10
    lo, hi = -rng.uniform(0.2, 1, n), rng.uniform(0.2, 1, n)
    A = rng.standard_normal((m, n))
    for i in range(m):
        A[i, int(rng.integers(1, n + 1)) :] = 0.0
    b = rng.uniform(0.01, 1.0, m)
    return H, g, lo, hi, A, b


def _solve(lib, H, g, lo, hi, A, b):
    n, m = g.size, b.size
    x, lam, steps = np.zeros(n), np.zeros(m), np.zeros(1, dtype=np.int64)
    arrays = [np.ascontiguousarray(a, dtype=float) for a in (H, g, lo, hi, A, b)]
    code = lib.lfm_dense_qp(
        n, m, *(a.ctypes.data for a in arrays), 1e-10, 50 * (n + m) + 100, x.ctypes.data,
        lam.ctypes.data, steps.ctypes.data,
    )  # fmt: skip
    return code, x, lam


def _eigh(lib, M):
    n = M.shape[0]
    w, V = np.zeros(n), np.zeros((n, n))
    M = np.ascontiguousarray(M)
    assert lib.lfm_dense_eigh(n, M.ctypes.data, w.ctypes.data, V.ctypes.data) == 0
    return w, V


def _outputs(lib) -> list[np.ndarray]:
    """The QP's and the eigen-decomposition's outputs on fixed problems of 5 to 101 inputs."""
    rng, out = np.random.default_rng(11), []
    for n in (5, 30, 61, 101):
        for m in (0, 7, 2 * n):
            code, x, lam = _solve(lib, *_qp(rng, n, m))
            out += [np.array([code]), x, lam]
        M = rng.standard_normal((n, n))
        out += list(_eigh(lib, M + M.T))
    return out


@pytest.mark.parametrize("n", [30, 61, 100])
def test_the_dense_qp_solves_long_horizon_sized_qps_as_daqp(n: int) -> None:
    """The dense QP against DAQP on QPs of a long horizon's size: the same step, and the KKT
    conditions of its multipliers."""
    daqp = pytest.importorskip("daqp")
    lib, rng = _lib(), np.random.default_rng(n)
    solved = active = 0
    for _ in range(8):
        H, g, lo, hi, A, b = _qp(rng, n, int(rng.integers(n // 2, 2 * n)))
        code, x, lam = _solve(lib, H, g, lo, hi, A, b)
        bu = np.concatenate([hi, b])
        bl = np.concatenate([lo, np.full(b.size, -1e30)])
        xd, _, flag, _ = daqp.solve(H, g, A, bu, bl, primal_tol=1e-10)
        assert flag in (1, 2)
        assert code == 0
        scale = max(1.0, float(np.max(np.abs(xd))))
        np.testing.assert_allclose(x, xd, rtol=0, atol=1e-7 * scale)
        assert np.all(A @ x <= b + 1e-8) and np.all(x <= hi + 1e-9) and np.all(x >= lo - 1e-9)
        assert np.all(lam >= 0) and np.all(lam * (b - A @ x) <= 1e-6)
        active += int(np.sum(lam > 0)) + int(np.sum((x <= lo + 1e-9) | (x >= hi - 1e-9)))
        solved += 1
    assert solved == 8 and active >= 8 * n // 4  # (binding rows and bounds)


def test_the_eigen_decomposition_of_a_long_horizons_hessian_matches_lapack() -> None:
    lib, rng = _lib(), np.random.default_rng(5)
    for n in (61, 100):
        Q, _ = np.linalg.qr(rng.standard_normal((n, n)))
        M = (Q * np.concatenate([-np.logspace(0, 2, 5), np.logspace(-3, 6, n - 5)])) @ Q.T
        M = 0.5 * (M + M.T)
        w, V = _eigh(lib, M)
        scale = float(np.max(np.abs(M)))
        np.testing.assert_allclose(w, np.linalg.eigvalsh(M), rtol=0, atol=1e-12 * scale)
        np.testing.assert_allclose(V @ np.diag(w) @ V.T, M, rtol=0, atol=1e-12 * scale)
        np.testing.assert_allclose(V.T @ V, np.eye(n), rtol=0, atol=1e-12)


def test_the_baseline_build_of_the_dense_pieces_rounds_as_the_running_one(
    tmp_path, monkeypatch
) -> None:
    """Built without the x86-64-v3 clones (-DLFM_NO_CLONES, a real cc behind a script), the
    QP and the eigen-decomposition give bitwise the outputs of the build the CPU picked (on
    an AVX2 machine: its clone, which must not fuse a product into a sum)."""
    running = _outputs(_lib())
    cc = tmp_path / "cc-without-clones"
    cc.write_text('#!/bin/sh\nexec cc -DLFM_NO_CLONES "$@"\n')
    cc.chmod(0o755)
    monkeypatch.setenv("CC", str(cc))
    monkeypatch.setenv("LFM_CACHE_DIR", str(tmp_path / "cache"))
    forget_loaded()
    try:
        baseline = _outputs(_lib())
    finally:
        forget_loaded()
    assert len(baseline) == len(running)
    for a, b in zip(running, baseline, strict=True):
        np.testing.assert_array_equal(a, b)
