"""State-space (SDE) representation of temporal Gaussian processes.

A stationary GP ``w(t)`` in time with a rational spectral density is the output
``w = H z`` of the linear time-invariant SDE (Hartikainen & Sarkka 2010)::

    dz/dt = F z + L xi(t),    E[xi(t) xi(s)^T] = Qc delta(t - s),

started from (or run long enough to reach) its stationary covariance ``Pinf``,
which solves ``F Pinf + Pinf F^T + L Qc L^T = 0``. Time is in seconds [s]; the
output ``w`` carries the unit of the modelled quantity (in the case study the
latent force, [m/s^2]). For :class:`Matern` state component ``i`` carries that
unit per ``[s^i]`` (the ``i``-th time derivative of ``w``); the other kernels use
better-conditioned state bases, and only ``w = H z`` has a fixed meaning.

:class:`StateSpaceKernel` holds the matrices and does the generic work
(discretisation, sampling, covariance check); subclasses only build the matrices
from hyperparameters:

* :class:`Matern` (half-integer ``nu``, exact),
* :class:`SquaredExponential` (Taylor-series spectral approximation of order ``N``),
* :class:`Periodic` (truncated Bessel series of resonators),
* :class:`SumKernel` / :class:`ProductKernel`, made by ``k1 + k2`` and ``k1 * k2``.

Inference (likelihood and fitting) lives in :mod:`lfm_env.gp.inference`.
"""

from __future__ import annotations

import functools
import math
from typing import Any

import numpy as np
import scipy.linalg
import scipy.special

DISCRETIZATION_METHODS = ("exact", "euler_maruyama")
START_MODES = ("stationary", "zero")


def _frozen_copy(value: Any, name: str, ndim: int = 2) -> np.ndarray:
    """Float copy of ``value`` checked to be finite with ``ndim`` dims, set read-only."""
    arr = np.array(value, dtype=float, copy=True)
    if arr.ndim != ndim:
        raise ValueError(f"{name} must be a {ndim}-D array, got shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} must contain only finite values")
    arr.flags.writeable = False
    return arr


def _check_dt(dt: Any) -> float:
    """Return ``dt`` [s] as a float, or raise ValueError naming ``dt``."""
    try:
        dt_f = float(dt)
    except (TypeError, ValueError):
        raise ValueError(f"dt={dt!r}: must be a finite number > 0 [s]") from None
    if not (math.isfinite(dt_f) and dt_f > 0.0):
        raise ValueError(f"dt={dt!r}: must be finite and > 0 [s]")
    return dt_f


def _check_positive(value: Any, name: str) -> float:
    """Return ``value`` as a float, or raise ValueError naming ``name`` and the allowed range."""
    # bool is an int subclass; a True variance is almost certainly a bug, not 1.0.
    if isinstance(value, bool):
        raise ValueError(f"{name}={value!r}: must be a finite float > 0")
    try:
        value_f = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name}={value!r}: must be a finite float > 0") from None
    if not (math.isfinite(value_f) and value_f > 0.0):
        raise ValueError(f"{name}={value!r}: must be finite and > 0")
    return value_f


def _psd_factor(cov: np.ndarray) -> np.ndarray:
    """Factor ``S`` with ``S S^T = cov`` for a symmetric PSD, possibly singular, ``cov``.

    Cholesky fails on the rank-one Euler-Maruyama noise covariance and on exact
    ones that are numerically singular for small ``dt``, so use the
    eigendecomposition and clip the rounding-level negative eigenvalues.
    """
    eigval, eigvec = np.linalg.eigh(0.5 * (cov + cov.T))
    return eigvec * np.sqrt(np.clip(eigval, 0.0, None))


