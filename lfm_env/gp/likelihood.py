"""The Kalman likelihood of a state-space GP over irregular sample times, and its gradient.

:func:`log_marginal_likelihood` runs a Kalman filter over (irregular) sample times;
:func:`log_marginal_likelihood_and_grad` adds its gradient by the filter's sensitivity
equations (the kernel matrices' derivatives by central differences in log-hyperparameters).
:func:`lfm_env.gp.inference.fit` maximises it. :func:`driven_log_likelihood` scores
measured states that the force drives (a latent force model's calibration data);
:func:`lfm_env.gp.inference.fit_driven` maximises it.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from typing import Any

import numpy as np
import scipy.linalg

from lfm_env.gp.kernels.base import StateSpaceKernel, _check_float

#: Step in log-hyperparameters for the central differences of the kernel matrices.
_MATRIX_FD_STEP = 1e-5


def _check_data(times: Any, values: Any) -> tuple[np.ndarray, np.ndarray]:
    """Validate and return ``(times, values)`` as 1-D float arrays."""
    t = np.asarray(times, dtype=float)
    y = np.asarray(values, dtype=float)
    if t.ndim != 1 or t.size == 0:
        raise ValueError(f"times must be a non-empty 1-D array, got shape {t.shape}")
    if y.shape != t.shape:
        raise ValueError(f"values must have the shape of times {t.shape}, got {y.shape}")
    if not (np.all(np.isfinite(t)) and np.all(np.isfinite(y))):
        raise ValueError("times and values must be finite")
    if np.any(np.diff(t) < 0.0):
        raise ValueError("times must be sorted in non-decreasing order")
    return t, y


def _check_noise(noise_variance: Any) -> float:
    """Return ``noise_variance`` as a float >= 0, or raise ValueError."""
    return _check_float(noise_variance, "noise_variance", ">= 0")


def _matrix_derivatives(
    kernel: StateSpaceKernel, names: list[str]
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``d(F, H, Pinf) / d log(theta)`` for each name, by central differences.

    The kernels' matrices are smooth, cheap functions of their hyperparameters, so a
    step of 1e-5 in log-space leaves ~1e-10 relative error; the filter recursion
    that uses them is differentiated exactly.

    Returns:
        ``(dF, dH, dPinf)`` of shapes ``(k, p, p)``, ``(k, 1, p)``, ``(k, p, p)``.
    """
    hp = kernel.hyperparameters
    p = kernel.state_dim
    dF = np.zeros((len(names), p, p))
    dH = np.zeros((len(names), 1, p))
    dP = np.zeros((len(names), p, p))
    h = _MATRIX_FD_STEP
    for i, name in enumerate(names):
        up = kernel.with_hyperparameters(**{name: hp[name] * math.exp(h)})
        down = kernel.with_hyperparameters(**{name: hp[name] * math.exp(-h)})
        dF[i] = (up.F - down.F) / (2.0 * h)
        dH[i] = (up.H - down.H) / (2.0 * h)
        dP[i] = (up.Pinf - down.Pinf) / (2.0 * h)
    return dF, dH, dP


#: Step lengths within this relative distance share one discretisation (``np.arange``
#: grids produce several values of the "same" step that differ in the last bits).
_STEP_GROUP_RTOL = 1e-12

#: The filter covariance (and its derivatives) count as converged to their steady state
#: once one update changes them by less than this, relative to their size.
_STEADY_STATE_RTOL = 1e-13


