"""Tests of the state-space GP kernels in ``lfm_env.gp``."""

from __future__ import annotations

import math

import numpy as np
import pytest
import scipy.linalg
import scipy.special
from hypothesis import given, settings
from hypothesis import strategies as st

from lfm_env.gp import Matern, StateSpaceKernel, matern

# Paper / REFERENCE.md values: nu = 5/2, sigma^2 = 4 [(m/s^2)^2], l = 4 [s].
PAPER_NU, PAPER_VAR, PAPER_LS = 2.5, 4.0, 4.0


def bessel_matern(nu: float, variance: float, lengthscale: float, tau: np.ndarray) -> np.ndarray:
    """Matern covariance from its general Bessel form, independent of the module."""
    x = math.sqrt(2.0 * nu) * np.abs(np.asarray(tau, dtype=float)) / lengthscale
    out = np.full_like(x, variance)
    pos = x > 0
    out[pos] = (
        variance
        * 2.0 ** (1.0 - nu)
        / scipy.special.gamma(nu)
        * x[pos] ** nu
        * scipy.special.kv(nu, x[pos])
    )
    return out


def state_space_cov(kernel: StateSpaceKernel, tau: np.ndarray) -> np.ndarray:
    """``H expm(F tau) Pinf H^T`` for tau >= 0, computed here rather than by the module."""
    return np.array(
        [(kernel.H @ scipy.linalg.expm(kernel.F * t) @ kernel.Pinf @ kernel.H.T)[0, 0] for t in tau]
    )


# ----------------------------------------------------------------------------- matrices


def test_paper_kernel_matrices_match_reference():
    k = matern(PAPER_NU, PAPER_VAR, PAPER_LS)
    lam = math.sqrt(5.0) / PAPER_LS
    np.testing.assert_allclose(
        k.F, [[0, 1, 0], [0, 0, 1], [-(lam**3), -3 * lam**2, -3 * lam]], rtol=1e-14
    )
    np.testing.assert_array_equal(k.L, [[0.0], [0.0], [1.0]])
    np.testing.assert_array_equal(k.H, [[1.0, 0.0, 0.0]])
    np.testing.assert_allclose(k.Qc, [[16.0 / 3.0 * PAPER_VAR * lam**5]], rtol=1e-13)
    kk = 5.0 * PAPER_VAR / (3.0 * PAPER_LS**2)
    expected = np.array([[PAPER_VAR, 0, -kk], [0, kk, 0], [-kk, 0, 25 * PAPER_VAR / PAPER_LS**4]])
    np.testing.assert_allclose(k.Pinf, expected, rtol=1e-12, atol=1e-14)
    assert k.state_dim == 3
    assert (k.nu, k.variance, k.lengthscale) == (2.5, 4.0, 4.0)


@pytest.mark.parametrize("variance, lengthscale", [(1.0, 1.0), (0.3, 7.0), (50.0, 0.05)])
def test_nu_5_2_pinf_closed_form(variance, lengthscale):
    k = matern(2.5, variance, lengthscale)
    kk = 5.0 * variance / (3.0 * lengthscale**2)
    expected = np.array([[variance, 0, -kk], [0, kk, 0], [-kk, 0, 25 * variance / lengthscale**4]])
    np.testing.assert_allclose(k.Pinf, expected, rtol=1e-12, atol=1e-14 * np.abs(expected).max())


@pytest.mark.parametrize("variance, lengthscale", [(1.0, 1.0), (2.5, 0.3), (0.1, 12.0)])
def test_spectral_density_formula(variance, lengthscale):
    lam_half = 1.0 / lengthscale
    assert matern(0.5, variance, lengthscale).Qc[0, 0] == pytest.approx(
        2.0 * variance * lam_half, rel=1e-14
    )
    lam_52 = math.sqrt(5.0) / lengthscale
    assert matern(2.5, variance, lengthscale).Qc[0, 0] == pytest.approx(
        16.0 / 3.0 * variance * lam_52**5, rel=1e-13
    )


def test_companion_last_row_is_binomial():
    lam = math.sqrt(7.0) / 2.0
    k = matern(3.5, 1.0, 2.0)
    np.testing.assert_allclose(k.F[-1], [-(lam**4), -4 * lam**3, -6 * lam**2, -4 * lam], rtol=1e-14)
    np.testing.assert_array_equal(k.F[:-1], np.eye(4)[1:])