class StateSpaceKernel:
    """Linear time-invariant SDE whose output ``w = H z`` is a stationary GP.

    Instances are immutable: the matrices are private read-only copies and
    attributes cannot be reassigned after construction. Subclasses set their
    own hyperparameter attributes *before* calling ``super().__init__``, which
    freezes the instance.

    Attributes:
        F: feedback matrix, shape ``(p, p)`` [1/s].
        L: noise effect matrix, shape ``(p, m)`` (``m = 1`` for a single kernel).
        Qc: white-noise spectral density, shape ``(m, m)``.
        H: output matrix, shape ``(1, p)``.
        Pinf: stationary state covariance, shape ``(p, p)``.
        fit_info: :class:`FitInfo` on a kernel returned by :func:`fit` (the fitted
            noise variance, log-likelihood, optimiser status), else None.
    """

    fit_info: Any = None  # lfm_env.gp.inference.FitInfo after fit(), else None
    F: np.ndarray
    L: np.ndarray
    Qc: np.ndarray
    H: np.ndarray
    Pinf: np.ndarray

    def __init__(
        self,
        F: Any,
        L: Any,
        Qc: Any,
        H: Any,
        Pinf: Any | None = None,
    ) -> None:
        """Store the SDE matrices.

        Args:
            F: feedback matrix ``(p, p)`` [1/s].
            L: noise effect matrix ``(p, m)``.
            Qc: white-noise spectral density ``(m, m)``, symmetric PSD.
            H: output matrix ``(1, p)``.
            Pinf: stationary covariance ``(p, p)``. If None it is obtained from
                the continuous Lyapunov equation, which needs ``F`` to be stable;
                kernels with marginally stable ``F`` (e.g. periodic ones) must pass it.

        Raises:
            ValueError: on non-finite entries or inconsistent shapes.
        """
        F_ = _frozen_copy(F, "F")
        L_ = _frozen_copy(L, "L")
        Qc_ = _frozen_copy(Qc, "Qc")
        H_ = _frozen_copy(H, "H")
        p = F_.shape[0]
        if F_.shape != (p, p) or p == 0:
            raise ValueError(f"F must be square and non-empty, got shape {F_.shape}")
        m = L_.shape[1]
        if L_.shape[0] != p:
            raise ValueError(f"L must have shape ({p}, m), got {L_.shape}")
        if Qc_.shape != (m, m):
            raise ValueError(f"Qc must have shape ({m}, {m}), got {Qc_.shape}")
        if H_.shape != (1, p):
            raise ValueError(f"H must have shape (1, {p}), got {H_.shape}")
        if Pinf is None:
            Pinf = scipy.linalg.solve_continuous_lyapunov(F_, -L_ @ Qc_ @ L_.T)
        Pinf_ = np.array(Pinf, dtype=float, copy=True)
        if Pinf_.shape != (p, p):
            raise ValueError(f"Pinf must have shape ({p}, {p}), got {Pinf_.shape}")
        Pinf_ = _frozen_copy(0.5 * (Pinf_ + Pinf_.T), "Pinf")

        self.F = F_
        self.L = L_
        self.Qc = Qc_
        self.H = H_
        self.Pinf = Pinf_
        object.__setattr__(self, "_frozen", True)

    def __setattr__(self, name: str, value: Any) -> None:
        if getattr(self, "_frozen", False):
            raise AttributeError(f"{type(self).__name__} is immutable; cannot set {name!r}")
        object.__setattr__(self, name, value)

    def __delattr__(self, name: str) -> None:
        raise AttributeError(f"{type(self).__name__} is immutable; cannot delete {name!r}")

    def __repr__(self) -> str:
        return (
            f"{type(self).__name__}(state_dim={self.state_dim}, "
            f"noise_dim={self.L.shape[1]}, variance={self.stationary_variance:.6g})"
        )

    @property
    def state_dim(self) -> int:
        """Dimension ``p`` of the latent state ``z``."""
        return int(self.F.shape[0])

    @property
    def stationary_variance(self) -> float:
        """Stationary output variance ``k(0) = H Pinf H^T`` [unit of w, squared]."""
        return float((self.H @ self.Pinf @ self.H.T)[0, 0])

    def discretize(self, dt: float, method: str = "exact") -> tuple[np.ndarray, np.ndarray]:
        """Discrete-time transition ``z_{k+1} = A z_k + q_k``, ``q_k ~ N(0, Q)``.

        Args:
            dt: step length [s], finite and > 0.
            method: ``"exact"`` for ``A = expm(F dt)``, ``Q = Pinf - A Pinf A^T``
                (keeps ``Pinf`` stationary); ``"euler_maruyama"`` for the paper's
                ``A = I + F dt``, ``Q = L Qc L^T dt`` (rank ``m``, and its
                stationary covariance is not ``Pinf``).

        Returns:
            ``(A, Q)``, both ``(p, p)`` new writable arrays; ``Q`` is symmetric.

        Raises:
            ValueError: if ``dt`` is not finite and positive or ``method`` is unknown.
        """
        dt_f = _check_dt(dt)
        if method == "exact":
            A = scipy.linalg.expm(self.F * dt_f)
            Q = self.Pinf - A @ self.Pinf @ A.T
        elif method == "euler_maruyama":
            A = np.eye(self.state_dim) + self.F * dt_f
            Q = self.L @ self.Qc @ self.L.T * dt_f
        else:
            raise ValueError(f"method={method!r}: must be one of {DISCRETIZATION_METHODS}")
        return A, 0.5 * (Q + Q.T)

    def covariance(self, tau: Any) -> np.ndarray:
        """Covariance ``k(tau) = H expm(F |tau|) Pinf H^T`` at lags ``tau`` [s].

        Generic (matrix-exponential) form, the same as :meth:`state_space_covariance`;
        subclasses override it with the closed form of the kernel they represent
        (for approximations such as :class:`SquaredExponential` that is the exact
        kernel, not the approximation).

        Args:
            tau: lag(s) [s], any shape.

        Returns:
            Array of the same shape as ``tau``.
        """
        return self.state_space_covariance(tau)

    def state_space_covariance(self, tau: Any) -> np.ndarray:
        """Covariance of the SDE itself, ``H expm(F |tau|) Pinf H^T``, at lags ``tau`` [s].

        For exact state-space kernels (Matern, sums and products of them) this equals
        :meth:`covariance`; for approximations it is the approximation's covariance.

        Args:
            tau: lag(s) [s], any shape.

        Returns:
            Array of the same shape as ``tau``.
        """
        tau_arr = np.abs(np.asarray(tau, dtype=float))
        flat = tau_arr.ravel()
        out = np.empty_like(flat)
        for i, t in enumerate(flat):
            out[i] = (self.H @ scipy.linalg.expm(self.F * t) @ self.Pinf @ self.H.T)[0, 0]
        return out.reshape(tau_arr.shape)

    @property
    def hyperparameters(self) -> dict[str, float]:
        """Named positive hyperparameters that :func:`fit` may learn (empty for raw matrices)."""
        return {}

    def with_hyperparameters(self, **hyperparameters: float) -> StateSpaceKernel:
        """Same kernel structure with some hyperparameters replaced.

        A kernel built from raw matrices has no hyperparameters, so only the empty
        call (returning ``self``) is valid here; subclasses override this.

        Raises:
            ValueError: naming an unknown hyperparameter.
        """
        _check_hyperparameter_names(self, hyperparameters)
        return self

    def __add__(self, other: Any) -> StateSpaceKernel:
        if not isinstance(other, StateSpaceKernel):
            return NotImplemented
        return SumKernel(self, other)

    def __radd__(self, other: Any) -> StateSpaceKernel:
        # ``sum(kernels)`` starts from the integer 0.
        if isinstance(other, int) and not isinstance(other, bool) and other == 0:
            return self
        return NotImplemented

    def __mul__(self, other: Any) -> StateSpaceKernel:
        if not isinstance(other, StateSpaceKernel):
            return NotImplemented
        return ProductKernel(self, other)

    def sample_path(
        self,
        n_steps: int,
        dt: float,
        rng: np.random.Generator,
        start: str = "stationary",
        method: str = "exact",
        n_paths: int | None = None,
    ) -> np.ndarray:
        """Draw latent-state paths ``z_0 .. z_n`` on the grid ``t_k = k dt``.

        The output is ``w_k = H z_k``, i.e. ``path[..., 0]`` for kernels whose
        ``H`` picks the first state.

        Args:
            n_steps: number of transitions ``n >= 0``.
            dt: step length [s], finite and > 0.
            rng: NumPy random generator (the only randomness source).
            start: ``"stationary"`` draws ``z_0 ~ N(0, Pinf)`` (the continuous
                model's, also for ``method="euler_maruyama"``); ``"zero"`` sets ``z_0 = 0``.
            method: discretisation, see :meth:`discretize`.
            n_paths: if given, draw that many independent paths at once.

        Returns:
            ``(n_steps + 1, p)`` array, or ``(n_paths, n_steps + 1, p)`` if ``n_paths`` is set.

        Raises:
            ValueError: on a bad ``n_steps``, ``n_paths``, ``dt``, ``start`` or ``method``.
        """
        if isinstance(n_steps, bool) or not isinstance(n_steps, (int, np.integer)) or n_steps < 0:
            raise ValueError(f"n_steps={n_steps!r}: must be an integer >= 0")
        if n_paths is not None and (
            isinstance(n_paths, bool) or not isinstance(n_paths, (int, np.integer)) or n_paths < 1
        ):
            raise ValueError(f"n_paths={n_paths!r}: must be None or an integer >= 1")
        if start not in START_MODES:
            raise ValueError(f"start={start!r}: must be one of {START_MODES}")
        A, Q = self.discretize(dt, method)
        S = _psd_factor(Q)
        p = self.state_dim
        batch = 1 if n_paths is None else int(n_paths)

        z = np.empty((n_steps + 1, batch, p))
        if start == "stationary":
            z[0] = rng.standard_normal((batch, p)) @ _psd_factor(self.Pinf).T
        else:
            z[0] = 0.0
        # One draw for all steps keeps a seed's path independent of how it is consumed.
        noise = rng.standard_normal((n_steps, batch, p)) @ S.T
        for k in range(n_steps):
            z[k + 1] = z[k] @ A.T + noise[k]
        z = np.swapaxes(z, 0, 1)
        return z[0] if n_paths is None else z


