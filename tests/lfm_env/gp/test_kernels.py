"""Tests of the squared-exponential, periodic, sum and product kernels in ``lfm_env.gp``.

Every state-space model is checked against the closed form of the kernel it
represents, through ``H expm(F tau) Pinf H^T`` computed here (not by the module).
"""

from __future__ import annotations

import math
import pickle

import numpy as np
import pytest
import scipy.linalg
import scipy.special
from hypothesis import given, settings
from hypothesis import strategies as st

from lfm_env.gp.kernels import (
    SE_MAX_ORDER,
    Matern,
    Periodic,
    ProductKernel,
    SquaredExponential,
    StateSpaceKernel,
    SumKernel,
    matern,
    periodic,
    squared_exponential,
)
from lfm_env.gp.kernels.squared_exponential_kernel import _stable_spectral_factor

# max |k_ss - k| / sigma^2 over tau in [0, 5 l], measured for this implementation
# (the maximum sits at tau = 0). The tests allow 20 % on top of these.
SE_MEASURED_ERROR = {
    1: 7.73e-1,
    2: 1.41e-1,
    3: 4.50e-2,
    4: 1.70e-2,
    5: 6.97e-3,
    6: 2.99e-3,
    7: 1.33e-3,
    8: 6.00e-4,
    10: 1.28e-4,
    12: 2.85e-5,
}


def expm_cov(kernel: StateSpaceKernel, tau: np.ndarray) -> np.ndarray:
    """``H expm(F |tau|) Pinf H^T``, computed independently of the module.

    The lags are visited in increasing order and ``expm(F tau_k) Pinf H^T`` is carried
    forward by ``expm(F (tau_k - tau_{k-1}))``, with one matrix exponential per
    distinct gap (to 13 digits): evenly spaced lags cost a single ``expm``.
    """
    lags = np.abs(np.ravel(np.asarray(tau, dtype=float)))
    out = np.empty_like(lags)
    v = kernel.Pinf @ kernel.H[0]
    prev = 0.0
    steps: dict[str, np.ndarray] = {}
    for idx in np.argsort(lags, kind="stable"):
        gap = lags[idx] - prev
        key = f"{gap:.12e}"
        if key not in steps:
            steps[key] = scipy.linalg.expm(kernel.F * gap)
        v = steps[key] @ v
        prev = lags[idx]
        out[idx] = kernel.H[0] @ v
    return out


def lyapunov_residual(kernel: StateSpaceKernel) -> float:
    """``|F Pinf + Pinf F^T + L Qc L^T|`` relative to the size of its terms."""
    noise = kernel.L @ kernel.Qc @ kernel.L.T
    residual = kernel.F @ kernel.Pinf + kernel.Pinf @ kernel.F.T + noise
    scale = 2.0 * np.linalg.norm(kernel.F) * np.linalg.norm(kernel.Pinf) + np.linalg.norm(noise)
    return float(np.linalg.norm(residual) / scale)


def bessel_weights(lengthscale: float, harmonics: int) -> np.ndarray:
    """``q_j^2`` from unscaled ``I_j`` (fine for the moderate ``l^-2`` used here)."""
    z = lengthscale**-2
    j = np.arange(harmonics + 1)
    return np.where(j == 0, 1.0, 2.0) * scipy.special.iv(j, z) / math.exp(z)


# -------------------------------------------------------------------- squared exponential


@pytest.mark.parametrize("order", sorted(SE_MEASURED_ERROR))
@pytest.mark.parametrize(("variance", "lengthscale"), [(1.0, 1.0), (2.5, 0.7), (0.3, 30.0)])
def test_se_accuracy_per_order(order, variance, lengthscale):
    k = squared_exponential(variance, lengthscale, order)
    tau = np.linspace(0.0, 5.0 * lengthscale, 101)
    exact = variance * np.exp(-0.5 * (tau / lengthscale) ** 2)
    np.testing.assert_allclose(k.covariance(tau), exact, rtol=1e-14)
    approx = expm_cov(k, tau)
    err = np.abs(approx - exact).max() / variance
    assert err <= 1.2 * SE_MEASURED_ERROR[order]
    # the error is a property of the order, not of variance or lengthscale
    assert err == pytest.approx(SE_MEASURED_ERROR[order], rel=0.02)
    np.testing.assert_allclose(k.state_space_covariance(tau), approx, rtol=1e-9, atol=1e-12)