# ---------------------------------------------------------------------------- covariance


@pytest.mark.parametrize("nu", [0.5, 1.5, 2.5])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_state_space_covariance_matches_bessel_form(nu, seed):
    rng = np.random.default_rng(seed)
    variance = float(10.0 ** rng.uniform(-2, 2))
    lengthscale = float(10.0 ** rng.uniform(-1.5, 1.5))
    k = matern(nu, variance, lengthscale)
    tau = np.linspace(0.0, 5.0 * lengthscale, 101)
    reference = bessel_matern(nu, variance, lengthscale, tau)
    np.testing.assert_allclose(state_space_cov(k, tau), reference, rtol=0, atol=1e-9 * variance)
    np.testing.assert_allclose(k.covariance(tau), reference, rtol=0, atol=1e-12 * variance)


@pytest.mark.parametrize("nu", [3.5, 4.5])
def test_higher_order_covariance_matches_bessel_form(nu):
    k = matern(nu, 2.0, 1.5)
    tau = np.linspace(0.0, 7.5, 61)
    reference = bessel_matern(nu, 2.0, 1.5, tau)
    np.testing.assert_allclose(state_space_cov(k, tau), reference, rtol=0, atol=1e-9 * 2.0)
    np.testing.assert_allclose(k.covariance(tau), reference, rtol=0, atol=1e-12 * 2.0)


def test_covariance_is_symmetric_in_lag_and_keeps_shape():
    k = matern(PAPER_NU, PAPER_VAR, PAPER_LS)
    tau = np.linspace(-10.0, 10.0, 21).reshape(3, 7)
    np.testing.assert_array_equal(k.covariance(tau), k.covariance(-tau))
    assert k.covariance(tau).shape == (3, 7)
    assert k.covariance(0.0) == pytest.approx(PAPER_VAR, rel=1e-15)


def test_base_class_generic_covariance_matches_closed_form():
    m = matern(1.5, 3.0, 2.0)
    base = StateSpaceKernel(m.F, m.L, m.Qc, m.H)  # Pinf from the generic Lyapunov solve
    np.testing.assert_allclose(base.Pinf, m.Pinf, rtol=1e-10, atol=1e-12)
    tau = np.array([-3.0, 0.0, 0.5, 4.0])
    np.testing.assert_allclose(base.covariance(tau), m.covariance(tau), rtol=0, atol=1e-10)
    assert base.stationary_variance == pytest.approx(3.0, rel=1e-12)


# -------------------------------------------------------------------------- discretisation


@pytest.mark.parametrize("nu", [0.5, 1.5, 2.5, 3.5])
@pytest.mark.parametrize("dt", [1e-3, 0.2, 3.0])
def test_exact_discretisation_keeps_stationarity(nu, dt):
    k = matern(nu, PAPER_VAR, PAPER_LS)
    A, Q = k.discretize(dt)
    np.testing.assert_allclose(A, scipy.linalg.expm(k.F * dt), rtol=1e-14, atol=1e-15)
    np.testing.assert_allclose(A @ k.Pinf @ A.T + Q, k.Pinf, rtol=0, atol=1e-12 * PAPER_VAR)
    np.testing.assert_array_equal(Q, Q.T)
    assert np.linalg.eigvalsh(Q).min() > -1e-12 * PAPER_VAR


def test_euler_maruyama_form():
    k = matern(PAPER_NU, PAPER_VAR, PAPER_LS)
    A, Q = k.discretize(0.2, method="euler_maruyama")
    np.testing.assert_allclose(A, np.eye(3) + k.F * 0.2, rtol=1e-15)
    np.testing.assert_allclose(Q, k.L @ k.Qc @ k.L.T * 0.2, rtol=1e-15)
    assert np.linalg.matrix_rank(Q) == 1


def test_euler_maruyama_stationary_variance_is_about_4_25():
    # REFERENCE.md: the code's Euler-Maruyama step inflates the variance to ~4.25 at dt=0.2.
    k = matern(PAPER_NU, PAPER_VAR, PAPER_LS)
    A, Q = k.discretize(0.2, method="euler_maruyama")
    P = scipy.linalg.solve_discrete_lyapunov(A, Q)
    em_var = (k.H @ P @ k.H.T)[0, 0]
    assert abs(em_var - 4.25) < 0.1
    assert em_var > PAPER_VAR + 0.2  # a real inflation, not rounding