def _is_positive_half_integer(nu: Any) -> bool:
    try:
        two_nu = 2.0 * float(nu)
    except (TypeError, ValueError):
        return False
    return (
        math.isfinite(two_nu) and two_nu > 0 and two_nu == round(two_nu) and round(two_nu) % 2 == 1
    )


class Matern(StateSpaceKernel):
    """Matern kernel with half-integer smoothness ``nu = p - 1/2`` as a ``p``-state SDE.

    With ``lambda = sqrt(2 nu) / lengthscale`` the state is ``z = [w, w', ..., w^(p-1)]``,
    ``F`` is the companion matrix of ``(s + lambda)^p``, ``L = e_p``, ``H = e_1``
    and ``Qc = q = 2 sigma^2 sqrt(pi) lambda^(2p-1) Gamma(p) / Gamma(p - 1/2)``.

    Attributes:
        nu: smoothness, a positive half-integer (0.5, 1.5, 2.5, ...).
        variance: ``sigma^2`` [unit of w, squared].
        lengthscale: ``l`` [s].
    """

    nu: float
    variance: float
    lengthscale: float

    def __init__(self, nu: float, variance: float, lengthscale: float) -> None:
        """Build the SDE matrices.

        Args:
            nu: smoothness, a positive half-integer (0.5, 1.5, 2.5, 3.5, ...).
            variance: ``sigma^2`` > 0 [unit of w, squared].
            lengthscale: ``l`` > 0 [s].

        Raises:
            ValueError: naming the offending field and its allowed values.
        """
        if isinstance(nu, bool) or not _is_positive_half_integer(nu):
            raise ValueError(
                f"nu={nu!r}: must be a positive half-integer (0.5, 1.5, 2.5, 3.5, ...)"
            )
        self.nu = float(nu)
        self.variance = _check_positive(variance, "variance")
        self.lengthscale = _check_positive(lengthscale, "lengthscale")

        p = int(round(self.nu + 0.5))
        lam = math.sqrt(2.0 * self.nu) / self.lengthscale
        binom = np.array([math.comb(p, j) for j in range(p)], dtype=float)
        F = np.diag(np.ones(p - 1), k=1)
        F[-1, :] = -binom * lam ** np.arange(p, 0, -1)
        L = np.zeros((p, 1))
        L[-1, 0] = 1.0
        H = np.zeros((1, p))
        H[0, 0] = 1.0
        # lgamma keeps the constant finite for large p, where Gamma(p) overflows.
        log_c = math.log(2.0 * math.sqrt(math.pi)) + math.lgamma(p) - math.lgamma(p - 0.5)
        c_unit = math.exp(log_c)
        q = self.variance * c_unit * lam ** (2 * p - 1)

        # Pinf entries span powers lambda^0 .. lambda^(2p-2); solving directly loses
        # the small ones to rounding for short lengthscales. With D = diag(lambda^i)
        # we have F = lambda D F1 D^-1 (F1 the lambda=1 companion matrix), so
        # Pinf = sigma^2 D P1 D with P1 the unit-variance, lambda=1 solution.
        F1 = np.diag(np.ones(p - 1), k=1)
        F1[-1, :] = -binom
        P1 = scipy.linalg.solve_continuous_lyapunov(F1, -c_unit * (L @ L.T))
        d = lam ** np.arange(p)
        Pinf = self.variance * (d[:, None] * P1 * d[None, :])

        super().__init__(F, L, np.array([[q]]), H, Pinf)

    @property
    def order(self) -> int:
        """Number of states ``p = nu + 1/2``."""
        return self.state_dim

    @property
    def hyperparameters(self) -> dict[str, float]:
        """``{"variance": sigma^2, "lengthscale": l}``; ``nu`` is structural, not learned."""
        return {"variance": self.variance, "lengthscale": self.lengthscale}

    def with_hyperparameters(self, **hyperparameters: float) -> Matern:
        """Matern kernel of the same ``nu`` with some of ``variance``, ``lengthscale`` replaced.

        Raises:
            ValueError: naming an unknown or invalid hyperparameter.
        """
        _check_hyperparameter_names(self, hyperparameters)
        return Matern(self.nu, **{**self.hyperparameters, **hyperparameters})

    def __repr__(self) -> str:
        return (
            f"Matern(nu={self.nu:g}, variance={self.variance:g}, lengthscale={self.lengthscale:g})"
        )

    def covariance(self, tau: Any) -> np.ndarray:
        """Closed-form Matern covariance at lags ``tau`` [s].

        For ``nu = p - 1/2`` and ``x = sqrt(2 nu) |tau| / l``::

            k = sigma^2 exp(-x) (p-1)!/(2p-2)! sum_{i=0}^{p-1} (p-1+i)!/(i!(p-1-i)!) (2x)^(p-1-i)

        Args:
            tau: lag(s) [s], any shape.

        Returns:
            Array of the same shape as ``tau``.
        """
        x = math.sqrt(2.0 * self.nu) * np.abs(np.asarray(tau, dtype=float)) / self.lengthscale
        p = self.state_dim
        poly = np.zeros_like(x)
        for i in range(p):
            coef = math.factorial(p - 1 + i) / (math.factorial(i) * math.factorial(p - 1 - i))
            poly = poly + coef * (2.0 * x) ** (p - 1 - i)
        scale = math.factorial(p - 1) / math.factorial(2 * p - 2)
        return self.variance * np.exp(-x) * scale * poly


