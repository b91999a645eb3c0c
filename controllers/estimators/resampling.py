"""Resampling schemes for particle filters, all vectorised over the particles.

Every scheme (a :data:`Resampler`) takes normalised weights ``w`` of shape ``(n,)`` and a
:class:`numpy.random.Generator`, and returns ``n`` ancestor indices (``np.intp``, in
ascending order) such that the expected number of copies of particle ``i`` is ``n * w[i]``
(unbiasedness). They differ in the variance of those counts:

* ``multinomial``: ``n`` independent draws from the weights; largest variance.
* ``stratified``: one uniform draw in each of the ``n`` strata ``[j/n, (j+1)/n)``;
  ``|count_i - n w_i| < 2``.
* ``systematic``: one uniform offset shared by all strata; ``|count_i - n w_i| < 1``,
  i.e. every count is ``floor(n w_i)`` or ``ceil(n w_i)``.
* ``residual``: ``floor(n w_i)`` deterministic copies, the remaining
  ``n - sum floor(n w_i)`` drawn multinomially from the fractional parts.

Multinomial draws (and the residual part of ``residual``) invert the cumulative
distribution with :func:`numpy.searchsorted`; ``systematic`` and ``stratified`` count
the points below each cumulative weight in closed form, which gives the same indices
as ``searchsorted`` in ``O(n)``. There is no Python loop over particles.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

# Tolerance on |sum(w) - 1|: loose enough for weights normalised in float64 by
# another routine, tight enough to catch unnormalised weights passed by mistake.
_SUM_TOLERANCE = 1.0e-6

#: Every scheme's signature, ``(weights, rng) -> ancestor indices`` (see the module docstring).
Resampler = Callable[[np.ndarray, np.random.Generator], np.ndarray]


def _cumulative(weights: np.ndarray) -> np.ndarray:
    """Validated cumulative sum of ``weights``, ending in exactly 1.

    An exact 1 guards against round-off leaving ``cdf[-1]`` slightly below a uniform
    draw close to 1, which would make ``searchsorted`` return ``n`` (out of range).
    Dividing by the total (rather than only overwriting the last entry) also gives
    trailing zero-weight particles exactly 1, so they keep an empty interval.
    """
    w = np.asarray(weights, dtype=float)
    if w.ndim != 1 or w.size == 0:
        raise ValueError(f"weights: expected a non-empty 1-D array, got shape {w.shape}")
    cdf = np.cumsum(w)
    total = cdf[-1]
    # A NaN anywhere propagates to the total, so this also rejects NaN weights.
    if not abs(total - 1.0) <= _SUM_TOLERANCE:
        raise ValueError(f"weights: must sum to 1 (normalised), got sum {total!r}")
    if w.min() < 0.0:
        raise ValueError("weights: must be non-negative")
    cdf /= total
    cdf[-1] = 1.0
    return cdf


def _invert(cdf: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Indices ``i`` with ``cdf[i-1] <= p < cdf[i]`` for every point ``p`` in ``[0, 1)``.

    ``side="right"`` skips zero-weight particles: their interval is empty.
    """
    idx = np.searchsorted(cdf, points, side="right")
    # Points are < 1 = cdf[-1], so idx <= n-1 already; the clip only protects against a
    # caller's hand-made cdf and costs next to nothing.
    np.minimum(idx, cdf.size - 1, out=idx)
    return idx.astype(np.intp, copy=False)