def test_se_default_order_six_is_within_a_third_of_a_percent():
    k = squared_exponential(4.0, 4.0)
    assert k.order == 6 and k.state_dim == 6
    tau = np.linspace(0.0, 20.0, 81)
    assert np.abs(expm_cov(k, tau) - k.covariance(tau)).max() < 3.1e-3 * 4.0
    # error decreases with the order
    errs = [SE_MEASURED_ERROR[n] for n in sorted(SE_MEASURED_ERROR)]
    assert all(a > b for a, b in zip(errs, errs[1:], strict=False))


@pytest.mark.parametrize("order", [1, 2, 4, 6, 9, 12])
def test_se_spectral_density_is_the_taylor_approximation(order):
    # S_ss(w) = Qc |H (i w I - F)^-1 L|^2 must equal sigma^2 sqrt(2 pi) l / P_N(w^2 l^2 / 2),
    # P_N the order-N Taylor polynomial of exp: checks factor, balancing and q together.
    variance, lengthscale = 1.7, 2.3
    k = squared_exponential(variance, lengthscale, order)
    for w in [0.0, 0.1, 0.5, 1.0, 2.0, 5.0]:
        g = k.H @ np.linalg.solve(1j * w * np.eye(order) - k.F, k.L)
        s_ss = k.Qc[0, 0] * abs(g[0, 0]) ** 2
        x = 0.5 * (w * lengthscale) ** 2
        taylor = sum(x**n / math.factorial(n) for n in range(order + 1))
        expected = variance * math.sqrt(2.0 * math.pi) * lengthscale / taylor
        assert s_ss == pytest.approx(expected, rel=1e-9)


@pytest.mark.parametrize("order", [1, 3, 6, 12])
def test_se_matrices_are_consistent(order):
    k = squared_exponential(2.0, 1.5, order)
    np.testing.assert_array_equal(k.H, np.eye(1, order))  # w = z[0] kept by the balancing
    assert k.L.shape == (order, 1) and k.Qc.shape == (1, 1)
    assert np.linalg.eigvals(k.F).real.max() < 0.0
    assert lyapunov_residual(k) < 1e-12
    np.testing.assert_array_equal(k.Pinf, k.Pinf.T)
    assert np.linalg.eigvalsh(k.Pinf).min() > 0.0
    assert k.stationary_variance == pytest.approx(2.0 * (1.0 + SE_MEASURED_ERROR[order]), rel=0.01)
    # balanced: no entry of F is more than ~100x another nonzero one at this lengthscale
    nz = np.abs(k.F[k.F != 0.0])
    assert nz.max() / nz.min() < 1e3


def test_se_scaling_in_variance_and_lengthscale():
    a = squared_exponential(1.0, 1.0)
    b = squared_exponential(3.0, 0.25)
    np.testing.assert_allclose(b.F, a.F / 0.25, rtol=1e-15)
    np.testing.assert_allclose(b.Pinf, 3.0 * a.Pinf, rtol=1e-15)
    np.testing.assert_allclose(b.Qc, 3.0 * a.Qc / 0.25, rtol=1e-15)
    # covariance at lag tau for (3, 0.25) is 3 times that of (1, 1) at tau / 0.25
    np.testing.assert_allclose(expm_cov(b, [0.1, 0.3]), 3.0 * expm_cov(a, [0.4, 1.2]), rtol=1e-10)


@pytest.mark.parametrize("bad", [0, -1, SE_MAX_ORDER + 1, 2.5, True, "6", None])
def test_se_bad_order_names_allowed_range(bad):
    with pytest.raises(ValueError, match=rf"^order=.*\[1, {SE_MAX_ORDER}\]"):
        squared_exponential(1.0, 1.0, bad)


