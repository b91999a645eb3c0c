"""Tests of the Kalman-filter likelihood, its gradient and hyperparameter fitting in ``lfm_env.gp``.

The filter is cross-checked against the dense GP likelihood ``log N(y; 0, K + r I)``
computed here by Cholesky, with ``K`` from the closed-form kernel (Matern, exact in
state space) or from the state-space covariance (SE and periodic approximations).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import scipy.linalg

from lfm_env.gp import (
    FitInfo,
    Matern,
    StateSpaceKernel,
    fit,
    log_marginal_likelihood,
    log_marginal_likelihood_and_grad,
    matern,
    periodic,
    squared_exponential,
)
from lfm_env.gp import likelihood as gp_likelihood


def dense_log_likelihood(K: np.ndarray, y: np.ndarray, noise_variance: float) -> float:
    """``log N(y; 0, K + noise_variance I)`` by Cholesky."""
    c, lower = scipy.linalg.cho_factor(K + noise_variance * np.eye(y.size), lower=True)
    alpha = scipy.linalg.cho_solve((c, lower), y)
    return float(
        -0.5 * y @ alpha - np.log(np.diag(c)).sum() - 0.5 * y.size * math.log(2.0 * math.pi)
    )


def state_space_gram(kernel: StateSpaceKernel, t: np.ndarray) -> np.ndarray:
    """``K_ij = H expm(F (t_j - t_i)) Pinf H^T`` for sorted ``t``, independently of the module.

    Row ``i`` carries ``Pinf H^T`` forward through the one-step exponentials
    ``expm(F (t_{j+1} - t_j))``, so only ``n - 1`` matrix exponentials are needed.
    """
    n = t.size
    steps = [scipy.linalg.expm(kernel.F * (t[j + 1] - t[j])) for j in range(n - 1)]
    h = kernel.H[0]
    K = np.empty((n, n))
    for i in range(n):
        v = kernel.Pinf @ h
        K[i, i] = h @ v
        for j in range(i + 1, n):
            v = steps[j - 1] @ v
            K[i, j] = K[j, i] = h @ v
    return K


def irregular_times(rng: np.random.Generator, n: int, span: float) -> np.ndarray:
    return np.sort(rng.uniform(0.0, span, n))


# ------------------------------------------------------------------- likelihood vs dense


@pytest.mark.parametrize("nu", [0.5, 1.5, 2.5])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_matern_likelihood_matches_dense_closed_form(nu, seed):
    rng = np.random.default_rng(seed)
    variance = float(np.exp(rng.uniform(np.log(0.1), np.log(10.0))))
    lengthscale = float(np.exp(rng.uniform(np.log(0.2), np.log(10.0))))
    noise = variance * float(np.exp(rng.uniform(np.log(1e-3), np.log(1.0))))
    n = int(rng.integers(50, 201))
    t = irregular_times(rng, n, span=n * 0.2)
    k = matern(nu, variance, lengthscale)
    y = rng.standard_normal(n) * math.sqrt(variance + noise)
    K = k.covariance(t[:, None] - t[None, :])  # closed form: Matern is exact in state space
    dense = dense_log_likelihood(K, y, noise)
    kalman = log_marginal_likelihood(k, t, y, noise)
    # measured agreement ~1e-14 relative
    assert kalman == pytest.approx(dense, rel=1e-9)


@pytest.mark.parametrize(
    "kernel",
    [
        squared_exponential(1.5, 2.0),
        squared_exponential(0.7, 0.8, order=10),
        periodic(1.0, 0.8, 3.0),
        matern(1.5, 1.0, 3.0) * periodic(1.0, 1.0, 2.0, harmonics=4),
        matern(0.5, 1.0, 1.0) + squared_exponential(0.5, 3.0, order=4),
    ],
    ids=["se6", "se10", "periodic", "quasi_periodic", "sum"],
)
def test_approximate_kernels_likelihood_matches_dense_state_space(kernel):
    rng = np.random.default_rng(5)
    n = 60
    t = irregular_times(rng, n, span=20.0)
    y = rng.standard_normal(n)
    K = state_space_gram(kernel, t)
    np.testing.assert_allclose(kernel.state_space_covariance(t - t[0]), K[0], rtol=0, atol=1e-10)
    for noise in (0.05, 1.0):
        dense = dense_log_likelihood(K, y, noise)
        # measured agreement ~1e-14 relative
        assert log_marginal_likelihood(kernel, t, y, noise) == pytest.approx(dense, rel=1e-9)


def test_repeated_and_regular_times():
    k = matern(2.5, 4.0, 4.0)
    rng = np.random.default_rng(3)
    t = np.repeat(0.2 * np.arange(40), 2)  # every time twice: dt = 0 steps
    y = rng.standard_normal(t.size)
    K = k.covariance(t[:, None] - t[None, :])
    assert log_marginal_likelihood(k, t, y, 0.3) == pytest.approx(
        dense_log_likelihood(K, y, 0.3), rel=1e-10
    )
    t1 = np.array([1.5])
    assert log_marginal_likelihood(k, t1, [0.7], 0.3) == pytest.approx(
        -0.5 * (math.log(2 * math.pi * 4.3) + 0.49 / 4.3), rel=1e-14
    )


def test_regular_grid_matches_dense():
    # np.arange grids: step lengths equal up to rounding share one discretisation, and the
    # filter switches to its steady-state gain once the covariance has converged.
    k = matern(2.5, 4.0, 4.0)
    rng = np.random.default_rng(9)
    t = 0.2 * np.arange(400) + 0.1
    assert np.unique(np.diff(t)).size > 1  # several binary values of "0.2"
    y = rng.standard_normal(t.size) * 2.0
    K = k.covariance(t[:, None] - t[None, :])
    assert log_marginal_likelihood(k, t, y, 0.1) == pytest.approx(
        dense_log_likelihood(K, y, 0.1), rel=1e-10
    )


@pytest.mark.parametrize(
    "kernel",
    [
        matern(2.5, 4.0, 4.0),
        squared_exponential(1.0, 2.0, 4),
        matern(0.5, 1.0, 1.0) + matern(1.5, 1, 2),
    ],
    ids=["m52", "se4", "sum"],
)
def test_steady_state_shortcut_matches_the_full_filter(kernel, monkeypatch):
    rng = np.random.default_rng(4)
    # two regular runs with different steps, a repeated time and an irregular tail
    t = np.concatenate(
        [
            0.2 * np.arange(300),
            60.0 + 0.5 * np.arange(150),
            [134.5],
            135.0 + np.cumsum(rng.uniform(0.1, 1.0, 30)),
        ]
    )
    y = rng.standard_normal(t.size)
    fast = log_marginal_likelihood(kernel, t, y, 0.1)
    fast_ll, fast_grad = log_marginal_likelihood_and_grad(kernel, t, y, 0.1)
    monkeypatch.setattr(gp_likelihood, "_STEADY_STATE_RTOL", -1.0)  # never converged: all steps
    slow = log_marginal_likelihood(kernel, t, y, 0.1)
    slow_ll, slow_grad = log_marginal_likelihood_and_grad(kernel, t, y, 0.1)
    assert fast == pytest.approx(slow, rel=1e-11)
    assert fast_ll == pytest.approx(slow_ll, rel=1e-11)
    for name, g in slow_grad.items():
        assert fast_grad[name] == pytest.approx(g, rel=1e-8, abs=1e-8), name


def test_periodic_without_noise_reports_a_degenerate_innovation():
    # one harmonic-free resonator is a random constant: after one exact observation
    # the next one is perfectly predicted, so the innovation variance is 0.
    k = periodic(1.0, 10.0, 1.0, harmonics=0)
    with pytest.raises(ValueError, match="innovation variance"):
        log_marginal_likelihood(k, [0.0, 1.0], [0.5, 0.5], 0.0)


@pytest.mark.parametrize(
    ("times", "values", "noise", "match"),
    [
        ([0.0, 2.0, 1.0], [0.0, 0.0, 0.0], 0.1, "sorted"),
        ([0.0, 1.0], [0.0], 0.1, "shape"),
        ([], [], 0.1, "non-empty"),
        ([0.0, 1.0], [0.0, float("nan")], 0.1, "finite"),
        ([[0.0, 1.0]], [[0.0, 1.0]], 0.1, "1-D"),
        ([0.0, 1.0], [0.0, 1.0], -0.1, "^noise_variance="),
        ([0.0, 1.0], [0.0, 1.0], float("inf"), "^noise_variance="),
        ([0.0, 1.0], [0.0, 1.0], None, "^noise_variance="),
    ],
)
def test_likelihood_input_errors(times, values, noise, match):
    with pytest.raises(ValueError, match=match):
        log_marginal_likelihood(matern(0.5, 1.0, 1.0), times, values, noise)


# ------------------------------------------------------------------------------ gradient


@pytest.mark.parametrize(
    "kernel",
    [
        matern(2.5, 4.0, 4.0),
        matern(0.5, 0.3, 0.7),
        squared_exponential(1.5, 2.0),
        periodic(1.0, 0.8, 3.0),
        matern(1.5, 1.0, 3.0) * periodic(1.0, 1.5, 2.0, harmonics=2),
        matern(0.5, 1.0, 1.0) + squared_exponential(0.5, 3.0, order=4),
    ],
    ids=["m52", "m12", "se", "periodic", "quasi_periodic", "sum"],
)
def test_gradient_matches_central_differences(kernel):
    rng = np.random.default_rng(8)
    t = irregular_times(rng, 30, span=15.0)
    y = rng.standard_normal(30)
    noise = 0.2
    ll, grad = log_marginal_likelihood_and_grad(kernel, t, y, noise)
    assert ll == pytest.approx(log_marginal_likelihood(kernel, t, y, noise), rel=1e-13)
    assert list(grad) == [*kernel.hyperparameters, "noise_variance"]
    h = 1e-5
    hp = kernel.hyperparameters
    for name, g in grad.items():
        if name == "noise_variance":

            def f(s):
                return log_marginal_likelihood(kernel, t, y, noise * math.exp(s))
        else:

            def f(s, name=name):
                k = kernel.with_hyperparameters(**{name: hp[name] * math.exp(s)})
                return log_marginal_likelihood(k, t, y, noise)

        fd = (f(h) - f(-h)) / (2.0 * h)
        # measured agreement 1e-10 .. 2e-7 relative
        assert g == pytest.approx(fd, rel=1e-5, abs=1e-6), name


def test_gradient_subset_and_errors():
    k = matern(1.5, 2.0, 1.0)
    t, y = np.linspace(0.0, 5.0, 20), np.sin(np.linspace(0.0, 5.0, 20))
    _, full = log_marginal_likelihood_and_grad(k, t, y, 0.1)
    _, part = log_marginal_likelihood_and_grad(k, t, y, 0.1, wrt=["lengthscale"])
    assert list(part) == ["lengthscale"]
    assert part["lengthscale"] == pytest.approx(full["lengthscale"], rel=1e-12)
    with pytest.raises(ValueError, match=r"wrt: unknown.*'period'.*variance, lengthscale"):
        log_marginal_likelihood_and_grad(k, t, y, 0.1, wrt=["period"])
    with pytest.raises(ValueError, match="noise_variance=0"):
        log_marginal_likelihood_and_grad(k, t, y, 0.0)
    _, no_noise = log_marginal_likelihood_and_grad(k, t, y, 0.0, wrt=["variance"])
    assert math.isfinite(no_noise["variance"])


# ----------------------------------------------------------------------------------- fit

TRUE_VAR, TRUE_LS, TRUE_NOISE, DT, N_SAMPLES = 4.0, 4.0, 0.1, 0.2, 2000


@pytest.fixture(scope="module")
def matern_data() -> tuple[np.ndarray, np.ndarray]:
    """A 400 s (100 lengthscales) noisy Matern 5/2 path with the paper's hyperparameters."""
    rng = np.random.default_rng(2024)
    w = matern(2.5, TRUE_VAR, TRUE_LS).sample_path(N_SAMPLES - 1, DT, rng)[:, 0]
    t = DT * np.arange(N_SAMPLES)
    return t, w + math.sqrt(TRUE_NOISE) * rng.standard_normal(N_SAMPLES)


