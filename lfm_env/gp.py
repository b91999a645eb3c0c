"""State-space (SDE) representation of temporal Gaussian processes.

A stationary GP ``w(t)`` in time with a rational spectral density is the output
``w = H z`` of the linear time-invariant SDE (Hartikainen & Sarkka 2010)::

    dz/dt = F z + L xi(t),    E[xi(t) xi(s)^T] = Qc delta(t - s),

started from (or run long enough to reach) its stationary covariance ``Pinf``,
which solves ``F Pinf + Pinf F^T + L Qc L^T = 0``. Time is in seconds [s]; the
output ``w`` carries the unit of the modelled quantity (in the case study the
latent force, [m/s^2]), and state component ``i`` carries that unit per
``[s^i]`` (the ``i``-th time derivative of ``w``).

:class:`StateSpaceKernel` holds the matrices and does the generic work
(discretisation, sampling, covariance check); subclasses such as :class:`Matern`
only build the matrices from hyperparameters.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import scipy.linalg

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
    """

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

        Generic (matrix-exponential) form; subclasses with a closed form override it.

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