@pytest.mark.parametrize("field", ["variance", "lengthscale"])
def test_se_bad_hyperparameter_names_field(field):
    kwargs = {"variance": 1.0, "lengthscale": 1.0, field: -1.0}
    with pytest.raises(ValueError, match=rf"^{field}=.*> 0"):
        squared_exponential(**kwargs)


def test_spectral_factor_rejects_roots_on_the_imaginary_axis():
    # P(w^2) = (1 - w^2)^2 vanishes at w = +-1: the factor would be marginally stable.
    with pytest.raises(ValueError, match="imaginary axis.*not stable"):
        _stable_spectral_factor([1.0, -2.0, 1.0])
    # P(w^2) = 1 + w^2 (Matern 1/2 with lambda = 1): G(s) = s + 1
    np.testing.assert_allclose(_stable_spectral_factor([1.0, 1.0]), [1.0, 1.0])


@pytest.mark.parametrize("ratio", [1e-3, 0.05, 1.0, 10.0, 1e4])
def test_se_exact_discretisation_keeps_stationarity(ratio):
    k = squared_exponential(2.0, 3.0)
    dt = ratio * 3.0
    A, Q = k.discretize(dt)
    np.testing.assert_allclose(A, scipy.linalg.expm(k.F * dt), rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(A @ k.Pinf @ A.T + Q, k.Pinf, rtol=0, atol=1e-12 * 2.0)
    assert np.linalg.eigvalsh(Q).min() > -1e-12 * 2.0
    if ratio >= 1e4:
        np.testing.assert_allclose(Q, k.Pinf, atol=1e-12)


def test_se_discretize_refuses_ill_conditioned_steps():
    k = squared_exponential(2.0, 3.0)
    with pytest.raises(ValueError, match=r"dt=.*too small for lengthscale=3.*order 6"):
        k.discretize(3.0e-10)
    k.discretize(3.0e-7)  # still accurate to ~1e-9 relative
    # Euler-Maruyama has no cancellation and no check
    A, Q = k.discretize(3.0e-10, method="euler_maruyama")
    assert np.all(np.isfinite(A)) and np.all(np.isfinite(Q))


def test_se_sample_path_variance_matches_the_approximation():
    k = squared_exponential(4.0, 4.0)
    paths = k.sample_path(30, 0.5, np.random.default_rng(11), n_paths=3000)
    w = paths[..., 0]
    se_var = k.stationary_variance * math.sqrt(2.0 / 2999)
    for step in (0, 15, 30):
        assert abs(w[:, step].var(ddof=1) - k.stationary_variance) < 5.0 * se_var
    rho = k.state_space_covariance(2.0) / k.stationary_variance  # lag 4 steps
    est = np.corrcoef(w[:, 10], w[:, 14])[0, 1]
    assert abs(est - rho) < 5.0 * (1.0 - rho**2) / math.sqrt(3000)


# ------------------------------------------------------------------------------ periodic


@pytest.mark.parametrize(
    ("lengthscale", "harmonics"), [(2.0, 3), (1.0, 6), (0.7, 6), (0.5, 6), (0.5, 10), (0.3, 10)]
)
def test_periodic_matches_closed_form_within_truncation_error(lengthscale, harmonics):
    variance, period = 1.7, 2.5
    k = periodic(variance, lengthscale, period, harmonics)
    tau = np.linspace(-1.5 * period, 2.5 * period, 161)
    exact = variance * np.exp(-2.0 * np.sin(np.pi * tau / period) ** 2 / lengthscale**2)
    np.testing.assert_allclose(k.covariance(tau), exact, rtol=1e-14)
    approx = expm_cov(k, tau)
    np.testing.assert_allclose(k.state_space_covariance(tau), approx, rtol=0, atol=1e-12)
    # the truncation error is exactly the tail sum, attained at tau = 0 mod period
    tail = 1.0 - bessel_weights(lengthscale, harmonics).sum()
    assert k.truncation_error == pytest.approx(tail, rel=1e-6, abs=1e-15)
    err = np.abs(approx - exact).max()
    assert err <= variance * k.truncation_error + 1e-12
    assert err == pytest.approx(variance * k.truncation_error, rel=1e-6, abs=1e-12)


@pytest.mark.parametrize(
    ("lengthscale", "harmonics", "expected"),
    [(1.0, 6, 1.254e-6), (0.7, 6, 7.714e-5), (0.5, 6, 1.968e-3), (0.5, 10, 3.111e-6)],
)
def test_periodic_documented_truncation_errors(lengthscale, harmonics, expected):
    k = periodic(1.0, lengthscale, 1.0, harmonics)
    assert k.truncation_error == pytest.approx(expected, rel=1e-3)


def test_periodic_matrices():
    k = periodic(2.0, 0.9, 4.0, harmonics=3)
    w0 = 2.0 * math.pi / 4.0
    assert k.state_dim == 8
    expected_F = scipy.linalg.block_diag(
        *[np.array([[0.0, -j * w0], [j * w0, 0.0]]) for j in range(4)]
    )
    np.testing.assert_allclose(k.F, expected_F, rtol=1e-15)
    np.testing.assert_array_equal(k.H, [[1, 0, 1, 0, 1, 0, 1, 0]])
    np.testing.assert_array_equal(k.Qc, np.zeros((8, 8)))
    np.testing.assert_allclose(np.diag(k.Pinf), 2.0 * np.repeat(bessel_weights(0.9, 3), 2))
    np.testing.assert_allclose(k.F @ k.Pinf + k.Pinf @ k.F.T, 0.0, atol=1e-14)
    A, Q = k.discretize(0.7)
    np.testing.assert_allclose(Q, 0.0, atol=1e-14)  # deterministic rotation
    np.testing.assert_allclose(A @ A.T, np.eye(8), atol=1e-14)
    assert k.stationary_variance == pytest.approx(2.0 * (1.0 - k.truncation_error), rel=1e-12)


def test_periodic_small_lengthscale_needs_more_harmonics():
    with pytest.raises(ValueError, match=r"lengthscale=0.2 is too small for harmonics=6.*>= 13"):
        periodic(1.0, 0.2, 1.0)
    k = periodic(1.0, 0.2, 1.0, harmonics=13)
    assert k.truncation_error <= 1e-2
    # a looser tolerance accepts the coarse model, a tighter one refuses the default
    assert periodic(1.0, 0.2, 1.0, max_truncation_error=0.3).truncation_error > 0.1
    with pytest.raises(ValueError, match="too small"):
        periodic(1.0, 1.0, 1.0, max_truncation_error=1e-8)


def test_periodic_extreme_lengthscales_do_not_overflow():
    with np.errstate(all="raise"):
        with pytest.raises(ValueError, match="too small"):
            periodic(1.0, 1e-3, 1.0)
        k = periodic(1.0, 0.05, 1.0, harmonics=80)  # z = 400: I_j(400) would overflow
        assert np.all(np.isfinite(k.Pinf))
        flat = periodic(1.0, 1e3, 1.0)  # nearly constant kernel
        assert flat.Pinf[0, 0] == pytest.approx(1.0, rel=1e-6)
    tau = np.linspace(0.0, 1.0, 21)
    np.testing.assert_allclose(expm_cov(k, tau), k.covariance(tau), atol=k.truncation_error + 1e-12)


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"period": 0.0}, "^period="),
        ({"period": -1.0}, "^period="),
        ({"lengthscale": float("nan")}, "^lengthscale="),
        ({"harmonics": -1}, "^harmonics="),
        ({"harmonics": 2.5}, "^harmonics="),
        ({"max_truncation_error": 0.0}, "^max_truncation_error="),
        ({"max_truncation_error": 2.0}, r"^max_truncation_error=.*\(0, 1\]"),
    ],
)
def test_periodic_bad_arguments_name_the_field(kwargs, match):
    args = {"variance": 1.0, "lengthscale": 1.0, "period": 1.0, **kwargs}
    with pytest.raises(ValueError, match=match):
        periodic(**args)


