"""The likelihood of measured states driven by a latent force
(:func:`lfm_env.gp.likelihood.driven_log_likelihood`) and its fit (``fit_driven``)."""

from __future__ import annotations

import numpy as np
import pytest

from lfm_env.gp import driven_log_likelihood, fit_driven, matern


def dense_log_likelihood(kernel, dt, measured, offset, gain, R, Q, Phi):
    """Independent check: the joint Gaussian of y_1..y_T, written out densely.

    The stacked state s = [x, z] follows s+ = F_k s + d_k + noise from s_0 ~ N([y_0, 0],
    diag(R, Pinf)); the covariance of s_i and s_j is Phi(i,0) P0 Phi(j,0)' plus the
    noise of each common step carried forward.
    """
    A_z, Q_z = kernel.discretize(dt)
    h = np.asarray(kernel.H, dtype=float).reshape(-1)
    T, m = offset.shape
    p = A_z.shape[0]
    n = m + p
    F, D, W = [], [], []
    for k in range(T):
        Fk = np.zeros((n, n))
        Fk[:m, :m] = Phi[k]
        Fk[:m, m:] = np.outer(gain[k], h)
        Fk[m:, m:] = A_z
        Wk = np.zeros((n, n))
        Wk[:m, :m] = Q[k]
        Wk[m:, m:] = Q_z
        F.append(Fk)
        D.append(np.concatenate([offset[k], np.zeros(p)]))
        W.append(Wk)

    def carry(i, j):  # the product F_{i-1} ... F_j (identity for i == j)
        M = np.eye(n)
        for k in range(j, i):
            M = F[k] @ M
        return M

    P0 = np.zeros((n, n))
    P0[:m, :m] = R
    P0[m:, m:] = kernel.Pinf
    mean = [np.concatenate([measured[0], np.zeros(p)])]
    for k in range(T):
        mean.append(F[k] @ mean[-1] + D[k])
    cov = np.zeros((T * m, T * m))
    for i in range(1, T + 1):
        for j in range(1, T + 1):
            c = carry(i, 0) @ P0 @ carry(j, 0).T
            for k in range(min(i, j)):
                c += carry(i, k + 1) @ W[k] @ carry(j, k + 1).T
            cov[(i - 1) * m : i * m, (j - 1) * m : j * m] = c[:m, :m] + (R if i == j else 0.0)
    resid = (measured[1:] - np.array(mean)[1:, :m]).reshape(-1)
    sign, logdet = np.linalg.slogdet(cov)
    assert sign > 0
    return -0.5 * (T * m * np.log(2 * np.pi) + logdet + resid @ np.linalg.solve(cov, resid))


@pytest.mark.parametrize("m", [1, 2])
def test_the_filter_equals_the_dense_gaussian(m):
    rng = np.random.default_rng(3)
    T, dt = 12, 0.2
    kernel = matern(2.5, 1.7, 1.3)
    measured = rng.normal(size=(T + 1, m))
    offset = rng.normal(size=(T, m)) * 0.1
    gain = rng.uniform(0.1, 0.3, size=(T, m))
    R = np.diag(rng.uniform(0.01, 0.05, m))
    Q = np.array([np.diag(rng.uniform(1e-4, 1e-3, m)) for _ in range(T)])
    Phi = np.array([np.eye(m) + 0.05 * rng.normal(size=(m, m)) for _ in range(T)])
    kf = driven_log_likelihood(kernel, dt, measured, offset, gain, np.diag(R), Q, Phi)
    dense = dense_log_likelihood(kernel, dt, measured, offset, gain, R, Q, Phi)
    assert kf == pytest.approx(dense, rel=1e-9)
    # No transition is the identity.
    eye = np.broadcast_to(np.eye(m), (T, m, m))
    assert driven_log_likelihood(kernel, dt, measured, offset, gain, R, Q) == pytest.approx(
        dense_log_likelihood(kernel, dt, measured, offset, gain, R, Q, eye), rel=1e-9
    )


def test_bad_shapes_name_the_argument():
    k = matern(1.5, 1.0, 1.0)
    with pytest.raises(ValueError, match="gain: expected finite numbers of shape"):
        driven_log_likelihood(k, 0.1, np.zeros((4, 1)), np.zeros((3, 1)), np.zeros((2, 1)), 1, 1)
    with pytest.raises(ValueError, match="measured"):
        driven_log_likelihood(k, 0.1, np.zeros((1, 1)), np.zeros((0, 1)), np.zeros((0, 1)), 1, 1)


def simulate(kernel, T, dt, rng, r=0.05, q=0.005):
    """A speed pushed by the force under random inputs: v+ = v + (a + w) dt + e."""
    A_z, Q_z = kernel.discretize(dt)
    h = np.asarray(kernel.H).reshape(-1)
    z = np.linalg.cholesky(kernel.Pinf) @ rng.standard_normal(len(h))
    v, a = 1.0, rng.uniform(-2, 2, T)
    measured = [v + r * rng.standard_normal()]
    for k in range(T):
        v = v + (a[k] + h @ z) * dt + q * rng.standard_normal()
        z = A_z @ z + np.linalg.cholesky(Q_z + 1e-15 * np.eye(len(h))) @ rng.standard_normal(len(h))
        measured.append(v + r * rng.standard_normal())
    return {
        "measured": np.array(measured)[:, None],
        "offset": (a * dt)[:, None],
        "gain": np.full((T, 1), dt),
        "measurement_variance": [r**2],
        "process_covariance": [q**2],
    }


def test_fit_driven_recovers_the_hyperparameters_within_their_standard_errors():
    truth = matern(2.5, 4.0, 4.0)
    rng = np.random.default_rng(7)
    episodes = [simulate(truth, 150, 0.2, rng) for _ in range(12)]
    fitted = fit_driven(matern(2.5, 1.0, 1.0), 0.2, episodes)
    info = fitted.fit_info
    assert info.success
    for name in ("variance", "lengthscale"):
        se = info.std_errors[name]
        assert np.isfinite(se) and se > 0
        assert abs(np.log(info.hyperparameters[name] / 4.0)) < 3.5 * se, (name, info)


def test_fit_driven_needs_episodes_and_known_names():
    with pytest.raises(ValueError, match="episodes"):
        fit_driven(matern(2.5, 1.0, 1.0), 0.2, [])
    with pytest.raises(ValueError, match="unknown"):
        fit_driven(matern(2.5, 1.0, 1.0), 0.2, [{}], names=("period",))