def multinomial(weights: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Multinomial resampling (a :data:`Resampler`): ``n`` independent draws from the
    categorical ``weights``."""
    cdf = _cumulative(weights)
    return _invert(cdf, _sorted_uniforms(cdf.size, rng))


def _sorted_uniforms(m: int, rng: np.random.Generator) -> np.ndarray:
    """``m`` sorted i.i.d. ``U[0, 1)`` draws in ``O(m)``, without a sort.

    Normalised partial sums of ``m + 1`` standard exponentials have exactly the joint
    law of the order statistics of ``m`` uniforms; this is about twice as fast as
    sorting, and sorted points make ``searchsorted`` and the later gather cache-friendly.
    """
    sums = np.cumsum(rng.standard_exponential(m + 1))
    return sums[:m] / sums[m]


def stratified(weights: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Stratified resampling (a :data:`Resampler`): one independent uniform draw in each
    stratum ``[j/n, (j+1)/n)``."""
    cdf = _cumulative(weights)
    n = cdf.size
    offsets = rng.random(n)
    # Same result as searchsorted(cdf, (j + U_j) / n) but O(n): the number of points
    # below c is k = floor(c n) full strata plus one if stratum k's point lies below c.
    scaled = cdf * n
    below = np.floor(scaled).astype(np.intp)
    np.clip(below, 0, n, out=below)
    partial = offsets[np.minimum(below, n - 1)] < (scaled - below)
    partial &= below < n
    below += partial
    return _from_points_below(below)


def systematic(weights: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Systematic resampling (a :data:`Resampler`): the points ``(j + U) / n`` with one shared
    ``U ~ U[0, 1)``."""
    cdf = _cumulative(weights)
    n = cdf.size
    offset = rng.random()
    # Same result as searchsorted(cdf, (j + U) / n) but O(n) and about twice as fast:
    # the number of points below c is #{j : j < c n - U} = ceil(c n - U), clipped.
    # In place on cdf (our own array) to skip three temporaries.
    below = cdf
    below *= n
    below -= offset
    np.ceil(below, out=below)
    np.clip(below, 0.0, n, out=below)
    return _from_points_below(below)


def _from_points_below(below: np.ndarray) -> np.ndarray:
    """Ancestor indices from ``below[i]``, the number of points below ``cdf[i]``.

    ``below`` holds non-decreasing whole numbers (int or float) ending in ``n``; the
    differences are the copy counts of each particle.
    """
    n = below.size
    counts = np.empty(n, dtype=np.intp)
    counts[0] = below[0]
    # Differences of whole floats are exact, so the unsafe cast loses nothing.
    np.subtract(below[1:], below[:-1], out=counts[1:], casting="unsafe")
    return np.repeat(np.arange(n, dtype=np.intp), counts)


def residual(weights: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Residual resampling (a :data:`Resampler`): ``floor(n w_i)`` copies of each particle, the
    rest multinomial."""
    w = np.asarray(weights, dtype=float)
    _cumulative(w)  # validation only
    n = w.size
    scaled = n * w
    counts = np.floor(scaled).astype(np.intp)
    n_rest = n - int(counts.sum())
    if n_rest < 0:
        # Only reachable through round-off on weights already at multiples of 1/n;
        # drop surplus copies from the largest counts to keep exactly n.
        order = np.argsort(counts)[::-1][:-n_rest]
        counts[order] -= 1
        n_rest = 0
    if n_rest > 0:
        fractional = scaled - counts
        cdf = np.cumsum(fractional)
        if not cdf[-1] > 0.0:
            # Round-off can leave no fractional mass although n_rest > 0; drawing
            # from the weights themselves keeps zero-weight particles excluded.
            cdf = np.cumsum(w)
        cdf /= cdf[-1]
        cdf[-1] = 1.0
        extra = _invert(cdf, _sorted_uniforms(n_rest, rng))
        counts += np.bincount(extra, minlength=n)
    return np.repeat(np.arange(n, dtype=np.intp), counts)


RESAMPLERS: dict[str, Resampler] = {
    "systematic": systematic,
    "stratified": stratified,
    "residual": residual,
    "multinomial": multinomial,
}


def effective_sample_size(log_weights: np.ndarray) -> float:
    """Kish effective sample size ``(sum w)^2 / sum w^2`` from (unnormalised) log-weights.

    Args:
        log_weights: log-weights, shape ``(n,)``; need not be normalised. ``-inf``
            entries count as zero weight.

    Returns:
        ESS in ``[1, n]``, or ``0.0`` when no weight is positive and finite (all
        ``-inf`` or NaN).
    """
    lw = np.asarray(log_weights, dtype=float)
    if lw.size == 0:
        return 0.0
    peak = np.max(lw)
    if not np.isfinite(peak):
        return 0.0
    w = np.exp(lw - peak)
    total = w.sum()
    return float(total * total / np.dot(w, w))