# --------------------------------------------------------------------- sums and products


def test_sum_structure_and_covariance():
    a, b, c = matern(1.5, 2.0, 1.0), periodic(0.5, 1.0, 3.0, 4), squared_exponential(1.0, 2.0, 4)
    k = a + b + c
    assert isinstance(k, SumKernel) and k.parts == (a, b, c)  # flattened
    assert k.state_dim == 2 + 10 + 4
    np.testing.assert_array_equal(k.F, scipy.linalg.block_diag(a.F, b.F, c.F))
    np.testing.assert_array_equal(k.Pinf, scipy.linalg.block_diag(a.Pinf, b.Pinf, c.Pinf))
    np.testing.assert_array_equal(k.L, scipy.linalg.block_diag(a.L, b.L, c.L))
    np.testing.assert_array_equal(k.Qc, scipy.linalg.block_diag(a.Qc, b.Qc, c.Qc))
    np.testing.assert_array_equal(k.H, np.hstack([a.H, b.H, c.H]))
    tau = np.linspace(0.0, 8.0, 41)
    closed = a.covariance(tau) + b.covariance(tau) + c.covariance(tau)
    np.testing.assert_allclose(k.covariance(tau), closed, rtol=1e-14)
    ss = expm_cov(k, tau)
    np.testing.assert_allclose(k.state_space_covariance(tau), ss, rtol=0, atol=1e-11)
    bound = 0.5 * b.truncation_error + 1.0 * SE_MEASURED_ERROR[4] * 1.2 + 1e-12
    assert np.abs(ss - closed).max() <= bound
    assert lyapunov_residual(k) < 1e-12
    assert sum([a, b, c]).parts == (a, b, c)


