"""Tests of the bootstrap particle filter and the resampling schemes."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from scipy.stats import norm

from controllers.estimators.particle_filter import (
    BOX_MULLER_MIN_SIZE,
    BoxMullerGenerator,
    ParticleFilter,
    UpdateInfo,
    gaussian_log_likelihood,
)
from controllers.estimators.resampling import (
    RESAMPLERS,
    effective_sample_size,
    multinomial,
    residual,
    stratified,
    systematic,
)

# --------------------------------------------------------------------------- helpers

# Linear-Gaussian test model: position/velocity with white-noise acceleration, noisy
# position measurement. Units are arbitrary but consistent (m, m/s, s).
DT = 0.5
A = np.array([[1.0, DT], [0.0, 1.0]])
Q = 0.5 * np.array([[DT**3 / 3.0, DT**2 / 2.0], [DT**2 / 2.0, DT]])
R_STD = 0.5
M0 = np.array([0.0, 1.0])
P0 = np.diag([0.5, 0.2])


def _linear_transition(particles: np.ndarray, u: object, rng: np.random.Generator) -> np.ndarray:
    chol = np.linalg.cholesky(Q)
    return particles @ A.T + rng.standard_normal(particles.shape) @ chol.T


def _linear_transition32(particles: np.ndarray, u: object, rng: np.random.Generator) -> np.ndarray:
    """The same model with single-precision noise (the filter's Box-Muller path)."""
    chol = np.linalg.cholesky(Q)
    noise = rng.standard_normal(particles.shape[::-1], dtype=np.float32)
    return particles @ A.T + (chol @ noise).T


def _simulate_measurements(seed: int, steps: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    x = M0 + np.linalg.cholesky(P0) @ rng.standard_normal(2)
    ys = np.empty(steps)
    for k in range(steps):
        x = A @ x + np.linalg.cholesky(Q) @ rng.standard_normal(2)
        ys[k] = x[0] + R_STD * rng.standard_normal()
    return ys


def _kalman(ys: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Exact filtering means (K, 2) and covariances (K, 2, 2), predict-then-update."""
    m, p = M0.copy(), P0.copy()
    h = np.array([1.0, 0.0])
    means, covs = [], []
    for y in ys:
        m = A @ m
        p = A @ p @ A.T + Q
        s = h @ p @ h + R_STD**2
        gain = p @ h / s
        m = m + gain * (y - h @ m)
        p = (np.eye(2) - np.outer(gain, h)) @ p
        means.append(m)
        covs.append(p)
    return np.array(means), np.array(covs)


def _make_linear_pf(
    n: int,
    seed: int,
    resampling: str = "systematic",
    ess_threshold: float | None = None,
    transition=_linear_transition,
) -> ParticleFilter:
    rng = np.random.default_rng(seed)
    p0 = M0 + rng.standard_normal((n, 2)) @ np.linalg.cholesky(P0).T
    return ParticleFilter(
        transition,
        gaussian_log_likelihood([R_STD], [0]),
        p0,
        rng,
        resampling=resampling,
        ess_threshold=ess_threshold,
    )


def _identity(particles: np.ndarray, u: object, rng: np.random.Generator) -> np.ndarray:
    return particles


def _flat(y: object, particles: np.ndarray) -> np.ndarray:
    return np.zeros(particles.shape[0])


# ----------------------------------------------------------- against Kalman filter


@pytest.mark.parametrize(
    ("resampling", "ess_threshold", "transition"),
    [
        ("systematic", None, _linear_transition),
        ("stratified", None, _linear_transition),
        ("residual", 0.5, _linear_transition),
        ("multinomial", None, _linear_transition),
        ("systematic", None, _linear_transition32),  # float32 noise: Box-Muller normals
    ],
)
def test_matches_kalman_filter_on_linear_gaussian_model(resampling, ess_threshold, transition):
    n, steps = 20000, 30
    ys = _simulate_measurements(seed=0, steps=steps)
    kf_means, kf_covs = _kalman(ys)
    pf = _make_linear_pf(n, 1, resampling, ess_threshold, transition)

    min_ess = float(n)
    for k, y in enumerate(ys):
        info = pf.step(None, y)
        assert not info.degenerate
        # Resampling noise accumulates, so the Monte-Carlo error of the mean scales with
        # the smallest effective sample size seen so far, not with n.
        min_ess = min(min_ess, info.ess)
        std = np.sqrt(np.diag(kf_covs[k]))
        tol = 5.0 * std / np.sqrt(min_ess) + 0.01 * std
        np.testing.assert_array_less(np.abs(pf.mean - kf_means[k]), tol)
        rel = np.abs(pf.covariance - kf_covs[k]) / np.sqrt(np.outer(np.diag(kf_covs[k]), std**2))
        assert rel.max() < 0.15, (k, rel)
        np.testing.assert_allclose(pf.std, np.sqrt(np.diag(pf.covariance)))
    # Guard against a vacuous tolerance: the filter stayed reasonably healthy.
    assert min_ess > 0.05 * n


# ------------------------------------------------------------------ noise draws


def test_box_muller_normals_are_standard_normal():
    from scipy import stats

    g = BoxMullerGenerator(np.random.PCG64(3))
    z = g.standard_normal((7, 30001), dtype=np.float32)  # an odd count: one unused sine
    assert z.shape == (7, 30001) and z.dtype == np.float32
    flat = z.ravel().astype(float)
    assert np.all(np.isfinite(flat))
    assert stats.kstest(flat, "norm").pvalue > 1e-3
    # Moments within ~5 standard errors of the normal's (210007 values).
    se = 1.0 / np.sqrt(flat.size)
    assert abs(flat.mean()) < 5 * se
    assert abs(flat.var() - 1.0) < 5 * np.sqrt(2.0) * se
    assert abs(stats.kurtosis(flat)) < 5 * np.sqrt(24.0) * se
    # Pairs from one uniform pair are uncorrelated (cos and sin halves).
    half = flat.size // 2
    assert abs(np.corrcoef(flat[:half], flat[half : 2 * half])[0, 1]) < 5 * np.sqrt(2) * se


def test_box_muller_generator_shares_the_stream_and_defers_small_draws():
    plain = np.random.default_rng(11)
    same = np.random.default_rng(11)
    g = BoxMullerGenerator(same.bit_generator)
    # Small or double-precision draws are NumPy's own, from the shared stream.
    np.testing.assert_array_equal(g.standard_normal(5), plain.standard_normal(5))
    np.testing.assert_array_equal(
        g.standard_normal(BOX_MULLER_MIN_SIZE - 1, dtype=np.float32),
        plain.standard_normal(BOX_MULLER_MIN_SIZE - 1, dtype=np.float32),
    )
    np.testing.assert_array_equal(g.standard_normal((3, 2000)), plain.standard_normal((3, 2000)))
    # A large float32 draw uses the transform and advances the shared bit generator.
    before = same.bit_generator.state["state"]["state"]
    a = g.standard_normal(4000, dtype=np.float32)
    assert same.bit_generator.state["state"]["state"] != before
    b = BoxMullerGenerator(np.random.default_rng(11).bit_generator)
    b.standard_normal(5), b.standard_normal(BOX_MULLER_MIN_SIZE - 1, dtype=np.float32)
    b.standard_normal((3, 2000))
    np.testing.assert_array_equal(b.standard_normal(4000, dtype=np.float32), a)


def test_filter_passes_the_transition_a_box_muller_generator_on_its_stream():
    seen = []

    def transition(particles, u, rng):
        seen.append(rng)
        return particles

    rng = np.random.default_rng(0)
    for fast in (True, False):
        pf = ParticleFilter(transition, _flat, np.zeros((10, 2)), rng, fast_normals=fast)
        pf.predict(None)
    assert isinstance(seen[0], BoxMullerGenerator)
    assert seen[0].bit_generator is rng.bit_generator
    assert seen[1] is rng


# ------------------------------------------------------------------ resamplers


def _test_weights(n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    w = rng.random(n) ** 3
    w[rng.random(n) < 0.2] = 0.0  # zero-weight particles must never be chosen
    w[0] = 0.0
    w[1] = 0.3  # one heavy particle, several copies expected
    return w / w.sum()


@pytest.mark.parametrize("name", sorted(RESAMPLERS))
def test_resampler_is_unbiased_and_well_formed(name):
    resample = RESAMPLERS[name]
    n, reps = 40, 20000
    w = _test_weights(n, seed=2)
    rng = np.random.default_rng(3)
    draws = np.stack([resample(w, rng) for _ in range(reps)])  # (reps, n)

    assert draws.dtype == np.intp
    assert draws.shape == (reps, n)
    assert draws.min() >= 0 and draws.max() < n
    assert np.all(np.diff(draws, axis=1) >= 0)  # documented ascending order
    offsets = (np.arange(reps) * n)[:, None]
    counts = np.bincount((draws + offsets).ravel(), minlength=reps * n).reshape(reps, n)
    assert np.all(counts[:, w == 0.0] == 0)

    expected = n * w
    # Multinomial counts have the largest variance of the four schemes, n w (1 - w).
    sem = np.sqrt(n * w * (1.0 - w) / reps)
    np.testing.assert_array_less(np.abs(counts.mean(axis=0) - expected), 5.0 * sem + 1e-12)

    floor = np.floor(expected)
    if name == "systematic":
        assert np.all(np.abs(counts - expected) < 1.0)
    elif name == "stratified":
        assert np.all(np.abs(counts - expected) < 2.0)
    elif name == "residual":
        n_rest = n - int(floor.sum())
        assert np.all(counts >= floor)
        assert np.all(counts <= floor + n_rest)


@pytest.mark.parametrize("name", sorted(RESAMPLERS))
def test_resampler_edge_cases(name):
    resample = RESAMPLERS[name]
    rng = np.random.default_rng(4)
    np.testing.assert_array_equal(resample(np.array([1.0]), rng), [0])
    one_hot = np.zeros(7)
    one_hot[4] = 1.0
    np.testing.assert_array_equal(resample(one_hot, rng), np.full(7, 4))
    uniform = np.full(5, 0.2)
    assert np.bincount(resample(uniform, rng), minlength=5).sum() == 5
    # Round-off in the normalisation is tolerated (last cumsum entry forced to 1).
    w = np.full(1000, 1.0 / 1000.0) * (1.0 - 1e-12)
    idx = resample(w, rng)
    assert idx.shape == (1000,) and idx.max() < 1000
    with pytest.raises(ValueError, match="weights"):
        resample(np.array([0.5, 0.6]), rng)
    with pytest.raises(ValueError, match="weights"):
        resample(np.array([1.5, -0.5]), rng)
    with pytest.raises(ValueError, match="weights"):
        resample(np.array([np.nan, 1.0]), rng)
    with pytest.raises(ValueError, match="weights"):
        resample(np.ones((2, 2)) / 4, rng)


def test_systematic_and_stratified_match_inverse_cdf_definition():
    # The O(n) counting implementations must reproduce searchsorted on the textbook
    # points (j + U) / n and (j + U_j) / n exactly.
    n = 500
    w = _test_weights(n, seed=5)
    cdf = np.cumsum(w)
    cdf[-1] = 1.0
    for seed in range(20):
        u = np.random.default_rng(seed).random()
        ref = np.searchsorted(cdf, (np.arange(n) + u) / n, side="right")
        np.testing.assert_array_equal(systematic(w, np.random.default_rng(seed)), ref)
        us = np.random.default_rng(seed).random(n)
        ref = np.searchsorted(cdf, (np.arange(n) + us) / n, side="right")
        np.testing.assert_array_equal(stratified(w, np.random.default_rng(seed)), ref)


def test_resampler_functions_are_registered():
    assert RESAMPLERS == {
        "systematic": systematic,
        "stratified": stratified,
        "residual": residual,
        "multinomial": multinomial,
    }


def test_effective_sample_size():
    assert effective_sample_size(np.zeros(10)) == pytest.approx(10.0)
    assert effective_sample_size(np.full(10, -1e5)) == pytest.approx(10.0)  # shift-invariant
    lw = np.full(6, -np.inf)
    lw[2] = 3.0
    assert effective_sample_size(lw) == pytest.approx(1.0)
    lw[:3] = 0.0
    assert effective_sample_size(lw) == pytest.approx(3.0)
    w = np.array([0.5, 0.25, 0.25])
    assert effective_sample_size(np.log(w)) == pytest.approx(1.0 / np.sum(w**2))
    assert effective_sample_size(np.full(4, -np.inf)) == 0.0
    assert effective_sample_size(np.array([np.nan, 0.0])) == 0.0


# ---------------------------------------------------------- gaussian likelihood


def test_gaussian_log_likelihood_matches_scipy():
    rng = np.random.default_rng(6)
    particles = rng.normal(size=(50, 7))
    std = np.array([0.15, 0.15, 0.15, np.deg2rad(0.5)])
    dims = [3, 0, 2, 1]  # non-contiguous, permuted on purpose
    y = rng.normal(size=4)
    ll = gaussian_log_likelihood(std, dims)(y, particles)
    ref = norm.logpdf(y, loc=particles[:, dims], scale=std).sum(axis=1)
    assert ll.shape == (50,)
    np.testing.assert_allclose(ll, ref, rtol=1e-12, atol=1e-9)
    with pytest.raises(ValueError, match="y"):
        gaussian_log_likelihood(std, dims)(np.zeros(3), particles)
    with pytest.raises(ValueError, match="observed_dims"):
        gaussian_log_likelihood([1.0, 1.0], [0])
    with pytest.raises(ValueError, match="measurement_std"):
        gaussian_log_likelihood([1.0, 0.0], [0, 1])


# ------------------------------------------------------------ ess_threshold rule


def _half_dead(y: object, particles: np.ndarray) -> np.ndarray:
    # Half the particles impossible, the rest equally likely: ESS exactly n / 2.
    out = np.zeros(particles.shape[0])
    out[::2] = -np.inf
    return out


def test_ess_threshold_controls_resampling():
    n = 1000
    p0 = np.arange(n, dtype=float)[:, None] * np.ones((1, 3))
    rng = np.random.default_rng(7)

    pf = ParticleFilter(_identity, _flat, p0, rng, ess_threshold=0.5)
    info = pf.update(None)
    assert info == UpdateInfo(ess=n, resampled=False, degenerate=False, max_log_likelihood=0.0)
    np.testing.assert_array_equal(pf.particles, p0)  # untouched

    # ESS = n/2 is not below 0.4 n: weights change, particles stay.
    pf = ParticleFilter(_identity, _half_dead, p0, rng, ess_threshold=0.4)
    info = pf.update(None)
    assert info.ess == pytest.approx(n / 2) and not info.resampled
    assert pf.ess == pytest.approx(n / 2)
    np.testing.assert_array_equal(pf.particles, p0)
    np.testing.assert_allclose(pf.weights[1::2], 2.0 / n)
    assert np.all(pf.weights[::2] == 0.0) and np.all(pf.log_weights[::2] == -np.inf)
    np.testing.assert_allclose(pf.mean, p0[1::2].mean(axis=0))
    # Predict keeps the weights, and the next update multiplies onto them: killing the
    # same (already dead) half again leaves ESS at n/2 instead of resetting it to n.
    pf.predict(None)
    again = pf.update(None)
    assert again.ess == pytest.approx(n / 2) and not again.resampled
    np.testing.assert_allclose(pf.weights[1::2], 2.0 / n)

    # ESS = n/2 is below 0.6 n: resample, weights uniform again, dead particles gone.
    pf = ParticleFilter(_identity, _half_dead, p0, rng, ess_threshold=0.6)
    info = pf.update(None)
    assert info.resampled and pf.n_resampled == 1
    np.testing.assert_allclose(pf.weights, 1.0 / n)
    assert pf.ess == pytest.approx(n)
    assert np.all(pf.particles[:, 0] % 2 == 1)  # only odd (alive) particles survive
    np.testing.assert_allclose(pf.mean, p0[1::2].mean(axis=0))  # systematic: exact

    # None: resample after every update, however high the ESS.
    pf = ParticleFilter(_identity, _flat, p0, rng)
    for _ in range(3):
        assert pf.update(None).resampled
    assert pf.n_resampled == 3 and pf.n_updates == 3


def test_non_uniform_weights_give_weighted_moments():
    p0 = np.array([[0.0, 1.0], [2.0, 3.0], [4.0, -1.0]])
    lw_target = np.log(np.array([0.2, 0.3, 0.5]))

    def ll(y: object, particles: np.ndarray) -> np.ndarray:
        return lw_target + 7.0  # constant offset must not matter

    pf = ParticleFilter(_identity, ll, p0, np.random.default_rng(8), ess_threshold=0.1)
    pf.update(None)
    w = np.exp(lw_target)
    mean = w @ p0
    cov = (p0 - mean).T @ ((p0 - mean) * w[:, None])
    np.testing.assert_allclose(pf.weights, w)
    np.testing.assert_allclose(pf.log_weights, lw_target)
    np.testing.assert_allclose(pf.mean, mean)
    np.testing.assert_allclose(pf.covariance, cov)
    lower, upper = pf.band(2.0)
    np.testing.assert_allclose(lower, mean - 2.0 * np.sqrt(np.diag(cov)))
    np.testing.assert_allclose(upper, mean + 2.0 * np.sqrt(np.diag(cov)))
    assert pf.last_info.max_log_likelihood == pytest.approx(np.log(0.5) + 7.0)


# --------------------------------------------------------------- degeneracy


@pytest.mark.parametrize("bad_y", [np.nan, 1e300], ids=["nan", "outlier"])
@pytest.mark.parametrize("ess_threshold", [None, 0.5])
def test_degenerate_measurement_is_skipped(bad_y, ess_threshold):
    n, steps = 2000, 10
    ys = _simulate_measurements(seed=9, steps=steps)
    kf_means, kf_covs = _kalman(ys)
    pf = _make_linear_pf(n, seed=10, ess_threshold=ess_threshold)
    for y in ys[:5]:
        pf.step(None, y)

    pf.predict(None)
    predicted_mean, predicted_cov = pf.mean, pf.covariance
    predicted_particles = pf.particles.copy()
    predicted_weights = pf.weights
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no RuntimeWarning either
        info = pf.update(np.array([bad_y]))
    assert info.degenerate and not info.resampled and info.ess == 0.0
    assert pf.last_info is info and pf.n_degenerate == 1
    # The measurement carried no information: the prediction is kept as it was.
    np.testing.assert_array_equal(pf.particles, predicted_particles)
    np.testing.assert_array_equal(pf.weights, predicted_weights)
    if ess_threshold is None:  # resampled every step: the kept weights are uniform
        np.testing.assert_allclose(pf.weights, 1.0 / n)
    np.testing.assert_array_equal(pf.mean, predicted_mean)
    np.testing.assert_array_equal(pf.covariance, predicted_cov)
    for value in (pf.mean, pf.covariance, pf.std, *pf.band()):
        assert np.all(np.isfinite(value))

    # Back to normal measurements: the filter works again.
    info = pf.update(np.array([ys[5]]))
    assert not info.degenerate and info.ess > 1.0
    assert pf.n_degenerate == 1
    for k in range(6, steps):
        assert not pf.step(None, ys[k]).degenerate
    std = np.sqrt(np.diag(kf_covs[-1]))
    np.testing.assert_array_less(np.abs(pf.mean - kf_means[-1]), std)  # sane estimate


def test_nan_log_likelihood_entries_count_as_impossible():
    p0 = np.arange(8, dtype=float)[:, None]

    def ll(y: object, particles: np.ndarray) -> np.ndarray:
        out = np.zeros(8)
        out[:7] = np.nan
        return out

    pf = ParticleFilter(_identity, ll, p0, np.random.default_rng(11))
    info = pf.update(None)
    assert not info.degenerate and info.ess == pytest.approx(1.0)
    np.testing.assert_array_equal(pf.particles[:, 0], np.full(8, 7.0))
    assert info.max_log_likelihood == 0.0


def test_non_finite_predicted_particles_are_dropped():
    p0 = np.arange(10, dtype=float)[:, None] * np.ones((1, 2))

    def poison(particles: np.ndarray, u: object, rng: np.random.Generator) -> np.ndarray:
        out = particles + 1.0
        out[:3, 1] = np.nan
        out[3, 0] = np.inf
        return out

    pf = ParticleFilter(poison, _flat, p0, np.random.default_rng(12))
    pf.predict(None)
    assert np.all(np.isfinite(pf.mean)) and np.all(np.isfinite(pf.covariance))
    np.testing.assert_allclose(pf.mean, (p0[4:] + 1.0).mean(axis=0))
    assert np.all(pf.weights[:4] == 0.0)
    pf.update(None)
    assert np.all(pf.particles[:, 0] >= 5.0)  # the dropped ones were not resampled

    def all_nan(particles: np.ndarray, u: object, rng: np.random.Generator) -> np.ndarray:
        return np.full_like(particles, np.nan)

    pf = ParticleFilter(all_nan, _flat, p0, np.random.default_rng(12))
    with pytest.raises(FloatingPointError, match="transition"):
        pf.predict(None)


# ------------------------------------------------------------- bad arguments


def test_bad_arguments_raise_value_error_naming_the_field():
    p0 = np.zeros((10, 2))
    rng = np.random.default_rng(13)
    with pytest.raises(ValueError, match="resampling.*multinomial"):
        ParticleFilter(_identity, _flat, p0, rng, resampling="bootstrap")
    for bad in (0.0, -0.1, 1.5, np.nan, "high"):
        with pytest.raises(ValueError, match="ess_threshold"):
            ParticleFilter(_identity, _flat, p0, rng, ess_threshold=bad)
    ParticleFilter(_identity, _flat, p0, rng, ess_threshold=1.0)  # closed at 1
    for bad in (np.zeros(10), np.zeros((2, 3, 4)), np.zeros((0, 2))):
        with pytest.raises(ValueError, match="initial_particles"):
            ParticleFilter(_identity, _flat, bad, rng)
    p_nan = p0.copy()
    p_nan[3, 1] = np.nan
    with pytest.raises(ValueError, match="initial_particles"):
        ParticleFilter(_identity, _flat, p_nan, rng)
    with pytest.raises(TypeError, match="rng"):
        ParticleFilter(_identity, _flat, p0, np.random.RandomState(0))

    def drops_a_column(particles: np.ndarray, u: object, rng: np.random.Generator):
        return particles[:, :1]

    pf = ParticleFilter(drops_a_column, _flat, p0, rng)
    with pytest.raises(ValueError, match=r"transition.*\(10, 1\).*\(10, 2\)"):
        pf.predict(None)

    pf = ParticleFilter(_identity, lambda y, p: np.zeros(3), p0, rng)
    with pytest.raises(ValueError, match="log_likelihood"):
        pf.update(None)


# ------------------------------------------------------ determinism, API misc


def _run(seed: int) -> tuple[np.ndarray, np.ndarray]:
    ys = _simulate_measurements(seed=14, steps=8)
    pf = _make_linear_pf(3000, seed=seed)
    for y in ys:
        pf.step(None, y)
    return pf.mean, pf.covariance


def test_same_seed_gives_identical_estimates():
    m1, c1 = _run(seed=15)
    m2, c2 = _run(seed=15)
    np.testing.assert_array_equal(m1, m2)
    np.testing.assert_array_equal(c1, c2)
    m3, _ = _run(seed=16)
    assert not np.array_equal(m1, m3)


def test_step_orders_and_reset():
    ys = _simulate_measurements(seed=17, steps=3)
    a = _make_linear_pf(500, seed=18)
    b = _make_linear_pf(500, seed=18)
    a.step(None, ys[0])
    b.predict(None)
    b.update(ys[0])
    np.testing.assert_array_equal(a.particles, b.particles)

    c = _make_linear_pf(500, seed=18)
    d = _make_linear_pf(500, seed=18)
    c.update_then_predict(ys[0], None)
    d.update(ys[0])
    d.predict(None)
    np.testing.assert_array_equal(c.particles, d.particles)

    c.update(np.array([np.nan]))
    assert c.n_degenerate == 1 and c.n_updates == 2
    new = np.ones((20, 3))
    c.reset(new)
    assert c.n_particles == 20 and c.dim == 3
    assert c.n_degenerate == 0 and c.n_updates == 0 and c.last_info is None
    np.testing.assert_allclose(c.weights, 1.0 / 20)
    np.testing.assert_allclose(c.mean, np.ones(3), rtol=1e-14)
    new[0, 0] = 5.0  # the filter holds a copy
    assert c.particles[0, 0] == 1.0
    with pytest.raises(ValueError):
        c.particles[0, 0] = 2.0  # read-only view


def test_unlikely_but_finite_measurement_is_used_not_skipped():
    pf = _make_linear_pf(2000, seed=19)
    pf.predict(None)
    info = pf.update(np.array([50.0]))  # ~50 prior std away, log-likelihoods finite
    assert not info.degenerate and info.resampled and pf.n_degenerate == 0
    assert 1.0 <= info.ess < 5.0  # weights collapse onto the closest particles
    assert np.isfinite(info.max_log_likelihood)
    assert np.all(np.isfinite(pf.mean)) and np.all(np.isfinite(pf.covariance))


# ------------------------------------------------------------------ particle layout


@pytest.mark.parametrize("resampling", ["systematic", "residual"])
def test_a_column_major_transition_gives_the_row_major_filter(resampling: str) -> None:
    """The filter keeps a column-major transition's particles as they come (as
    LatentForceModel.transition returns them): same particles, weights and estimates as
    the row-major filter on the same draws, with and without resampling every step."""

    def column_major(particles, u, rng):
        return np.asfortranarray(_linear_transition(particles, u, rng))

    ess = None if resampling == "systematic" else 0.5
    rows = _make_linear_pf(400, 5, resampling, ess)
    cols = _make_linear_pf(400, 5, resampling, ess, transition=column_major)
    for y in np.linspace(-1.0, 1.0, 12):
        a, b = rows.step(0.1, y), cols.step(0.1, y)
        assert a == b
        assert rows.particles.flags.c_contiguous and cols.particles.flags.f_contiguous
        np.testing.assert_array_equal(rows.particles, cols.particles)
        np.testing.assert_array_equal(rows.weights, cols.weights)
        np.testing.assert_allclose(rows.mean, cols.mean, rtol=0, atol=1e-14)
        np.testing.assert_allclose(rows.covariance, cols.covariance, rtol=0, atol=1e-14)
    assert rows.n_resampled == cols.n_resampled > 0


def test_a_strided_transition_result_is_copied_to_row_major() -> None:
    def strided(particles, u, rng):
        out = _linear_transition(particles, u, rng)
        wide = np.zeros((out.shape[0], 2 * out.shape[1]))
        wide[:, ::2] = out
        return wide[:, ::2]  # neither row- nor column-major

    pf = _make_linear_pf(50, 2, transition=strided)
    ref = _make_linear_pf(50, 2)
    pf.predict(0.1)
    ref.predict(0.1)
    assert pf.particles.flags.c_contiguous
    np.testing.assert_array_equal(pf.particles, ref.particles)
