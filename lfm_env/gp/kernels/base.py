"""The state-space kernel: what every temporal GP of :mod:`lfm_env.gp.kernels` shares.

:class:`StateSpaceKernel` holds ``F, L, Qc, H, Pinf`` and does the generic work (discretisation,
sampling, the covariance check); the families build the matrices from hyperparameters. Sums
and products of kernels (:class:`SumKernel`, :class:`ProductKernel`, made by ``k1 + k2`` and
``k1 * k2``) are kernels of this module too, as the operators of the base class build them.
"""

from __future__ import annotations

import functools
import math
import operator
from collections.abc import Callable
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


def _check_float(
    value: Any,
    name: str,
    rule: str = "> 0",
    kind: str = "float",
    unit: str = "",
    bools: bool = False,
) -> float:
    """Return ``value`` as a finite float that satisfies ``rule`` (``"> 0"`` or ``">= 0"``), or
    raise ValueError naming ``name``: ``must be a finite <kind> <rule><unit>`` for what is no
    number (a bool too, unless ``bools``), ``must be finite and <rule><unit>`` out of range."""
    # bool is an int subclass; a True variance is almost certainly a bug, not 1.0.
    if isinstance(value, bool) and not bools:
        raise ValueError(f"{name}={value!r}: must be a finite {kind} {rule}{unit}")
    try:
        value_f = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name}={value!r}: must be a finite {kind} {rule}{unit}") from None
    in_range = value_f >= 0.0 if rule == ">= 0" else value_f > 0.0
    if not (math.isfinite(value_f) and in_range):
        raise ValueError(f"{name}={value!r}: must be finite and {rule}{unit}")
    return value_f


def _check_dt(dt: Any) -> float:
    """Return ``dt`` [s] as a float, or raise ValueError naming ``dt``."""
    return _check_float(dt, "dt", kind="number", unit=" [s]", bools=True)


def _check_positive(value: Any, name: str) -> float:
    """Return ``value`` as a float, or raise ValueError naming ``name`` and the allowed range."""
    return _check_float(value, name)


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


# --------------------------------------------------------------------------- sums and products


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
    """What sums and products share: the parts (nested ones of the same kind flattened),
    their hyperparameters exposed as ``k{i}_name`` (part ``i``'s ``name``), and the
    covariances combined part by part with :attr:`_combine`. A subclass gives its symbol,
    its ``_combine`` and :meth:`_matrices`."""

    parts: tuple[StateSpaceKernel, ...]
    _symbol = ""  # between the parts in the repr
    _combine: Callable[[Any, Any], Any]  # two parts' covariances -> the combination's

    def __init__(self, *parts: StateSpaceKernel) -> None:
        """Combine the parts' SDEs (:meth:`_matrices`).

        Raises:
            TypeError: if a part is not a :class:`StateSpaceKernel`.
            ValueError: with fewer than two parts.
        """
        self.parts = _flatten_parts(parts, type(self))
        super().__init__(*self._matrices(self.parts))

    @staticmethod
    def _matrices(parts: tuple[StateSpaceKernel, ...]) -> tuple[np.ndarray, ...]:
        """``(F, L, Qc, H, Pinf)`` of the combination of ``parts``."""
        raise NotImplementedError

    def __repr__(self) -> str:
        return f"{type(self).__name__}(" + f" {self._symbol} ".join(map(repr, self.parts)) + ")"

    @property
    def hyperparameters(self) -> dict[str, float]:
        """Parts' hyperparameters, prefixed ``k0_``, ``k1_``, ... by part index."""
        return {
            f"k{i}_{name}": value
            for i, part in enumerate(self.parts)
            for name, value in part.hyperparameters.items()
        }

    def with_hyperparameters(self, **hyperparameters: float) -> _CompositeKernel:
        """The same combination of the parts with some (prefixed) hyperparameters replaced.

        Raises:
            ValueError: naming an unknown or invalid hyperparameter.
        """
        return type(self)(*self._parts_with(hyperparameters))

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

    def covariance(self, tau: Any) -> np.ndarray:
        """The parts' :meth:`covariance` (exact closed forms), combined."""
        return functools.reduce(self._combine, (k.covariance(tau) for k in self.parts))

    def state_space_covariance(self, tau: Any) -> np.ndarray:
        """The parts' :meth:`state_space_covariance`, combined (= ``H e^{F tau} Pinf H^T``)."""
        return functools.reduce(self._combine, (k.state_space_covariance(tau) for k in self.parts))


class SumKernel(_CompositeKernel):
    """Sum ``k1 + k2 + ...`` of independent state-space GPs.

    The states are stacked: ``F``, ``L``, ``Qc``, ``Pinf`` block-diagonal, ``H``
    concatenated. Nested sums are flattened into :attr:`parts`. Covariances add.

    Attributes:
        parts: the summed kernels.
    """

    _symbol = "+"
    _combine = staticmethod(operator.add)

    @staticmethod
    def _matrices(parts: tuple[StateSpaceKernel, ...]) -> tuple[np.ndarray, ...]:
        return (
            scipy.linalg.block_diag(*[k.F for k in parts]),
            scipy.linalg.block_diag(*[k.L for k in parts]),
            scipy.linalg.block_diag(*[k.Qc for k in parts]),
            np.hstack([k.H for k in parts]),
            scipy.linalg.block_diag(*[k.Pinf for k in parts]),
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
    Covariances multiply.

    Attributes:
        parts: the multiplied kernels.
    """

    _symbol = "*"
    _combine = staticmethod(operator.mul)

    @staticmethod
    def _matrices(parts: tuple[StateSpaceKernel, ...]) -> tuple[np.ndarray, ...]:
        return functools.reduce(_kron_matrices, tuple((k.F, k.L, k.Qc, k.H, k.Pinf) for k in parts))