def matern(nu: float, variance: float, lengthscale: float) -> Matern:
    """Matern state-space kernel; see :class:`Matern`.

    Args:
        nu: smoothness, a positive half-integer (0.5, 1.5, 2.5, 3.5, ...).
        variance: ``sigma^2`` > 0 [unit of w, squared].
        lengthscale: ``l`` > 0 [s].

    Returns:
        The frozen :class:`Matern` kernel.
    """
    return Matern(nu, variance, lengthscale)


# ---------------------------------------------------------------- hyperparameter helpers


def _check_hyperparameter_names(kernel: StateSpaceKernel, given: dict[str, Any]) -> None:
    """Raise ValueError if ``given`` names a hyperparameter ``kernel`` does not have."""
    allowed = list(kernel.hyperparameters)
    unknown = sorted(set(given) - set(allowed))
    if unknown:
        names = ", ".join(allowed) if allowed else "none"
        raise ValueError(
            f"unknown hyperparameter(s) {unknown} for {type(kernel).__name__}; allowed: {names}"
        )


def _check_int(value: Any, name: str, low: int, high: int | None = None) -> int:
    """Return ``value`` as an int in ``[low, high]``, or raise ValueError naming ``name``."""
    allowed = f"an integer >= {low}" if high is None else f"an integer in [{low}, {high}]"
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        raise ValueError(f"{name}={value!r}: must be {allowed}")
    if value < low or (high is not None and value > high):
        raise ValueError(f"{name}={value!r}: must be {allowed}")
    return int(value)


# ------------------------------------------------------------------- squared exponential

#: Largest Taylor order accepted by :class:`SquaredExponential`. With balancing the
#: construction still works beyond it, but the covariance error is already < 3e-5 of
#: the variance at 12 while cond(Pinf) grows 5-10x per order (~4e3 at 12, ~2e5 at 16),
#: which the Kalman filter's covariance updates pay for in lost digits.
SE_MAX_ORDER = 12

#: :meth:`SquaredExponential.discretize` refuses a step whose ``Q = Pinf - A Pinf A^T``
#: carries a larger estimated relative rounding error than this.
SE_DISCRETIZATION_RTOL = 1e-6


def _stable_spectral_factor(coeffs: Any) -> np.ndarray:
    """Stable spectral factor of a spectral-density denominator ``P(w^2)``.

    With ``P(w^2) = sum_n c_n w^(2n)`` (``c_N > 0``, ``P > 0`` on the real axis), the
    polynomial ``P(-s^2)`` in ``s = i w`` has ``2N`` roots in ``+-`` pairs; the monic
    ``G(s)`` built from the ``N`` roots with negative real part satisfies
    ``P(w^2) = c_N |G(i w)|^2``, so ``1 / G`` is the transfer function of a stable SDE.

    Args:
        coeffs: ``[c_0, ..., c_N]``, coefficient of ``w^(2n)`` at index ``n``.

    Returns:
        ``G``'s real coefficients, highest power first (``G[0] == 1``), length ``N + 1``.

    Raises:
        ValueError: if ``P(-s^2)`` has roots on (or numerically at) the imaginary axis,
            i.e. no stable factor of order ``N`` exists.
    """
    c = np.asarray(coeffs, dtype=float)
    order = c.size - 1
    poly_s = np.zeros(2 * order + 1)
    for n in range(order + 1):
        # w^(2n) = (-s^2)^n; np.roots wants the highest power first.
        poly_s[2 * order - 2 * n] = (-1) ** n * c[n]
    roots = np.roots(poly_s)
    scale = max(1.0, float(np.abs(roots).max()))
    stable = roots[roots.real < -1e-9 * scale]
    if stable.size != order:
        raise ValueError(
            f"spectral density denominator of order {order} has {order - stable.size} root "
            f"pair(s) on the imaginary axis: no stable state-space model (F not stable)"
        )
    return np.real(np.poly(stable))