def _group_steps(dts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Distinct step lengths (to ``_STEP_GROUP_RTOL``) and each step's index into them.

    Regular grids then need a single discretisation (and derivative), and the filter
    sees one repeated transition it can run in steady state. Merging changes a step by
    at most 1e-12 relative, far below the resolution of any sampled time stamp.
    """
    if dts.size == 0:
        return np.zeros(0), np.zeros(0, dtype=int)
    uniq, inverse = np.unique(dts, return_inverse=True)
    group = np.empty(uniq.size, dtype=int)
    reps: list[float] = []
    for i, step in enumerate(uniq):
        if reps and step - reps[-1] <= _STEP_GROUP_RTOL * reps[-1]:
            group[i] = len(reps) - 1
        else:
            reps.append(float(step))
            group[i] = len(reps) - 1
    return np.array(reps), group[inverse.ravel()]


def _converged(new: np.ndarray, old: np.ndarray) -> bool:
    """Whether each ``(p, p)`` slice of ``new`` equals ``old`` to ``_STEADY_STATE_RTOL``."""
    change = np.abs(new - old).reshape(new.shape[0], -1).max(axis=1)
    size = np.abs(new).reshape(new.shape[0], -1).max(axis=1)
    return bool(np.all(change <= _STEADY_STATE_RTOL * size))


def _transition_at(
    n: int, step_index: np.ndarray, trans: list[tuple[np.ndarray, ...] | None]
) -> tuple[int, tuple[np.ndarray, ...] | None]:
    """``(j, transition)`` that brings the filter to sample ``n``: step group ``j`` (-1 and
    no transition for the first sample; no transition for a repeated time either)."""
    j = step_index[n - 1] if n > 0 else -1
    return j, (trans[j] if n > 0 else None)


def _steady_run_end(steady: bool, step_index: np.ndarray, n: int, j: int) -> int | None:
    """Where a run of steady-state steps after sample ``n`` ends: the first index
    ``end > n + 1`` such that samples ``n + 1 .. end - 1`` all arrive by step ``j``, when the
    filter is steady and the next step is ``j`` too; ``None`` otherwise."""
    if not (steady and n + 1 <= step_index.size and step_index[n] == j):
        return None
    end = n + 1
    while end <= step_index.size and step_index[end - 1] == j:
        end += 1
    return end


def _steady_state_run(
    A: np.ndarray,
    dA: np.ndarray,
    h: np.ndarray,
    dh: np.ndarray,
    K: np.ndarray,
    dK: np.ndarray,
    m: np.ndarray,
    dm: np.ndarray,
    y: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Kalman mean recursion (and its sensitivities) with a frozen steady-state gain.

    Once the covariance has converged on a run of equal steps, ``P``, ``S``, ``K`` and
    their derivatives no longer change, and the filter is the linear time-invariant
    system ``x_n = Phi x_{n-1} + Gamma y_n`` in ``x = [m; dm_1; ...; dm_k]``
    (``m+ = (I - K h) A m + K y``, ``dm+_i = (I - K h) A dm_i + B_i m + dK_i y`` with
    ``B_i = dA_i - dK_i h A - K (dh_i A + h dA_i)``), whose innovations
    ``v = y - h A m``, ``dv_i = -(dh_i A + h dA_i) m - h A dm_i`` follow from the
    stored states in one product. One matrix-vector product per sample remains.

    Returns:
        ``(v, dv, m, dm)``: innovations ``(n,)``, their derivatives ``(n, k)``, and
        the final filtered mean and its derivatives.
    """
    p = h.size
    k = dh.shape[0]
    IKhA = A - np.outer(K, h @ A)
    hA = h @ A
    Phi = np.zeros(((k + 1) * p, (k + 1) * p))
    C = np.zeros((k + 1, (k + 1) * p))
    Phi[:p, :p] = IKhA
    C[0, :p] = -hA
    for i in range(k):
        rows = slice((i + 1) * p, (i + 2) * p)
        Phi[rows, rows] = IKhA
        Phi[rows, :p] = dA[i] - np.outer(dK[i], hA) - np.outer(K, dh[i] @ A + h @ dA[i])
        C[i + 1, :p] = -(dh[i] @ A + h @ dA[i])
        C[i + 1, rows] = -hA
    Gamma = np.concatenate([K, dK.ravel()])
    D = np.zeros(k + 1)
    D[0] = 1.0
    x = np.concatenate([m, dm.ravel()])
    drive = np.outer(y, Gamma)
    prev = np.empty((y.size, x.size))
    PhiT = Phi.T
    for n in range(y.size):
        prev[n] = x
        x = x @ PhiT + drive[n]
    out = prev @ C.T + np.outer(y, D)
    return out[:, 0], out[:, 1:], x[:p], x[p:].reshape(k, p)


def _kalman_log_likelihood(
    kernel: StateSpaceKernel,
    t: np.ndarray,
    y: np.ndarray,
    noise_variance: float,
    sens: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None = None,
) -> tuple[float, np.ndarray]:
    """Prediction-error decomposition of ``log p(y)`` by a Kalman filter.

    ``y_n = H z(t_n) + r_n``, ``r_n ~ N(0, noise_variance)``, ``z(t_0) ~ N(0, Pinf)``.
    If ``sens = (dF, dH, dPinf, dR)`` (leading axis: parameters) is given, the
    filter's sensitivity equations (derivatives of the mean, covariance and
    innovations; Sarkka 2013, Bayesian Filtering and Smoothing, ch. 12) carry
    ``d log p / d theta`` along.

    Returns:
        ``(log_likelihood, gradient)``; the gradient is empty without ``sens``.

    Raises:
        ValueError: if an innovation variance is not positive.
    """
    p = kernel.state_dim
    F, Pinf = kernel.F, kernel.Pinf
    n_par = 0 if sens is None else sens[0].shape[0]
    steps, step_index = _group_steps(np.diff(t))
    trans: list[tuple[np.ndarray, ...] | None] = []
    for dt in steps:
        if dt == 0.0:
            trans.append(None)  # repeated time: no prediction step
            continue
        A, Q = kernel.discretize(float(dt))
        if sens is None:
            trans.append((A, A.T.copy(), Q))
            continue
        dF, _, dPinf, _ = sens
        # Frechet derivatives of expm in all directions from one block-triangular expm:
        # expm([[F, dF_i], [0, F]] dt) has d expm(F dt)[dF_i dt] as its top-right block.
        M = np.zeros(((n_par + 1) * p, (n_par + 1) * p))
        for i in range(n_par + 1):
            M[i * p : (i + 1) * p, i * p : (i + 1) * p] = F * dt
        for i in range(n_par):
            M[:p, (i + 1) * p : (i + 2) * p] = dF[i] * dt
        top = scipy.linalg.expm(M)[:p, p:]
        dA = top.reshape(p, n_par, p).transpose(1, 0, 2)
        X = dA @ (Pinf @ A.T)
        dQ = dPinf - X - np.swapaxes(X, 1, 2) - A @ dPinf @ A.T
        dQ = 0.5 * (dQ + np.swapaxes(dQ, 1, 2))
        trans.append((A, A.T.copy(), np.concatenate([Q[None], dQ]), dA))
    if sens is None:
        return _kalman_value(kernel.H[0], Pinf, y, noise_variance, trans, step_index), np.zeros(0)
    return _kalman_value_and_grad(kernel.H[0], Pinf, y, noise_variance, trans, step_index, sens[1:])


def _innovation_variance(h: np.ndarray, Ph: np.ndarray, noise_variance: float, n: int) -> float:
    """``S = h P h' + R`` of sample ``n`` (``Ph = P h``), or a ValueError unless it is > 0."""
    S = float(h @ Ph) + noise_variance
    if not S > 0.0:
        raise ValueError(
            f"innovation variance {S:.3g} <= 0 at sample {n}: "
            "noise_variance = 0 with a (numerically) deterministic prediction"
        )
    return S


def _kalman_value(
    h: np.ndarray,
    Pinf: np.ndarray,
    y: np.ndarray,
    noise_variance: float,
    trans: list[tuple[np.ndarray, ...] | None],
    step_index: np.ndarray,
) -> float:
    """The filter without derivatives; see :func:`_kalman_log_likelihood`."""
    log_2pi = math.log(2.0 * math.pi)
    p = h.size
    no_par = np.zeros((0, p))
    m = np.zeros(p)
    P = np.array(Pinf)
    P_pred_prev: np.ndarray | None = None
    ll = 0.0
    n = 0
    while n < y.size:
        j, tr = _transition_at(n, step_index, trans)
        steady = False
        if tr is not None:
            A, AT, Q = tr
            m = A @ m
            P = A @ P @ AT + Q
            P = 0.5 * (P + P.T)
            steady = P_pred_prev is not None and _converged(P[None], P_pred_prev[None])
            P_pred_prev = P
        else:
            P_pred_prev = None
        Ph = P @ h
        S = _innovation_variance(h, Ph, noise_variance, n)
        v = float(y[n] - h @ m)
        ll -= 0.5 * (log_2pi + math.log(S) + v * v / S)
        K = Ph / S
        m = m + K * v
        P = P - np.outer(Ph, K)
        end = _steady_run_end(steady, step_index, n, j)
        if end is not None:
            vs, _, m, _ = _steady_state_run(
                A, no_par.reshape(0, p, p), h, no_par, K, no_par, m, no_par, y[n + 1 : end]
            )
            ll -= 0.5 * ((end - n - 1) * (log_2pi + math.log(S)) + float(vs @ vs) / S)
            P_pred_prev = None
            n = end
        else:
            n += 1
    return ll


def _kalman_value_and_grad(
    h: np.ndarray,
    Pinf: np.ndarray,
    y: np.ndarray,
    noise_variance: float,
    trans: list[tuple[np.ndarray, ...] | None],
    step_index: np.ndarray,
    sens: tuple[np.ndarray, np.ndarray, np.ndarray],
) -> tuple[float, np.ndarray]:
    """The filter with its sensitivity equations; see :func:`_kalman_log_likelihood`.

    The mean and covariance travel stacked with their derivatives, ``ms = [m; dm_i]``
    and ``Ps = [P; dP_i]``, so one batched product serves all parameters.
    """
    dH, dPinf, dR = sens
    dh = dH[:, 0, :]
    n_par = dh.shape[0]
    log_2pi = math.log(2.0 * math.pi)
    ms = np.zeros((n_par + 1, h.size))
    Ps = np.concatenate([np.asarray(Pinf)[None], dPinf])
    Ps_pred_prev: np.ndarray | None = None
    ll = 0.0
    grad = np.zeros(n_par)
    n = 0
    while n < y.size:
        j, tr = _transition_at(n, step_index, trans)
        steady = False
        if tr is not None:
            A, AT, Qs, dA = tr
            # d(A m) = dA m + A dm;  d(A P A^T) = dA P A^T + A dP A^T + A P dA^T
            X = dA @ (Ps[0] @ AT)
            ms_m = ms[0]
            ms = ms @ AT
            ms[1:] += dA @ ms_m
            Ps = A @ Ps @ AT + Qs
            Ps[1:] += X + np.swapaxes(X, 1, 2)
            Ps = 0.5 * (Ps + np.swapaxes(Ps, 1, 2))
            steady = Ps_pred_prev is not None and _converged(Ps, Ps_pred_prev)
            Ps_pred_prev = Ps
        else:
            Ps_pred_prev = None
        P, m = Ps[0], ms[0]
        PHs = Ps @ h  # [P h; dP_i h]
        Ph = PHs[0]
        S = _innovation_variance(h, Ph, noise_variance, n)
        dPh = PHs[1:] + dh @ P
        dS = dh @ Ph + dPh @ h + dR
        HM = ms @ h
        v = float(y[n] - HM[0])
        dv = -(dh @ m + HM[1:])
        ll -= 0.5 * (log_2pi + math.log(S) + v * v / S)
        grad -= 0.5 * (dS / S + (2.0 * v / S) * dv - (v * v / S**2) * dS)
        K = Ph / S
        dK = dPh / S - dS[:, None] * (K / S)[None, :]
        # m+ = m + K v;  P+ = P - Ph K^T;  dP+ = dP - dPh K^T - K dPh^T + dS K K^T
        ms[1:] += dK * v + dv[:, None] * K[None, :]
        ms[0] = m + K * v
        KdPh = K[None, :, None] * dPh[:, None, :]
        PHs[1:] = dPh  # reuse as [P h; d(P h)_i]
        Ps = Ps - PHs[:, :, None] * K[None, None, :]
        Ps[1:] += dS[:, None, None] * np.outer(K, K)[None] - KdPh
        end = _steady_run_end(steady, step_index, n, j)
        if end is not None:
            vs, dvs, m_end, dm_end = _steady_state_run(
                A, dA, h, dh, K, dK, ms[0], ms[1:], y[n + 1 : end]
            )
            count = end - n - 1
            ll -= 0.5 * (count * (log_2pi + math.log(S)) + float(vs @ vs) / S)
            grad -= 0.5 * (count * dS / S + (2.0 / S) * (vs @ dvs) - (float(vs @ vs) / S**2) * dS)
            ms = np.concatenate([m_end[None], dm_end])
            Ps_pred_prev = None
            n = end
        else:
            n += 1
    return ll, grad


def log_marginal_likelihood(
    kernel: StateSpaceKernel, times: Any, values: Any, noise_variance: float
) -> float:
    """Log marginal likelihood ``log p(y)`` of noisy samples of a zero-mean state-space GP.

    Model: ``y_n = w(t_n) + r_n``, ``w = H z`` stationary, ``r_n ~ N(0, noise_variance)``
    independent. A Kalman filter with :meth:`~StateSpaceKernel.discretize` between
    consecutive times gives it in ``O(n p^3)``; it equals the dense
    ``log N(y; 0, K + noise_variance I)`` with ``K_ij = H expm(F |t_i - t_j|) Pinf H^T``
    (the exact kernel for Matern, the approximation for SE and periodic).

    Steps equal to 1e-12 relative share one discretisation, and on a run of equal
    steps the filter freezes its gain once the predicted covariance has converged (to
    1e-13 relative), leaving one matrix-vector product per sample; together they
    change the result by < 1e-11 relative and make long regular series ~10x cheaper.

    Args:
        kernel: any state-space kernel.
        times: sample times [s], 1-D, sorted non-decreasing (irregular and repeated ok).
        values: observations, same shape [unit of w]; subtract a known mean first.
        noise_variance: measurement-noise variance >= 0 [unit of w, squared].

    Returns:
        The log-likelihood [nats].

    Raises:
        ValueError: on malformed data, a negative noise variance, or a degenerate
            innovation (``noise_variance = 0`` with a deterministic prediction).
    """
    t, y = _check_data(times, values)
    ll, _ = _kalman_log_likelihood(kernel, t, y, _check_noise(noise_variance))
    return ll


def _log_likelihood_and_grad(
    kernel: StateSpaceKernel,
    t: np.ndarray,
    y: np.ndarray,
    noise_variance: float,
    names: list[str],
    with_noise: bool,
) -> tuple[float, np.ndarray]:
    """Log-likelihood and its gradient in ``log`` of ``names`` (then of the noise)."""
    p = kernel.state_dim
    if names:
        dF, dH, dPinf = _matrix_derivatives(kernel, names)
    else:
        dF, dH, dPinf = np.zeros((0, p, p)), np.zeros((0, 1, p)), np.zeros((0, p, p))
    dR = np.zeros(len(names))
    if with_noise:
        dF = np.concatenate([dF, np.zeros((1, p, p))])
        dH = np.concatenate([dH, np.zeros((1, 1, p))])
        dPinf = np.concatenate([dPinf, np.zeros((1, p, p))])
        dR = np.append(dR, noise_variance)  # d R / d log R
    return _kalman_log_likelihood(kernel, t, y, noise_variance, (dF, dH, dPinf, dR))


def log_marginal_likelihood_and_grad(
    kernel: StateSpaceKernel,
    times: Any,
    values: Any,
    noise_variance: float,
    wrt: Iterable[str] | None = None,
) -> tuple[float, dict[str, float]]:
    """:func:`log_marginal_likelihood` and its gradient in log-hyperparameters.

    The gradient runs the Kalman filter's sensitivity equations alongside the filter
    (exact derivatives of ``A = expm(F dt)`` by the Frechet derivative, of
    ``Q = Pinf - A Pinf A^T``, the predictions, gains and innovations). Only the
    kernel matrices' own derivatives ``d(F, H, Pinf) / d log theta`` are taken by
    central differences (step 1e-5, ~1e-10 relative error), so the gradient agrees
    with central differences of the likelihood to ~1e-7 relative.

    Args:
        kernel: any state-space kernel.
        times: sample times [s], 1-D, sorted non-decreasing.
        values: observations, same shape [unit of w].
        noise_variance: measurement-noise variance > 0 [unit of w, squared].
        wrt: names to differentiate: keys of ``kernel.hyperparameters`` and/or
            ``"noise_variance"``; default all of them.

    Returns:
        ``(log_likelihood, {name: d log_likelihood / d log(name)})``.

    Raises:
        ValueError: as :func:`log_marginal_likelihood`, or on an unknown name in ``wrt``.
    """
    t, y = _check_data(times, values)
    r = _check_noise(noise_variance)
    hp = kernel.hyperparameters
    wanted = list(hp) + ["noise_variance"] if wrt is None else list(wrt)
    unknown = sorted(set(wanted) - set(hp) - {"noise_variance"})
    if unknown:
        raise ValueError(
            f"wrt: unknown name(s) {unknown}; allowed: {', '.join([*hp, 'noise_variance'])}"
        )
    names = [name for name in hp if name in wanted]
    with_noise = "noise_variance" in wanted
    if with_noise and r == 0.0:
        raise ValueError("noise_variance=0.0: its log-gradient needs noise_variance > 0")
    ll, grad = _log_likelihood_and_grad(kernel, t, y, r, names, with_noise)
    out = dict(zip(names, grad[: len(names)], strict=True))
    if with_noise:
        out["noise_variance"] = float(grad[-1])
    return ll, {name: float(g) for name, g in out.items()}


def _per_step(value: Any, T: int, m: int, name: str, square: bool) -> np.ndarray:
    """``value`` as ``(T, m, m)`` (square) or ``(T, m)``: one array per step, or one for all."""
    a = np.asarray(value, dtype=float)
    if square and a.shape == (m,):
        a = np.diag(a)  # variances
    if not square and m == 1 and a.shape == (T,):
        a = a[:, None]  # one state: one number per step
    one = (m, m) if square else (m,)
    if a.shape == one:
        a = np.broadcast_to(a, (T, *one))
    if a.shape != (T, *one) or not np.all(np.isfinite(a)):
        raise ValueError(f"{name}: expected finite numbers of shape {(T, *one)} or {one}")
    return a


def driven_log_likelihood(
    kernel: StateSpaceKernel,
    dt: float,
    measured: Any,
    offset: Any,
    gain: Any,
    measurement_variance: Any,
    process_covariance: Any,
    transition: Any = None,
) -> float:
    """Log-likelihood [nats] of measured states driven by a latent force, by a Kalman filter.

    The states ``x`` (``m`` of them) move by a known linear step and are pushed by the
    force ``w = H z``, a stationary state-space GP; each is measured with noise::

        x_{k+1} = Phi_k x_k + c_k + g_k w_k + e_k,   e_k ~ N(0, Q_k)
        z_{k+1} = A z_k + eta_k                      (the kernel's exact discretisation)
        y_k     = x_k + n_k,                         n_k ~ N(0, R)

    The filter runs on ``[x, z]`` from ``x_0 ~ N(y_0, R)`` (the first measurement decides
    it) and ``z_0 ~ N(0, Pinf)``; the result is ``log p(y_1, ..., y_T)``. Keeping the
    measurement noise in the model avoids the correlated (moving-average) noise of
    differenced measurements. This is the likelihood :func:`lfm_env.gp.inference.fit_driven`
    maximises (``lfm-calibrate`` builds ``Phi, c, g, Q`` from a system's force gain).

    Args:
        kernel: the force's state-space kernel (hyperparameters to score).
        dt: step [s] between measurements, > 0.
        measured: ``(T + 1, m)`` measurements ``y_0 .. y_T``.
        offset: ``(T, m)`` the known part ``c_k`` of each step.
        gain: ``(T, m)`` how one step moves the states per unit of force, ``g_k``.
        measurement_variance: ``R``: ``(m,)`` variances or ``(m, m)``.
        process_covariance: ``Q_k``: ``(m,)`` variances, ``(m, m)``, or ``(T, m, m)``.
        transition: ``Phi_k``: ``(T, m, m)`` or ``(m, m)``; ``None`` for the identity.

    Raises:
        ValueError: for arrays of the wrong shape or not finite, or an innovation
            covariance that is not positive definite.
    """
    y = np.asarray(measured, dtype=float)
    if y.ndim == 1:
        y = y[:, None]
    if y.ndim != 2 or y.shape[0] < 2 or not np.all(np.isfinite(y)):
        raise ValueError(f"measured: expected finite numbers of shape (T + 1, m), got {y.shape}")
    T, m = y.shape[0] - 1, y.shape[1]
    c = _per_step(offset, T, m, "offset", False)
    g = _per_step(gain, T, m, "gain", False)
    R = _per_step(measurement_variance, 1, m, "measurement_variance", True)[0]
    Q = _per_step(process_covariance, T, m, "process_covariance", True)
    Phi = None if transition is None else _per_step(transition, T, m, "transition", True)
    A_z, Q_z = kernel.discretize(float(dt))
    h = np.asarray(kernel.H, dtype=float).reshape(-1)
    p = A_z.shape[0]
    n = m + p
    A = np.zeros((n, n))
    A[:m, :m] = np.eye(m)
    A[m:, m:] = A_z
    Qs = np.zeros((n, n))
    Qs[m:, m:] = Q_z
    mean = np.zeros(n)
    mean[:m] = y[0]
    P = np.zeros((n, n))
    P[:m, :m] = R
    P[m:, m:] = kernel.Pinf
    total = 0.0
    log_2pi = math.log(2.0 * math.pi)
    for k in range(T):
        if Phi is not None:
            A[:m, :m] = Phi[k]
        A[:m, m:] = np.outer(g[k], h)
        Qs[:m, :m] = Q[k]
        mean = A @ mean
        mean[:m] += c[k]
        P = A @ P @ A.T + Qs
        S = P[:m, :m] + R
        innov = y[k + 1] - mean[:m]
        try:
            L = np.linalg.cholesky(0.5 * (S + S.T))
        except np.linalg.LinAlgError:
            raise ValueError(f"innovation covariance not positive definite at step {k}") from None
        white = scipy.linalg.solve_triangular(L, innov, lower=True)
        total -= 0.5 * (m * log_2pi + 2.0 * float(np.sum(np.log(np.diag(L)))) + white @ white)
        gain_k = scipy.linalg.cho_solve((L, True), P[:m, :]).T  # (n, m): P H' S^-1
        mean = mean + gain_k @ innov
        P = P - gain_k @ P[:m, :]
        P = 0.5 * (P + P.T)
    return float(total)


__all__ = ["driven_log_likelihood", "log_marginal_likelihood", "log_marginal_likelihood_and_grad"]