@pytest.mark.parametrize(
    "factors",
    [
        (matern(0.5, 2.0, 1.5), matern(2.5, 1.0, 3.0)),
        (matern(1.5, 1.0, 2.0), matern(1.5, 3.0, 0.5)),
        (matern(0.5, 1.0, 1.0), matern(0.5, 1.0, 2.0), matern(1.5, 2.0, 4.0)),
    ],
)
def test_product_of_maternas_is_exact(factors):
    k = factors[0]
    for f in factors[1:]:
        k = k * f
    assert isinstance(k, ProductKernel) and k.parts == factors
    assert k.state_dim == math.prod(f.state_dim for f in factors)
    tau = np.linspace(0.0, 6.0, 31)
    closed = np.prod([f.covariance(tau) for f in factors], axis=0)
    np.testing.assert_allclose(k.covariance(tau), closed, rtol=1e-14)
    np.testing.assert_allclose(expm_cov(k, tau), closed, rtol=0, atol=1e-10 * closed[0])
    assert lyapunov_residual(k) < 1e-12
    # Pinf is the Kronecker product and also the Lyapunov solution for the built noise
    solved = scipy.linalg.solve_continuous_lyapunov(k.F, -k.L @ k.Qc @ k.L.T)
    np.testing.assert_allclose(solved, k.Pinf, rtol=0, atol=1e-10 * np.abs(k.Pinf).max())


def test_quasi_periodic_product():
    m, p = matern(1.5, 2.0, 5.0), periodic(1.0, 0.8, 2.0, harmonics=6)
    k = m * p
    assert k.state_dim == 2 * 14
    # periodic factor has Qc = 0: only the Matern's noise, L = L_m (x) I, Qc = Qc_m (x) Pinf_p
    np.testing.assert_array_equal(k.L, np.kron(m.L, np.eye(14)))
    np.testing.assert_allclose(k.Qc, np.kron(m.Qc, p.Pinf), rtol=1e-15)
    np.testing.assert_allclose(k.F, np.kron(m.F, np.eye(14)) + np.kron(np.eye(2), p.F))
    np.testing.assert_array_equal(k.H, np.kron(m.H, p.H))
    np.testing.assert_allclose(k.Pinf, np.kron(m.Pinf, p.Pinf), rtol=1e-15)
    assert lyapunov_residual(k) < 1e-12
    tau = np.linspace(0.0, 10.0, 41)
    closed = m.covariance(tau) * p.covariance(tau)
    np.testing.assert_allclose(k.covariance(tau), closed, rtol=1e-14)
    ss = expm_cov(k, tau)
    np.testing.assert_allclose(k.state_space_covariance(tau), ss, rtol=0, atol=1e-11)
    assert np.abs(ss - closed).max() <= 2.0 * p.truncation_error + 1e-11
    # the order does not matter for the covariance
    np.testing.assert_allclose(expm_cov(p * m, tau), ss, rtol=0, atol=1e-11)
    # stationarity under exact discretisation
    A, Q = k.discretize(0.3)
    np.testing.assert_allclose(A @ k.Pinf @ A.T + Q, k.Pinf, atol=1e-12)
    assert np.linalg.eigvalsh(Q).min() > -1e-12