@functools.cache
def _se_unit_model(
    order: int,
) -> tuple[np.ndarray, np.ndarray, float, np.ndarray, np.ndarray]:
    """Balanced order-``order`` SE model for unit variance and lengthscale.

    Returns:
        ``(F1, L1, q1, H1, P1)`` as read-only arrays (``q1`` a float), ``H1 = e_1``.

    Raises:
        ValueError: if the spectral factor or its Lyapunov solution is not usable.
    """
    # S(w) = sqrt(2 pi) exp(-w^2/2) ~ sqrt(2 pi) / sum_n (w^2/2)^n / n! (Hartikainen &
    # Sarkka 2010): the denominator is the order-N Taylor polynomial of exp(w^2/2).
    coeffs = [1.0 / (2.0**n * math.factorial(n)) for n in range(order + 1)]
    g = _stable_spectral_factor(coeffs)
    F = np.diag(np.ones(order - 1), k=1)
    F[-1, :] = -g[1:][::-1]
    # P = c_N |G|^2, so S = sqrt(2 pi) / (c_N |G|^2) = q / |G|^2.
    q = math.sqrt(2.0 * math.pi) * 2.0**order * math.factorial(order)
    # The companion matrix's entries span many orders of magnitude (cond(F) ~ 2e3 at
    # order 6, 7e7 at 12); a diagonal similarity z' = T^-1 z fixes that. matrix_balance
    # uses powers of two, so rescaling T to T[0, 0] = 1 is exact and keeps H = e_1.
    _, T = scipy.linalg.matrix_balance(F, permute=False, separate=False)
    t = np.diag(T) / T[0, 0]
    F_b = F * t[None, :] / t[:, None]
    L_b = np.zeros((order, 1))
    L_b[-1, 0] = 1.0 / t[-1]
    H_b = np.zeros((1, order))
    H_b[0, 0] = 1.0
    max_re = float(np.linalg.eigvals(F_b).real.max())
    if not max_re < 0.0:
        raise ValueError(f"order={order}: F is not stable (max real eigenvalue {max_re:.3g})")
    P = scipy.linalg.solve_continuous_lyapunov(F_b, -q * (L_b @ L_b.T))
    P = 0.5 * (P + P.T)
    if not np.linalg.eigvalsh(P).min() > 0.0:
        raise ValueError(f"order={order}: stationary covariance is not positive definite")
    arrays = (F_b, L_b, H_b, P)
    for arr in arrays:
        arr.flags.writeable = False
    return F_b, L_b, q, H_b, P


class SquaredExponential(StateSpaceKernel):
    """Squared-exponential kernel, approximated by an order-``N`` stable SDE.

    The exact kernel ``k(tau) = sigma^2 exp(-tau^2 / (2 l^2))`` has spectral density
    ``S(w) = sigma^2 sqrt(2 pi) l exp(-w^2 l^2 / 2)``, which is not rational.
    Hartikainen & Sarkka (2010) replace ``exp(x)`` in ``1 / exp(x)`` by its order-``N``
    Taylor polynomial; the stable spectral factor of that polynomial gives an ``N``-state
    companion-form model, here balanced (diagonal similarity, ``H = e_1`` kept) and
    time-scaled from the unit-lengthscale model: ``F = F1 / l``, ``Qc = sigma^2 q1 / l``,
    ``Pinf = sigma^2 P1``.

    Accuracy measured (``max |k_ss - k| / sigma^2`` over ``tau`` in ``[0, 5 l]``; the
    maximum sits at ``tau = 0``, i.e. the approximation's variance is slightly too large):

    ======  =======  ======  ======  ======  ======  ======  ======  ======
    order   2        3       4       5       6       8       10      12
    error   1.4e-1   4.5e-2  1.7e-2  7.0e-3  3.0e-3  6.0e-4  1.3e-4  2.9e-5
    ======  =======  ======  ======  ======  ======  ======  ======  ======

    :meth:`covariance` is the exact closed form; :meth:`state_space_covariance` is
    the approximation's. The state is a scaled basis of ``[w, w', ..., w^(N-1)]``
    with ``w = z[0]``.

    Attributes:
        variance: ``sigma^2`` [unit of w, squared].
        lengthscale: ``l`` [s].
        order: Taylor order ``N`` = state dimension, in ``[1, SE_MAX_ORDER]``.
    """

    variance: float
    lengthscale: float
    order: int

    def __init__(self, variance: float, lengthscale: float, order: int = 6) -> None:
        """Build the balanced SDE matrices.

        Args:
            variance: ``sigma^2`` > 0 [unit of w, squared].
            lengthscale: ``l`` > 0 [s].
            order: Taylor order ``N``, an integer in ``[1, SE_MAX_ORDER]``.

        Raises:
            ValueError: naming the offending field and its allowed values, or if the
                order's spectral factor is not stable.
        """
        self.variance = _check_positive(variance, "variance")
        self.lengthscale = _check_positive(lengthscale, "lengthscale")
        self.order = _check_int(order, "order", 1, SE_MAX_ORDER)
        F1, L1, q1, H1, P1 = _se_unit_model(self.order)
        # w(t) = sigma w1(t / l): time scaling divides F by l and the white-noise
        # intensity by l, and the output scaling multiplies Qc and Pinf by sigma^2.
        super().__init__(
            F1 / self.lengthscale,
            L1,
            np.array([[self.variance * q1 / self.lengthscale]]),
            H1,
            self.variance * P1,
        )

    def __repr__(self) -> str:
        return (
            f"SquaredExponential(variance={self.variance:g}, "
            f"lengthscale={self.lengthscale:g}, order={self.order})"
        )

    @property
    def hyperparameters(self) -> dict[str, float]:
        """``{"variance": sigma^2, "lengthscale": l}``; ``order`` is structural."""
        return {"variance": self.variance, "lengthscale": self.lengthscale}

    def with_hyperparameters(self, **hyperparameters: float) -> SquaredExponential:
        """Same order with some of ``variance``, ``lengthscale`` replaced.

        Raises:
            ValueError: naming an unknown or invalid hyperparameter.
        """
        _check_hyperparameter_names(self, hyperparameters)
        return SquaredExponential(**{**self.hyperparameters, **hyperparameters}, order=self.order)

    def covariance(self, tau: Any) -> np.ndarray:
        """Exact squared-exponential covariance ``sigma^2 exp(-tau^2 / (2 l^2))``.

        Args:
            tau: lag(s) [s], any shape.

        Returns:
            Array of the same shape as ``tau``.
        """
        tau_arr = np.asarray(tau, dtype=float)
        return self.variance * np.exp(-0.5 * (tau_arr / self.lengthscale) ** 2)

    def discretize(self, dt: float, method: str = "exact") -> tuple[np.ndarray, np.ndarray]:
        """Discrete transition as :meth:`StateSpaceKernel.discretize`, with a conditioning check.

        For ``dt << l`` the exact ``Q = Pinf - A Pinf A^T`` is a difference of nearly
        equal matrices (``|Q| / |Pinf| ~ 0.7 dt / l`` at order 6), so its relative
        rounding error is about ``N eps |Pinf| / |Q|``.

        Raises:
            ValueError: as the base class, or if that error estimate exceeds
                ``SE_DISCRETIZATION_RTOL`` (``dt / l`` below ~2e-9 at order 6) or ``A``
                is not finite.
        """
        A, Q = super().discretize(dt, method)
        if method == "exact":
            if not np.all(np.isfinite(A)):
                raise ValueError(f"dt={dt!r}: expm(F dt) overflowed for {self!r}")
            q_norm = float(np.linalg.norm(Q))
            rel_err = (
                self.state_dim * np.finfo(float).eps * float(np.linalg.norm(self.Pinf)) / q_norm
                if q_norm > 0.0
                else math.inf
            )
            if rel_err > SE_DISCRETIZATION_RTOL:
                raise ValueError(
                    f"dt={dt!r} [s] is too small for lengthscale={self.lengthscale:g} [s] at "
                    f"order {self.order}: Q = Pinf - A Pinf A^T has relative rounding error "
                    f"~{rel_err:.1e} > {SE_DISCRETIZATION_RTOL:g} (dt / lengthscale = "
                    f"{float(dt) / self.lengthscale:.1e}); use a longer step or merge samples"
                )
        return A, Q


