"""Sums and products of state-space kernels (:class:`SumKernel`, :class:`ProductKernel`), made
by ``k1 + k2`` and ``k1 * k2``."""

from __future__ import annotations

import functools
import operator
from collections.abc import Callable
from typing import Any

import numpy as np
import scipy.linalg
import scipy.special

from lfm_env.gp.kernels.base import (
    StateSpaceKernel,
    _check_hyperparameter_names,
)


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