def test_products_with_se_and_of_periodic_kernels():
    se, p1, p2 = squared_exponential(1.0, 2.0, 4), periodic(1.0, 1.0, 1.0, 3), periodic(1, 1, 3, 3)
    tau = np.linspace(0.0, 6.0, 25)
    k = se * p1
    assert lyapunov_residual(k) < 1e-12
    np.testing.assert_allclose(
        expm_cov(k, tau),
        se.state_space_covariance(tau) * p1.state_space_covariance(tau),
        atol=1e-11,
    )
    both = p1 * p2  # deterministic: no noise block at all
    assert np.all(both.Qc == 0.0)
    np.testing.assert_allclose(
        expm_cov(both, tau),
        p1.state_space_covariance(tau) * p2.state_space_covariance(tau),
        atol=1e-11,
    )


def test_composite_hyperparameters_route_to_parts():
    m, p = matern(2.5, 4.0, 4.0), periodic(1.0, 1.0, 2.0)
    k = m * p + squared_exponential(0.5, 10.0)
    assert isinstance(k, SumKernel) and isinstance(k.parts[0], ProductKernel)
    assert k.hyperparameters == {
        "k0_k0_variance": 4.0,
        "k0_k0_lengthscale": 4.0,
        "k0_k1_variance": 1.0,
        "k0_k1_lengthscale": 1.0,
        "k0_k1_period": 2.0,
        "k1_variance": 0.5,
        "k1_lengthscale": 10.0,
    }
    k2 = k.with_hyperparameters(k0_k1_period=3.0, k1_lengthscale=5.0)
    assert k2.parts[0].parts[1].period == 3.0 and k2.parts[0].parts[1].harmonics == 6
    assert k2.parts[1].lengthscale == 5.0 and k2.parts[1].order == 6
    assert k2.parts[0].parts[0] is m  # untouched parts are reused
    assert k.hyperparameters["k0_k1_period"] == 2.0  # original unchanged
    with pytest.raises(ValueError, match=r"unknown hyperparameter.*'k0_period'.*k0_k0_variance"):
        k.with_hyperparameters(k0_period=1.0)
    with pytest.raises(ValueError, match=r"^period="):
        k.with_hyperparameters(k0_k1_period=-1.0)


def test_leaf_with_hyperparameters():
    assert matern(1.5, 1.0, 2.0).with_hyperparameters(variance=3.0).hyperparameters == {
        "variance": 3.0,
        "lengthscale": 2.0,
    }
    assert matern(1.5, 1.0, 2.0).with_hyperparameters(lengthscale=5.0).nu == 1.5
    se = squared_exponential(1.0, 1.0, 3).with_hyperparameters(lengthscale=2.0)
    assert (se.order, se.lengthscale) == (3, 2.0)
    p = periodic(1.0, 1.0, 1.0, 8, max_truncation_error=1e-3).with_hyperparameters(period=2.0)
    assert (p.harmonics, p.max_truncation_error, p.period) == (8, 1e-3, 2.0)
    raw = StateSpaceKernel([[-1.0]], [[1.0]], [[2.0]], [[1.0]])
    assert raw.hyperparameters == {} and raw.with_hyperparameters() is raw
    with pytest.raises(ValueError, match="allowed: none"):
        raw.with_hyperparameters(variance=1.0)
    with pytest.raises(ValueError, match=r"unknown.*'nu'.*variance, lengthscale"):
        matern(1.5, 1.0, 1.0).with_hyperparameters(nu=2.5)