@pytest.fixture(scope="module")
def matern_fits(matern_data):
    t, y = matern_data
    near = fit(matern(2.5, 1.0, 1.0), t, y)
    far = fit(matern(2.5, 30.0, 20.0), t, y, initial_noise_variance=2.0)
    return near, far


def test_fit_recovers_matern_hyperparameters(matern_data, matern_fits):
    t, y = matern_data
    fitted, _ = matern_fits
    assert isinstance(fitted, Matern) and fitted.nu == 2.5
    info = fitted.fit_info
    assert isinstance(info, FitInfo) and info.success and info.noise_variance_learned
    estimate = np.log([fitted.variance, fitted.lengthscale, info.noise_variance])
    truth = np.log([TRUE_VAR, TRUE_LS, TRUE_NOISE])
    # Asymptotic standard errors from the observed information (Hessian of the
    # log-likelihood in log-parameters, by central differences of the gradient).
    names = ["variance", "lengthscale", "noise_variance"]

    def grad_at(theta):
        k = fitted.with_hyperparameters(variance=math.exp(theta[0]), lengthscale=math.exp(theta[1]))
        _, g = log_marginal_likelihood_and_grad(k, t, y, math.exp(theta[2]))
        return np.array([g[name] for name in names])

    h = 1e-3
    hess = np.column_stack(
        [(grad_at(estimate + h * e) - grad_at(estimate - h * e)) / (2 * h) for e in np.eye(3)]
    )
    cov = np.linalg.inv(-0.5 * (hess + hess.T))
    # at the optimum: the Newton step is negligible against the standard errors
    assert np.abs(cov @ grad_at(estimate)).max() < 1e-4
    std_err = np.sqrt(np.diag(cov))
    # ~20 % on the variance, ~5 % on the lengthscale, ~3 % on the noise for 100 lengthscales
    # (a 20-seed sweep at this size gave sd 0.84, 0.23, 0.004 around 4, 4, 0.1)
    assert std_err[0] < 0.3 and std_err[1] < 0.1 and std_err[2] < 0.06
    assert np.all(np.abs(estimate - truth) < 3.0 * std_err)
    assert fitted.variance == pytest.approx(TRUE_VAR, rel=0.6)  # 3 sd: poorly identified
    assert fitted.lengthscale == pytest.approx(TRUE_LS, rel=0.15)
    assert info.noise_variance == pytest.approx(TRUE_NOISE, rel=0.15)
    # a maximum: at least as likely as the truth, and fit_info is consistent
    truth_ll = log_marginal_likelihood(matern(2.5, TRUE_VAR, TRUE_LS), t, y, TRUE_NOISE)
    assert info.log_likelihood >= truth_ll
    assert info.log_likelihood == pytest.approx(
        log_marginal_likelihood(fitted, t, y, info.noise_variance), rel=1e-14
    )
    assert info.hyperparameters == fitted.hyperparameters