def squared_exponential(variance: float, lengthscale: float, order: int = 6) -> SquaredExponential:
    """Squared-exponential state-space approximation; see :class:`SquaredExponential`.

    Args:
        variance: ``sigma^2`` > 0 [unit of w, squared].
        lengthscale: ``l`` > 0 [s].
        order: Taylor order ``N`` in ``[1, SE_MAX_ORDER]`` (6: covariance within 0.3 %
            of the variance).

    Returns:
        The frozen :class:`SquaredExponential` kernel.
    """
    return SquaredExponential(variance, lengthscale, order)


# ------------------------------------------------------------------------------ periodic


def _periodic_weights(lengthscale: float, harmonics: int) -> np.ndarray:
    """Bessel-series weights ``q_j^2 / sigma^2`` for ``j = 0 .. harmonics``.

    ``exp(z cos x) = I_0(z) + 2 sum_j I_j(z) cos(j x)`` with ``z = l^-2``, times
    ``exp(-z)``; ``ive`` is ``I_j(z) exp(-z)``, finite for any ``z``. They sum to 1 as
    ``harmonics -> oo``.
    """
    j = np.arange(harmonics + 1)
    return np.where(j == 0, 1.0, 2.0) * scipy.special.ive(j, lengthscale**-2)


def _periodic_tail(lengthscale: float, harmonics: int) -> float:
    """Truncation error ``sum_{j > harmonics} q_j^2 / sigma^2`` (= max_tau |k_J - k| / sigma^2)."""
    tail = 1.0 - float(_periodic_weights(lengthscale, harmonics).sum())
    if tail > 1e-8:
        return tail
    # 1 - sum only resolves ~1e-16; sum the tail terms (super-exponentially decaying
    # once j exceeds ~sqrt(z)) instead when it is small.
    z = lengthscale**-2
    j = np.arange(harmonics + 1, harmonics + 60 + int(30.0 * math.sqrt(z)))
    return float(2.0 * scipy.special.ive(j, z).sum())