def test_composition_type_errors():
    k = matern(0.5, 1.0, 1.0)
    with pytest.raises(TypeError):
        k + 1.0
    with pytest.raises(TypeError):
        k * 2.0
    with pytest.raises(TypeError, match="StateSpaceKernel"):
        SumKernel(k, "abc")
    with pytest.raises(ValueError, match="at least two"):
        ProductKernel(k)


def test_new_kernels_are_frozen_picklable_and_readable():
    kernels = [
        squared_exponential(1.0, 2.0, 4),
        periodic(1.0, 1.0, 2.0),
        matern(0.5, 1.0, 1.0) + periodic(1.0, 1.0, 2.0),
        matern(0.5, 1.0, 1.0) * periodic(1.0, 1.0, 2.0),
    ]
    for k in kernels:
        for arr in (k.F, k.L, k.Qc, k.H, k.Pinf):
            assert not arr.flags.writeable
        with pytest.raises(AttributeError):
            k.variance = 2.0
        assert k.fit_info is None
        k2 = pickle.loads(pickle.dumps(k))
        np.testing.assert_array_equal(k2.F, k.F)
        assert repr(k2) == repr(k)
    assert repr(kernels[0]) == "SquaredExponential(variance=1, lengthscale=2, order=4)"
    assert repr(kernels[1]) == "Periodic(variance=1, lengthscale=1, period=2, harmonics=6)"
    assert repr(kernels[3]).startswith("ProductKernel(Matern(nu=0.5") and " * Periodic(" in repr(
        kernels[3]
    )
    assert isinstance(kernels[0], SquaredExponential) and isinstance(kernels[1], Periodic)


def test_base_state_space_covariance_equals_closed_form_for_matern():
    m = matern(2.5, 4.0, 4.0)
    assert isinstance(m, Matern)
    tau = np.array([0.0, 0.5, 3.0, 12.0])
    np.testing.assert_allclose(m.state_space_covariance(tau), m.covariance(tau), atol=1e-10)


# ----------------------------------------------------------------------------- properties


@settings(max_examples=40, deadline=None)
@given(
    order=st.integers(min_value=1, max_value=SE_MAX_ORDER),
    variance=st.floats(min_value=1e-2, max_value=1e2),
    lengthscale=st.floats(min_value=1e-2, max_value=1e2),
)
def test_se_pinf_properties(order, variance, lengthscale):
    k = squared_exponential(variance, lengthscale, order)
    unit = squared_exponential(1.0, 1.0, order)
    np.testing.assert_array_equal(k.Pinf, k.Pinf.T)
    assert np.linalg.eigvalsh(k.Pinf / variance).min() > 0.0
    assert k.stationary_variance == pytest.approx(variance * unit.stationary_variance, rel=1e-13)
    assert abs(k.stationary_variance / variance - 1.0) <= 1.2 * SE_MEASURED_ERROR.get(order, 1.0)
    assert lyapunov_residual(k) < 1e-12


@settings(max_examples=40, deadline=None)
@given(
    variance=st.floats(min_value=1e-2, max_value=1e2),
    lengthscale=st.floats(min_value=0.45, max_value=1e2),
    period=st.floats(min_value=1e-2, max_value=1e2),
    harmonics=st.integers(min_value=6, max_value=12),
)
def test_periodic_pinf_properties(variance, lengthscale, period, harmonics):
    k = periodic(variance, lengthscale, period, harmonics)
    np.testing.assert_array_equal(k.Pinf, np.diag(np.diag(k.Pinf)))
    assert np.all(np.diag(k.Pinf) >= 0.0)
    assert k.stationary_variance == pytest.approx(variance * (1.0 - k.truncation_error), rel=1e-12)
    assert 0.0 <= k.truncation_error <= 1e-2
    tau = np.array([0.0, 0.3 * period, 0.5 * period, 1.7 * period])
    err = np.abs(k.state_space_covariance(tau) - k.covariance(tau)).max()
    assert err <= variance * k.truncation_error + 1e-12 * variance