def test_discretize_returns_writable_copies():
    k = matern(PAPER_NU, PAPER_VAR, PAPER_LS)
    A, Q = k.discretize(0.2)
    A[0, 0] = 123.0  # must not raise nor touch the kernel
    assert k.F[0, 0] == 0.0


# ------------------------------------------------------------------------------ sampling


def test_sample_path_statistics_match_kernel():
    k = matern(PAPER_NU, PAPER_VAR, PAPER_LS)
    dt, n_paths = 0.2, 4000
    paths = k.sample_path(50, dt, np.random.default_rng(12345), n_paths=n_paths)
    assert paths.shape == (n_paths, 51, 3)
    w = paths @ k.H[0]
    se_var = PAPER_VAR * math.sqrt(2.0 / (n_paths - 1))
    for step in (0, 25, 50):
        assert abs(w[:, step].var(ddof=1) - PAPER_VAR) < 5.0 * se_var
    # lag 1 s = 5 steps; standard error of a correlation estimate ~ (1 - rho^2) / sqrt(n)
    rho = k.covariance(1.0) / PAPER_VAR
    se_rho = (1.0 - rho**2) / math.sqrt(n_paths)
    for step in (0, 20, 45):
        est = np.corrcoef(w[:, step], w[:, step + 5])[0, 1]
        assert abs(est - rho) < 5.0 * se_rho
    # full state covariance at one time also matches Pinf (entry-wise ~5 standard errors)
    emp = np.cov(paths[:, 30, :].T)
    se = np.sqrt((k.Pinf**2 + np.outer(np.diag(k.Pinf), np.diag(k.Pinf))) / n_paths)
    assert np.all(np.abs(emp - k.Pinf) < 5.0 * se)


@pytest.mark.parametrize("method", ["exact", "euler_maruyama"])
def test_zero_start_variance_follows_discrete_recursion(method):
    k = matern(PAPER_NU, PAPER_VAR, PAPER_LS)
    dt, n_paths, n_steps = 0.2, 4000, 40
    paths = k.sample_path(
        n_steps, dt, np.random.default_rng(7), start="zero", method=method, n_paths=n_paths
    )
    np.testing.assert_array_equal(paths[:, 0], 0.0)
    A, Q = k.discretize(dt, method)
    P = np.zeros((3, 3))
    for step in range(1, n_steps + 1):
        P = A @ P @ A.T + Q
        if step in (5, 20, 40):
            var = P[0, 0]
            assert abs(paths[:, step, 0].var(ddof=1) - var) < 5.0 * var * math.sqrt(2.0 / n_paths)


def test_sample_path_single_shape_and_reproducibility():
    k = matern(PAPER_NU, PAPER_VAR, PAPER_LS)
    a = k.sample_path(30, 0.1, np.random.default_rng(3))
    b = k.sample_path(30, 0.1, np.random.default_rng(3))
    c = k.sample_path(30, 0.1, np.random.default_rng(4))
    assert a.shape == (31, 3)
    np.testing.assert_array_equal(a, b)
    assert not np.allclose(a, c)
    z0 = k.sample_path(0, 0.1, np.random.default_rng(3), start="zero")
    np.testing.assert_array_equal(z0, np.zeros((1, 3)))


def test_sample_path_does_not_use_global_numpy_state():
    k = matern(1.5, 1.0, 1.0)
    np.random.seed(0)
    before = np.random.get_state()[1].copy()
    k.sample_path(10, 0.1, np.random.default_rng(0), n_paths=3)
    np.testing.assert_array_equal(np.random.get_state()[1], before)


# -------------------------------------------------------------------------------- errors


@pytest.mark.parametrize("field", ["variance", "lengthscale"])
@pytest.mark.parametrize("bad", [0.0, -1.0, float("nan"), float("inf"), -float("inf"), "abc"])
def test_bad_hyperparameter_names_field(field, bad):
    kwargs = {"nu": 2.5, "variance": 1.0, "lengthscale": 1.0, field: bad}
    with pytest.raises(ValueError, match=rf"^{field}=.*> 0"):
        matern(**kwargs)