def test_fit_from_a_wrong_start_reaches_the_same_optimum(matern_fits):
    near, far = matern_fits
    assert far.fit_info.success
    assert far.fit_info.log_likelihood == pytest.approx(near.fit_info.log_likelihood, abs=1e-4)
    assert far.variance == pytest.approx(near.variance, rel=2e-3)
    assert far.lengthscale == pytest.approx(near.lengthscale, rel=2e-3)
    assert far.fit_info.noise_variance == pytest.approx(near.fit_info.noise_variance, rel=2e-3)


def test_fit_with_fixed_noise_and_fixed_hyperparameters(matern_data, matern_fits):
    t, y = matern_data[0][:500], matern_data[1][:500]
    start = matern(2.5, 2.0, 4.0)
    fitted = fit(start, t, y, noise_variance=TRUE_NOISE, fixed=["lengthscale"])
    assert fitted.lengthscale == 4.0
    assert fitted.fit_info.noise_variance == TRUE_NOISE
    assert not fitted.fit_info.noise_variance_learned
    assert fitted.variance != 2.0
    assert start.fit_info is None and start.variance == 2.0  # the start is not touched
    # only the variance moved, so its gradient vanishes at the optimum
    _, g = log_marginal_likelihood_and_grad(fitted, t, y, TRUE_NOISE, wrt=["variance"])
    assert abs(g["variance"]) < 1e-2