class Periodic(StateSpaceKernel):
    """Periodic kernel as a sum of undamped resonators (Solin & Sarkka 2014).

    The exact kernel is ``k(tau) = sigma^2 exp(-2 sin^2(pi tau / T) / l^2)``; with
    ``z = l^-2`` it expands as ``sigma^2 sum_j q_j^2 cos(j w0 tau)``, ``w0 = 2 pi / T``,
    ``q_0^2 = I_0(z) / e^z``, ``q_j^2 = 2 I_j(z) / e^z``. Truncating at ``J`` harmonics
    gives ``J + 1`` two-state resonators: ``F`` block-diagonal ``[[0, -j w0], [j w0, 0]]``,
    ``L = I``, ``Qc = 0`` (the process is deterministic given its initial state, so
    ``Pinf = sigma^2 diag(q_j^2 I_2)`` is given, not solved), ``H = [1, 0, 1, 0, ...]``.

    The truncation error ``max_tau |k_J(tau) - k(tau)| = sigma^2 sum_{j > J} q_j^2`` (at
    ``tau = 0``) is exact and stored in :attr:`truncation_error`. With ``J = 6`` it is
    1.3e-6 at ``l = 1``, 7.7e-5 at 0.7, 2.0e-3 at 0.5 and 1.1e-2 at 0.4; with ``J = 10``
    it is 3.1e-6 at 0.5 and 2.0e-3 at 0.3.

    :meth:`covariance` is the exact closed form; :meth:`state_space_covariance` the
    truncated series (equal to ``H expm(F tau) Pinf H^T``).

    Attributes:
        variance: ``sigma^2`` [unit of w, squared].
        lengthscale: ``l`` [-], dimensionless (it scales ``sin(pi tau / T)``).
        period: ``T`` [s].
        harmonics: ``J``, number of harmonics above the constant term.
        max_truncation_error: largest accepted truncation error, relative to ``sigma^2``.
        truncation_error: this kernel's truncation error, relative to ``sigma^2``.
    """

    variance: float
    lengthscale: float
    period: float
    harmonics: int
    max_truncation_error: float
    truncation_error: float

    def __init__(
        self,
        variance: float,
        lengthscale: float,
        period: float,
        harmonics: int = 6,
        max_truncation_error: float = 1e-2,
    ) -> None:
        """Build the resonator matrices.

        Args:
            variance: ``sigma^2`` > 0 [unit of w, squared].
            lengthscale: ``l`` > 0 [-].
            period: ``T`` > 0 [s].
            harmonics: ``J`` >= 0.
            max_truncation_error: in ``(0, 1]``; the truncated series' largest
                covariance error, relative to ``sigma^2``, must not exceed it.

        Raises:
            ValueError: naming the offending field, or if ``lengthscale`` is too small
                for ``harmonics`` (the message says how many harmonics would do).
        """
        self.variance = _check_positive(variance, "variance")
        self.lengthscale = _check_positive(lengthscale, "lengthscale")
        self.period = _check_positive(period, "period")
        self.harmonics = _check_int(harmonics, "harmonics", 0)
        tol = _check_positive(max_truncation_error, "max_truncation_error")
        if tol > 1.0:
            raise ValueError(f"max_truncation_error={max_truncation_error!r}: must be in (0, 1]")
        self.max_truncation_error = tol
        self.truncation_error = _periodic_tail(self.lengthscale, self.harmonics)
        if self.truncation_error > tol:
            raise ValueError(
                f"lengthscale={self.lengthscale:g} is too small for harmonics={self.harmonics}: "
                f"truncation error {self.truncation_error:.2e} (relative to variance) > "
                f"max_truncation_error={tol:g}; use harmonics >= "
                f"{self._harmonics_needed(self.lengthscale, tol)} or a larger lengthscale"
            )
        weights = _periodic_weights(self.lengthscale, self.harmonics)
        w0 = 2.0 * math.pi / self.period
        p = 2 * (self.harmonics + 1)
        F = scipy.linalg.block_diag(
            *[np.array([[0.0, -j * w0], [j * w0, 0.0]]) for j in range(self.harmonics + 1)]
        )
        H = np.tile([1.0, 0.0], self.harmonics + 1)[None, :]
        Pinf = self.variance * np.diag(np.repeat(weights, 2))
        super().__init__(F, np.eye(p), np.zeros((p, p)), H, Pinf)

    @staticmethod
    def _harmonics_needed(lengthscale: float, tol: float) -> int:
        """Smallest ``J`` whose truncation error is <= ``tol``."""
        z = lengthscale**-2
        j_max = 60 + int(30.0 * math.sqrt(z))
        weights = np.where(np.arange(j_max + 1) == 0, 1.0, 2.0) * scipy.special.ive(
            np.arange(j_max + 1), z
        )
        tails = 1.0 - np.cumsum(weights)
        return int(np.argmax(tails <= tol)) if np.any(tails <= tol) else j_max

    def __repr__(self) -> str:
        return (
            f"Periodic(variance={self.variance:g}, lengthscale={self.lengthscale:g}, "
            f"period={self.period:g}, harmonics={self.harmonics})"
        )

    @property
    def hyperparameters(self) -> dict[str, float]:
        """``{"variance": sigma^2, "lengthscale": l, "period": T}``."""
        return {"variance": self.variance, "lengthscale": self.lengthscale, "period": self.period}

    def with_hyperparameters(self, **hyperparameters: float) -> Periodic:
        """Same ``harmonics`` and tolerance with some hyperparameters replaced.

        Raises:
            ValueError: naming an unknown or invalid hyperparameter, or if the new
                lengthscale is too small for ``harmonics``.
        """
        _check_hyperparameter_names(self, hyperparameters)
        return Periodic(
            **{**self.hyperparameters, **hyperparameters},
            harmonics=self.harmonics,
            max_truncation_error=self.max_truncation_error,
        )

    def covariance(self, tau: Any) -> np.ndarray:
        """Exact periodic covariance ``sigma^2 exp(-2 sin^2(pi tau / T) / l^2)``.

        Args:
            tau: lag(s) [s], any shape.

        Returns:
            Array of the same shape as ``tau``.
        """
        s = np.sin(math.pi * np.asarray(tau, dtype=float) / self.period)
        return self.variance * np.exp(-2.0 * s**2 / self.lengthscale**2)

    def state_space_covariance(self, tau: Any) -> np.ndarray:
        """Truncated series ``sigma^2 sum_{j <= J} q_j^2 cos(j w0 tau) = H e^{F tau} Pinf H^T``.

        Args:
            tau: lag(s) [s], any shape.

        Returns:
            Array of the same shape as ``tau``.
        """
        tau_arr = np.asarray(tau, dtype=float)
        weights = np.diag(self.Pinf)[::2]
        w0 = 2.0 * math.pi / self.period
        j = np.arange(self.harmonics + 1)
        return np.cos(tau_arr[..., None] * (j * w0)) @ weights


def periodic(
    variance: float,
    lengthscale: float,
    period: float,
    harmonics: int = 6,
    *,
    max_truncation_error: float = 1e-2,
) -> Periodic:
    """Periodic state-space kernel; see :class:`Periodic`.

    Args:
        variance: ``sigma^2`` > 0 [unit of w, squared].
        lengthscale: ``l`` > 0 [-] (dimensionless).
        period: ``T`` > 0 [s].
        harmonics: ``J`` >= 0 (6: exact to 1e-6 of the variance for ``l >= 1``, to 2e-3
            for ``l >= 0.5``).
        max_truncation_error: accepted truncation error relative to ``sigma^2``.

    Returns:
        The frozen :class:`Periodic` kernel.
    """
    return Periodic(variance, lengthscale, period, harmonics, max_truncation_error)


# --------------------------------------------------------------------- sums and products


def _flatten_parts(parts: tuple[Any, ...], cls: type) -> tuple[StateSpaceKernel, ...]:
    flat: list[StateSpaceKernel] = []
    for part in parts:
        if not isinstance(part, StateSpaceKernel):
            raise TypeError(f"{cls.__name__} parts must be StateSpaceKernel, got {part!r}")
        flat.extend(part.parts if isinstance(part, cls) else [part])
    if len(flat) < 2:
        raise ValueError(f"{cls.__name__} needs at least two kernels, got {len(flat)}")
    return tuple(flat)


class _CompositeKernel(StateSpaceKernel):
    """Shared hyperparameter plumbing: part ``i``'s ``name`` is exposed as ``k{i}_name``."""

    parts: tuple[StateSpaceKernel, ...]

    @property
    def hyperparameters(self) -> dict[str, float]:
        """Parts' hyperparameters, prefixed ``k0_``, ``k1_``, ... by part index."""
        return {
            f"k{i}_{name}": value
            for i, part in enumerate(self.parts)
            for name, value in part.hyperparameters.items()
        }

    def _parts_with(self, hyperparameters: dict[str, float]) -> list[StateSpaceKernel]:
        _check_hyperparameter_names(self, hyperparameters)
        per_part: list[dict[str, float]] = [{} for _ in self.parts]
        for name, value in hyperparameters.items():
            prefix, rest = name.split("_", 1)
            per_part[int(prefix[1:])][rest] = value
        return [
            part.with_hyperparameters(**kw) if kw else part
            for part, kw in zip(self.parts, per_part, strict=True)
        ]