@pytest.mark.parametrize("bad_nu", [2.0, 0, 0.0, -0.5, 1.0, 0.25, float("nan"), float("inf"), True])
def test_bad_nu_lists_supported_values(bad_nu):
    with pytest.raises(ValueError, match=r"nu=.*0\.5, 1\.5, 2\.5"):
        matern(bad_nu, 1.0, 1.0)


@pytest.mark.parametrize("bad_dt", [0.0, -0.1, float("nan"), float("inf"), None])
def test_bad_dt_names_dt(bad_dt):
    k = matern(PAPER_NU, PAPER_VAR, PAPER_LS)
    with pytest.raises(ValueError, match=r"^dt="):
        k.discretize(bad_dt)
    with pytest.raises(ValueError, match=r"^dt="):
        k.sample_path(3, bad_dt, np.random.default_rng(0))


def test_bad_method_and_start_name_allowed_values():
    k = matern(PAPER_NU, PAPER_VAR, PAPER_LS)
    with pytest.raises(ValueError, match=r"method='euler'.*exact.*euler_maruyama"):
        k.discretize(0.1, method="euler")
    with pytest.raises(ValueError, match=r"method=.*exact"):
        k.sample_path(3, 0.1, np.random.default_rng(0), method="rk4")
    with pytest.raises(ValueError, match=r"start='random'.*stationary.*zero"):
        k.sample_path(3, 0.1, np.random.default_rng(0), start="random")
    with pytest.raises(ValueError, match=r"n_steps="):
        k.sample_path(-1, 0.1, np.random.default_rng(0))
    with pytest.raises(ValueError, match=r"n_paths="):
        k.sample_path(3, 0.1, np.random.default_rng(0), n_paths=0)


def test_base_class_rejects_inconsistent_shapes():
    with pytest.raises(ValueError, match=r"H must have shape"):
        StateSpaceKernel(-np.eye(2), np.ones((2, 1)), [[1.0]], np.ones((1, 3)))
    with pytest.raises(ValueError, match=r"Qc must have shape"):
        StateSpaceKernel(-np.eye(2), np.ones((2, 1)), np.eye(2), np.ones((1, 2)))


# --------------------------------------------------------------------------- immutability


def test_kernel_is_frozen_and_has_readable_repr():
    F = np.array([[-1.0]])
    k = StateSpaceKernel(F, [[1.0]], [[2.0]], [[1.0]])
    F[0, 0] = -5.0  # the kernel holds its own copy
    assert k.F[0, 0] == -1.0
    assert k.Pinf[0, 0] == pytest.approx(1.0)
    m = matern(PAPER_NU, PAPER_VAR, PAPER_LS)
    for arr in (m.F, m.L, m.Qc, m.H, m.Pinf):
        assert not arr.flags.writeable
        with pytest.raises(ValueError):
            arr[0, 0] = 1.0
    with pytest.raises(AttributeError):
        m.variance = 2.0
    with pytest.raises(AttributeError):
        m.F = np.eye(3)
    assert repr(m) == "Matern(nu=2.5, variance=4, lengthscale=4)"
    assert "state_dim=1" in repr(k)
    assert isinstance(m, Matern) and isinstance(m, StateSpaceKernel)


# ----------------------------------------------------------------------------- properties


@settings(max_examples=60, deadline=None)
@given(
    nu=st.sampled_from([0.5, 1.5, 2.5]),
    variance=st.floats(min_value=1e-2, max_value=1e2),
    lengthscale=st.floats(min_value=1e-2, max_value=1e2),
)
def test_pinf_properties(nu, variance, lengthscale):
    k = matern(nu, variance, lengthscale)
    P = k.Pinf
    np.testing.assert_array_equal(P, P.T)
    # PD checked on the diagonally scaled matrix: entries span lambda^0..lambda^(2p-2).
    d = np.sqrt(np.diag(P))
    assert np.linalg.eigvalsh(P / np.outer(d, d)).min() > 1e-8
    assert (k.H @ P @ k.H.T)[0, 0] == pytest.approx(variance, rel=1e-12)
    noise = k.L @ k.Qc @ k.L.T
    residual = k.F @ P + P @ k.F.T + noise
    scale = 2.0 * np.linalg.norm(k.F) * np.linalg.norm(P) + np.linalg.norm(noise)
    assert np.linalg.norm(residual) <= 1e-12 * scale