def test_fit_recovers_a_period():
    rng = np.random.default_rng(7)
    truth = periodic(1.0, 1.0, 3.0)
    # given z_0 ~ N(0, Pinf) the periodic process is deterministic (Q = 0 on any grid)
    path = truth.sample_path(149, 0.13, rng)
    t = 0.13 * np.arange(150)
    y = path @ truth.H[0]
    y = y + 0.1 * rng.standard_normal(t.size)
    fitted = fit(periodic(1.0, 0.8, 3.2), t, y, noise_variance=0.01)
    assert fitted.fit_info.success
    assert fitted.period == pytest.approx(3.0, rel=0.01)


def test_fit_nothing_to_fit_and_errors():
    raw = StateSpaceKernel([[-1.0]], [[1.0]], [[2.0]], [[1.0]])
    t, y = np.arange(5.0), np.zeros(5)
    fitted = fit(raw, t, y, noise_variance=0.5)
    assert fitted.fit_info.message == "nothing to fit" and fitted.fit_info.n_evaluations == 0
    assert fitted.fit_info.log_likelihood == pytest.approx(log_marginal_likelihood(raw, t, y, 0.5))
    learned = fit(raw, t, np.ones(5))
    assert learned.fit_info.noise_variance_learned and learned.fit_info.noise_variance > 0
    with pytest.raises(ValueError, match=r"fixed: unknown.*'period'"):
        fit(matern(0.5, 1.0, 1.0), t, y, fixed=["period"])
    with pytest.raises(ValueError, match="^noise_variance="):
        fit(matern(0.5, 1.0, 1.0), t, y, noise_variance=0.0)
    with pytest.raises(ValueError, match="sorted"):
        fit(matern(0.5, 1.0, 1.0), t[::-1], y)


def test_fit_stays_inside_the_valid_region():
    # The data want a lengthscale (0.4) that 3 harmonics cannot represent within the
    # default 1e-2 truncation error; the optimiser must stop at that wall, not crash.
    rng = np.random.default_rng(3)
    truth = periodic(1.0, 0.4, 2.0, harmonics=12)
    y = truth.sample_path(119, 0.1, rng) @ truth.H[0] + 0.05 * rng.standard_normal(120)
    fitted = fit(periodic(1.0, 1.5, 2.0, harmonics=3), 0.1 * np.arange(120), y, 0.0025)
    assert fitted.harmonics == 3
    assert 0.5 * fitted.max_truncation_error < fitted.truncation_error <= 1e-2
    assert fitted.period == pytest.approx(2.0, rel=1e-3)


def test_fit_warns_when_not_converged(matern_data):
    t, y = matern_data[0][:200], matern_data[1][:200]
    with pytest.warns(RuntimeWarning, match="did not converge"):
        fitted = fit(matern(2.5, 1.0, 1.0), t, y, max_iter=1)
    assert not fitted.fit_info.success and fitted.fit_info.n_iterations == 1