class SumKernel(_CompositeKernel):
    """Sum ``k1 + k2 + ...`` of independent state-space GPs.

    The states are stacked: ``F``, ``L``, ``Qc``, ``Pinf`` block-diagonal, ``H``
    concatenated. Nested sums are flattened into :attr:`parts`.

    Attributes:
        parts: the summed kernels.
    """

    def __init__(self, *parts: StateSpaceKernel) -> None:
        """Stack the parts' SDEs.

        Raises:
            TypeError: if a part is not a :class:`StateSpaceKernel`.
            ValueError: with fewer than two parts.
        """
        self.parts = _flatten_parts(parts, SumKernel)
        super().__init__(
            scipy.linalg.block_diag(*[k.F for k in self.parts]),
            scipy.linalg.block_diag(*[k.L for k in self.parts]),
            scipy.linalg.block_diag(*[k.Qc for k in self.parts]),
            np.hstack([k.H for k in self.parts]),
            scipy.linalg.block_diag(*[k.Pinf for k in self.parts]),
        )

    def __repr__(self) -> str:
        return "SumKernel(" + " + ".join(repr(k) for k in self.parts) + ")"

    def with_hyperparameters(self, **hyperparameters: float) -> SumKernel:
        """Sum of the parts with some (prefixed) hyperparameters replaced.

        Raises:
            ValueError: naming an unknown or invalid hyperparameter.
        """
        return SumKernel(*self._parts_with(hyperparameters))

    def covariance(self, tau: Any) -> np.ndarray:
        """Sum of the parts' :meth:`covariance` (exact closed forms)."""
        return sum((k.covariance(tau) for k in self.parts[1:]), self.parts[0].covariance(tau))

    def state_space_covariance(self, tau: Any) -> np.ndarray:
        """Sum of the parts' :meth:`state_space_covariance` (= ``H e^{F tau} Pinf H^T``)."""
        return sum(
            (k.state_space_covariance(tau) for k in self.parts[1:]),
            self.parts[0].state_space_covariance(tau),
        )


def _kron_matrices(a: tuple[np.ndarray, ...], b: tuple[np.ndarray, ...]) -> tuple[np.ndarray, ...]:
    """``(F, L, Qc, H, Pinf)`` of the product of two state-space kernels.

    With ``z = z_a (x) z_b``: ``F = F_a (x) I + I (x) F_b`` makes ``expm(F tau)`` the
    Kronecker product of the parts', so ``H expm(F tau) Pinf H^T = k_a k_b`` with
    ``H = H_a (x) H_b`` and ``Pinf = Pinf_a (x) Pinf_b``. Then
    ``F Pinf + Pinf F^T = -(L_a Qc_a L_a^T) (x) Pinf_b - Pinf_a (x) (L_b Qc_b L_b^T)``,
    a PSD sum realised by ``L = [L_a (x) I, I (x) L_b]``,
    ``Qc = blkdiag(Qc_a (x) Pinf_b, Pinf_a (x) Qc_b)``. A factor with ``Qc = 0``
    (periodic) contributes no block: the quasi-periodic ``L = L_a (x) I`` of
    Solin & Sarkka (2014).
    """
    Fa, La, Qa, Ha, Pa = a
    Fb, Lb, Qb, Hb, Pb = b
    Ia, Ib = np.eye(Fa.shape[0]), np.eye(Fb.shape[0])
    F = np.kron(Fa, Ib) + np.kron(Ia, Fb)
    blocks = []
    if np.any(Qa != 0.0):
        blocks.append((np.kron(La, Ib), np.kron(Qa, Pb)))
    if np.any(Qb != 0.0):
        blocks.append((np.kron(Ia, Lb), np.kron(Pa, Qb)))
    if blocks:
        L = np.hstack([blk[0] for blk in blocks])
        Qc = scipy.linalg.block_diag(*[blk[1] for blk in blocks])
    else:
        L, Qc = np.eye(F.shape[0]), np.zeros_like(F)
    return F, L, Qc, np.kron(Ha, Hb), np.kron(Pa, Pb)


class ProductKernel(_CompositeKernel):
    """Product ``k1 * k2 * ...`` of state-space kernels, by Kronecker products.

    See :func:`_kron_matrices` for the construction; it is exact for any factors
    (a Matern times a periodic kernel is the usual quasi-periodic case). The state
    dimension is the product of the parts'. Nested products are flattened into
    :attr:`parts`. Note that the parts' variances are only identifiable as a product.

    Attributes:
        parts: the multiplied kernels.
    """

    def __init__(self, *parts: StateSpaceKernel) -> None:
        """Combine the parts' SDEs.

        Raises:
            TypeError: if a part is not a :class:`StateSpaceKernel`.
            ValueError: with fewer than two parts.
        """
        self.parts = _flatten_parts(parts, ProductKernel)
        mats = tuple((k.F, k.L, k.Qc, k.H, k.Pinf) for k in self.parts)
        combined = functools.reduce(_kron_matrices, mats)
        super().__init__(*combined)

    def __repr__(self) -> str:
        return "ProductKernel(" + " * ".join(repr(k) for k in self.parts) + ")"

    def with_hyperparameters(self, **hyperparameters: float) -> ProductKernel:
        """Product of the parts with some (prefixed) hyperparameters replaced.

        Raises:
            ValueError: naming an unknown or invalid hyperparameter.
        """
        return ProductKernel(*self._parts_with(hyperparameters))

    def covariance(self, tau: Any) -> np.ndarray:
        """Product of the parts' :meth:`covariance` (exact closed forms)."""
        out = self.parts[0].covariance(tau)
        for k in self.parts[1:]:
            out = out * k.covariance(tau)
        return out

    def state_space_covariance(self, tau: Any) -> np.ndarray:
        """Product of the parts' :meth:`state_space_covariance` (= ``H e^{F tau} Pinf H^T``)."""
        out = self.parts[0].state_space_covariance(tau)
        for k in self.parts[1:]:
            out = out * k.state_space_covariance(tau)
        return out
