"""Generic bootstrap particle filter, vectorised over the particles.

The filter knows nothing about the vehicle: the user supplies a ``transition`` that
propagates all particles at once (including the process noise, drawn from the
generator it is given) and a ``log_likelihood`` of a measurement for all particles.
The proposal is the transition density (bootstrap filter), so the weight update is
the likelihood alone.

Weights are kept as log-weights, normalised with a log-sum-exp after every update, so
very unlikely measurements underflow gracefully instead of producing zero or NaN
weights. A measurement that leaves *no* particle with a finite log-weight (an outlier
far outside the particle cloud, or NaN in the measurement) is skipped: the predicted
particles are kept with their prior weights (uniform when resampling every step, the
default) and the event is recorded in :attr:`ParticleFilter.last_info` and
:attr:`ParticleFilter.n_degenerate`. A merely *unlikely* measurement (all
log-likelihoods finite, however small) is not skipped: it is used, and typically
collapses the weights onto the particles closest to it (``ess`` near 1).

The transition's process noise is drawn through a :class:`BoxMullerGenerator` sharing
the filter's bit generator: its large single-precision ``standard_normal`` draws use the
Box-Muller transform on vectorised ``log``/``sin``/``cos`` (about 3x faster than NumPy's
ziggurat for the 49000 normals of a 7000-particle step). The samples have the same
standard normal distribution; only the random stream differs from NumPy's.

Typical use at sample ``k``, where ``u_prev`` is the input applied since sample ``k-1``::

    pf.step(u_prev, y_k)          # predict(u_prev) then update(y_k)
    x_hat, (lo, hi) = pf.mean, pf.band(2.0)
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from controllers.estimators.resampling import RESAMPLERS

# Draws with fewer values go to NumPy's ziggurat: Box-Muller's fixed costs do not pay off.
BOX_MULLER_MIN_SIZE = 1024
_TWO_PI32 = np.float32(2.0 * np.pi)
_TWO_TO_MINUS_24 = np.float32(2.0**-24)

Transition = Callable[[np.ndarray, object, np.random.Generator], np.ndarray]
LogLikelihood = Callable[[object, np.ndarray], np.ndarray]


@dataclass(frozen=True)
class UpdateInfo:
    """Record of one :meth:`ParticleFilter.update`.

    Attributes:
        ess: effective sample size of the posterior weights *before* resampling, in
            particles (``0.0`` when the measurement was degenerate).
        resampled: whether the particles were resampled in this update.
        degenerate: whether every log-weight was ``-inf`` or NaN, so the measurement
            was skipped: particles and weights stay as predicted (weights uniform
            unless ``ess_threshold`` left them unequal before this update).
        max_log_likelihood: largest finite per-particle log-likelihood of the
            measurement (``-inf`` if none was finite); a cheap outlier indicator.
    """

    ess: float
    resampled: bool
    degenerate: bool
    max_log_likelihood: float


def gaussian_log_likelihood(
    measurement_std: Sequence[float] | np.ndarray, observed_dims: Sequence[int] | np.ndarray
) -> LogLikelihood:
    """Log-likelihood of ``y = x[observed_dims] + e`` with independent ``e_j ~ N(0, std_j^2)``.

    Angles are compared without wrapping: fine for the case study, whose heading stays
    well inside ``(-pi, pi)`` (near ``0 .. pi/2``). Wrap the residual yourself if a
    measured angle can cross ``+-pi``.

    A NaN anywhere in ``y`` makes every log-likelihood NaN, which the filter treats
    as a degenerate (skipped) measurement; there is no partial-measurement handling.

    Args:
        measurement_std: noise standard deviations, shape ``(m,)``, in the units of
            the observed states (e.g. ``[m, m, m/s, rad]``); all must be positive.
        observed_dims: indices of the measured state components, shape ``(m,)``.

    Returns:
        ``log_likelihood(y, particles) -> (n,)`` with ``y`` of shape ``(m,)`` and
        ``particles`` of shape ``(n, d)``; includes the normalising constant.
    """
    std = np.asarray(measurement_std, dtype=float).reshape(-1)
    dims = np.asarray(observed_dims, dtype=np.intp).reshape(-1)
    if std.shape != dims.shape:
        raise ValueError(
            f"measurement_std: shape {std.shape} does not match observed_dims {dims.shape}"
        )
    if not (np.all(np.isfinite(std)) and np.all(std > 0.0)):
        raise ValueError(f"measurement_std: must be finite and > 0, got {std}")
    if np.any(dims < 0):
        raise ValueError(f"observed_dims: must be non-negative indices, got {dims}")
    # Folding the 1/2 of the Gaussian exponent into the scale saves one pass over n.
    scale = np.sqrt(0.5) / std
    log_norm = -float(np.sum(np.log(std))) - 0.5 * dims.size * np.log(2.0 * np.pi)
    dim_list = [int(k) for k in dims]

    def log_likelihood(y: object, particles: np.ndarray) -> np.ndarray:
        y_arr = np.asarray(y, dtype=float).reshape(-1)
        if y_arr.shape != std.shape:
            raise ValueError(f"y: expected shape {std.shape}, got {y_arr.shape}")
        n = particles.shape[0]
        out = np.full(n, log_norm)
        tmp = np.empty(n)
        # The loop runs over the m measured components, not over particles: one
        # column at a time avoids the (n, m) temporaries of a broadcast and was 1.5-4x
        # faster than an einsum on row-major particles.
        # A wild outlier may overflow the square to inf (log-likelihood -inf): that is
        # the intended result, so silence the warning.
        with np.errstate(over="ignore"):
            for j, dim in enumerate(dim_list):
                np.subtract(particles[:, dim], y_arr[j], out=tmp)
                tmp *= scale[j]
                tmp *= tmp
                out -= tmp
        return out

    return log_likelihood


def measurement_noise_covariance(measurement_std: Any, nx: int) -> np.ndarray:
    """``R = diag(std^2)`` of the full-state measurement ``y = x + e`` (the Rao-Blackwellised
    filter's and the UKF's), or a ValueError naming ``measurement_std`` unless it is ``nx``
    numbers > 0."""
    std = np.asarray(measurement_std, dtype=float).reshape(-1)
    if std.shape != (nx,) or not np.all(std > 0.0):
        raise ValueError(f"measurement_std={std.tolist()}: must be {nx} numbers > 0")
    return np.diag(std**2)


class BoxMullerGenerator(np.random.Generator):
    """A :class:`numpy.random.Generator` whose large float32 normal draws use Box-Muller.

    It shares the bit generator it is built on (drawing from it advances that stream).
    ``standard_normal(size, dtype=np.float32)`` with at least :data:`BOX_MULLER_MIN_SIZE`
    values (and no ``out``) is computed as ``sqrt(-2 log(1 - U1)) (cos, sin)(2 pi U2)`` from
    float32 uniforms ``U1, U2 ~ U[0, 1)``: two normals per pair of uniforms, exactly the
    standard normal distribution up to single-precision rounding, except that the radius of
    a 24-bit uniform truncates ``|z|`` at ``sqrt(48 log 2) = 5.77`` (probability ``8e-9`` per
    value). Every other draw is NumPy's own.
    """

    def standard_normal(self, size=None, dtype=np.float64, out=None):  # noqa: D102
        if out is None and size is not None and np.dtype(dtype) == np.float32:
            shape = (int(size),) if np.ndim(size) == 0 else tuple(int(s) for s in size)
            m = int(np.prod(shape))
            if m >= BOX_MULLER_MIN_SIZE:
                return _box_muller32(self, m).reshape(shape)
        return super().standard_normal(size, dtype=dtype, out=out)


def _box_muller32(rng: np.random.Generator, m: int) -> np.ndarray:
    """``m`` standard normal float32 values by the Box-Muller transform, in one new array."""
    h = (m + 1) // 2
    # 2h uniforms on [0, 1) with 24 bits each (as Generator.random(dtype=np.float32) makes
    # them), from the two 32-bit halves of h raw 64-bit words: the bit generator's cheapest
    # output, and most of this function's cost.
    bits = rng.bit_generator.random_raw(h).view(np.uint32)
    bits >>= 8
    uniforms = bits.astype(np.float32)
    uniforms *= _TWO_TO_MINUS_24
    radius, angle = uniforms[:h], uniforms[h:]
    # In place on the uniforms: radius = sqrt(-2 log(1 - U1)), angle = 2 pi U2.
    np.negative(radius, out=radius)
    np.log1p(radius, out=radius)
    radius *= -2.0
    np.sqrt(radius, out=radius)
    angle *= _TWO_PI32
    out = np.empty(m, dtype=np.float32)
    np.cos(angle, out=out[:h])
    out[:h] *= radius
    rest = m - h
    np.sin(angle[:rest], out=out[h:])
    out[h:] *= radius[:rest]
    return out


def _gather(particles: np.ndarray, idx: np.ndarray) -> np.ndarray:
    """The particles ``particles[idx]`` ``(m, d)``, in the layout of ``particles``.

    Row-major: whole rows (``np.take`` along axis 0; on a column-major array it is ~10x
    slower). Column-major: ``np.take`` along the particle axis of the component-major
    transpose (about 2x a row gather, but the transition then needs no transposed copies).
    """
    if particles.flags.c_contiguous:
        return np.take(particles, idx, axis=0)
    return np.take(particles.T, idx, axis=1).T


class ParticleFilter:
    """Bootstrap particle filter over ``n`` particles of dimension ``d``.

    Args:
        transition: ``transition(particles, u, rng) -> particles`` propagates the
            ``(n, d)`` array one sample ahead, drawing its process noise from ``rng``.
            It may modify its input in place (the filter owns that array) and must
            return an ``(n, d)`` array.
        log_likelihood: ``log_likelihood(y, particles) -> (n,)``, the log-density of
            measurement ``y`` given each particle, up to a constant shared by all
            particles. NaN entries count as ``-inf`` (impossible).
        initial_particles: prior samples, shape ``(n, d)``, finite; copied.
        rng: the filter's only source of randomness (resampling, and passed on to
            ``transition``).
        resampling: one of :data:`controllers.estimators.resampling.RESAMPLERS`' keys.
        ess_threshold: ``None`` resamples after every update (the paper's filter); a
            float in ``(0, 1]`` resamples only when ``ESS < ess_threshold * n``.
        fast_normals: pass ``transition`` a :class:`BoxMullerGenerator` on ``rng``'s bit
            generator (the default) instead of ``rng`` itself: the same distributions,
            a different random stream, faster large float32 normal draws.

    Raises:
        ValueError: an argument is invalid; the message names it.
        TypeError: ``rng`` is not a :class:`numpy.random.Generator`.
    """

    def __init__(
        self,
        transition: Transition,
        log_likelihood: LogLikelihood,
        initial_particles: np.ndarray,
        rng: np.random.Generator,
        resampling: str = "systematic",
        ess_threshold: float | None = None,
        fast_normals: bool = True,
    ) -> None:
        if not callable(transition):
            raise ValueError("transition: must be callable")
        if not callable(log_likelihood):
            raise ValueError("log_likelihood: must be callable")
        if not isinstance(rng, np.random.Generator):
            raise TypeError(f"rng: expected numpy.random.Generator, got {type(rng).__name__}")
        if resampling not in RESAMPLERS:
            raise ValueError(f"resampling: {resampling!r} is not one of {sorted(RESAMPLERS)}")
        if ess_threshold is not None:
            try:
                thr = float(ess_threshold)
            except (TypeError, ValueError):
                thr = float("nan")
            if not 0.0 < thr <= 1.0:
                raise ValueError(f"ess_threshold: must be None or in (0, 1], got {ess_threshold!r}")
            ess_threshold = thr
        self._transition = transition
        self._log_likelihood = log_likelihood
        self._rng = rng
        self._fast_normals = bool(fast_normals)
        self._resampling = resampling
        self._resample = RESAMPLERS[resampling]
        self._ess_threshold = ess_threshold
        self.reset(initial_particles)

    # ------------------------------------------------------------------ state

    def reset(self, initial_particles: np.ndarray) -> None:
        """Restart from new prior samples with uniform weights; clears the counters.

        Args:
            initial_particles: shape ``(n, d)``, finite; copied. ``n`` and ``d`` may
                differ from the previous ones.
        """
        p = np.array(initial_particles, dtype=float, copy=True, order="C")
        if p.ndim != 2 or p.shape[0] < 1 or p.shape[1] < 1:
            raise ValueError(f"initial_particles: expected shape (n, d), got {p.shape}")
        if not np.all(np.isfinite(p)):
            raise ValueError("initial_particles: contains NaN or inf")
        n = p.shape[0]
        self._particles = p
        self._log_weights = np.full(n, -np.log(n))
        self._weights = np.full(n, 1.0 / n)
        self._uniform = True
        self._moments: tuple[np.ndarray, np.ndarray] | None = None
        self._scratch: tuple[np.ndarray, np.ndarray] | None = None
        self._last_info: UpdateInfo | None = None
        self._n_degenerate = 0
        self._n_updates = 0
        self._n_resampled = 0

    def predict(self, u: object) -> None:
        """Propagate every particle through ``transition`` with input ``u``.

        Particles that come back non-finite get zero weight and a finite placeholder
        value (a copy of the heaviest finite particle), so estimates never become NaN;
        the next resampling removes them.

        Raises:
            ValueError: ``transition`` returned a wrong shape.
            FloatingPointError: no particle with non-zero weight stayed finite.
        """
        # Built per call (about 1 us) so that a pickled filter keeps sharing one stream.
        rng = BoxMullerGenerator(self._rng.bit_generator) if self._fast_normals else self._rng
        out = self._transition(self._particles, u, rng)
        # Either layout is kept as it comes, row-major (n, d) or column-major (the transpose
        # of a component-major (d, n) buffer, as LatentForceModel.transition returns it): the
        # resampling gathers each in its own order. Anything else is copied to row-major.
        out = np.asarray(out, dtype=float)
        if not (out.flags.c_contiguous or out.flags.f_contiguous):
            out = np.ascontiguousarray(out)
        if out.shape != self._particles.shape:
            raise ValueError(
                f"transition: returned shape {out.shape}, expected {self._particles.shape}"
            )
        # One flat sum is ~10x cheaper than a per-row isfinite on row-major data, and
        # any NaN/inf makes it non-finite; only then is the exact per-row check paid.
        if not np.isfinite(out.sum()):
            self._drop_non_finite(out)
        else:
            self._particles = out
        self._moments = None

    def _drop_non_finite(self, out: np.ndarray) -> None:
        """Give non-finite predicted particles zero weight and a finite placeholder."""
        finite = np.isfinite(out).all(axis=1)
        lw = np.where(finite, self._log_weights, -np.inf)
        heaviest = int(np.argmax(lw))
        if lw[heaviest] == -np.inf:
            raise FloatingPointError("transition: returned no finite particle with weight > 0")
        if not finite.all():
            if out is not self._particles:
                # Never write into an array the transition may still reference.
                out = out.copy()
            # The placeholder only has to be finite (its weight is zero); a real particle
            # also keeps the next transition well-defined.
            out[~finite] = out[heaviest]
            self._set_log_weights(lw - _logsumexp(lw))
        self._particles = out

    def update(self, y: object) -> UpdateInfo:
        """Weight the particles by the likelihood of ``y`` and resample per the rule.

        Never raises on a bad measurement: if every log-weight is ``-inf`` or NaN the
        measurement is skipped (see :class:`UpdateInfo`).

        Returns:
            The record also stored in :attr:`last_info`.

        Raises:
            ValueError: ``log_likelihood`` returned a wrong shape.
        """
        n = self._particles.shape[0]
        ll = np.asarray(self._log_likelihood(y, self._particles), dtype=float)
        if ll.shape != (n,):
            raise ValueError(f"log_likelihood: returned shape {ll.shape}, expected ({n},)")
        self._n_updates += 1
        if self._uniform:
            # Uniform prior weights only shift every log-weight by the same constant,
            # which the normalisation removes anyway.
            lw = ll.copy()
        else:
            with np.errstate(invalid="ignore"):  # +inf + -inf -> NaN, handled below
                lw = ll + self._log_weights
        peak = lw.max()
        if np.isnan(peak) or peak == np.inf:
            # NaN (bad measurement or model) and +inf (broken likelihood) carry no
            # usable information; treat them as impossible.
            lw[~(lw < np.inf)] = -np.inf
            peak = lw.max()
            max_ll = _finite_max(ll)
        else:
            # No NaN or +inf in ll here, so its plain max is the answer.
            max_ll = float(peak) if self._uniform else float(ll.max())
        if peak == -np.inf:
            self._n_degenerate += 1
            info = UpdateInfo(ess=0.0, resampled=False, degenerate=True, max_log_likelihood=max_ll)
            self._last_info = info
            return info

        # Normalise once in the linear domain and reuse the weights for the ESS and
        # the resampler: one exp over n instead of three.
        lw -= peak
        w = np.exp(lw)
        total = w.sum()
        # Before normalising: equal weights then give exactly n, not n +- round-off.
        ess = float(total * total / np.dot(w, w))
        w /= total

        resample = self._ess_threshold is None or ess < self._ess_threshold * n
        if resample:
            idx = self._resample(w, self._rng)
            self._particles = _gather(self._particles, idx)
            self._log_weights.fill(-np.log(n))
            self._weights.fill(1.0 / n)
            self._uniform = True
            self._n_resampled += 1
        else:
            lw -= np.log(total)
            self._log_weights = lw
            self._weights = w
            self._uniform = False
        self._moments = None
        info = UpdateInfo(ess=ess, resampled=resample, degenerate=False, max_log_likelihood=max_ll)
        self._last_info = info
        return info

    def step(self, u: object, y: object) -> UpdateInfo:
        """:meth:`predict` with ``u``, then :meth:`update` with ``y``.

        ``u`` is the input applied since the previous sample and ``y`` the measurement
        taken now, so afterwards the filter holds the filtering estimate of now.
        """
        self.predict(u)
        return self.update(y)

    def update_then_predict(self, y: object, u: object) -> UpdateInfo:
        """:meth:`update` with ``y``, then :meth:`predict` with ``u``.

        Leaves the filter holding the one-step *prediction*, for a loop that applies
        ``u`` right after measuring ``y``.
        """
        info = self.update(y)
        self.predict(u)
        return info

    # -------------------------------------------------------------- estimates

    def _compute_moments(self) -> tuple[np.ndarray, np.ndarray]:
        if self._moments is None:
            p = self._particles
            w = self._weights
            if self._scratch is None or self._scratch[0].shape != p.shape:
                self._scratch = (np.empty_like(p), np.empty_like(p))
            centred, weighted = self._scratch
            # Matrix products go through BLAS (numpy's axis-0 reductions on a tall
            # row-major array were ~7x slower), and the two (n, d) temporaries live in
            # reused buffers: fresh ones cost ~3x the arithmetic in page faults here.
            mean = w @ p
            np.subtract(p, mean, out=centred)
            np.multiply(centred, w[:, None], out=weighted)
            cov = weighted.T @ centred
            # Round-off can break exact symmetry; consumers (Cholesky) expect it.
            cov += cov.T
            cov *= 0.5
            self._moments = (mean, cov)
        return self._moments

    @property
    def mean(self) -> np.ndarray:
        """Weighted particle mean, shape ``(d,)``."""
        return self._compute_moments()[0].copy()

    @property
    def covariance(self) -> np.ndarray:
        """Weighted particle covariance ``sum_i w_i (x_i - m)(x_i - m)^T``, shape ``(d, d)``.

        The plain (maximum-likelihood) normalisation, no ``n / (n - 1)`` correction.
        """
        return self._compute_moments()[1].copy()

    @property
    def std(self) -> np.ndarray:
        """Per-state standard deviation, shape ``(d,)``."""
        return np.sqrt(np.maximum(np.diag(self._compute_moments()[1]), 0.0))

    def band(self, k: float = 2.0) -> tuple[np.ndarray, np.ndarray]:
        """Per-state band ``(mean - k std, mean + k std)``, each of shape ``(d,)``."""
        mean, std = self._compute_moments()[0], self.std
        return mean - k * std, mean + k * std

    @property
    def particles(self) -> np.ndarray:
        """Current particles, shape ``(n, d)``, as a read-only view.

        Copy it to keep it: a transition that works in place overwrites this array on
        the next :meth:`predict` (resampling and out-of-place transitions do not).
        """
        view = self._particles.view()
        view.flags.writeable = False
        return view

    @property
    def log_weights(self) -> np.ndarray:
        """Normalised log-weights, shape ``(n,)`` (a copy)."""
        return self._log_weights.copy()

    @property
    def weights(self) -> np.ndarray:
        """Normalised weights, shape ``(n,)`` (a copy)."""
        return self._weights.copy()

    @property
    def ess(self) -> float:
        """Effective sample size of the current weights, in particles."""
        if self._uniform:
            return float(self._particles.shape[0])
        return float(1.0 / np.dot(self._weights, self._weights))

    @property
    def n_particles(self) -> int:
        """Number of particles ``n``."""
        return int(self._particles.shape[0])

    @property
    def dim(self) -> int:
        """State dimension ``d``."""
        return int(self._particles.shape[1])

    @property
    def last_info(self) -> UpdateInfo | None:
        """Record of the last :meth:`update` (``None`` before the first one)."""
        return self._last_info

    @property
    def n_degenerate(self) -> int:
        """Number of skipped (degenerate) measurements since the last reset."""
        return self._n_degenerate

    @property
    def n_updates(self) -> int:
        """Number of :meth:`update` calls since the last reset."""
        return self._n_updates

    @property
    def n_resampled(self) -> int:
        """Number of resampling events since the last reset."""
        return self._n_resampled

    @property
    def resampling(self) -> str:
        """Name of the resampling scheme."""
        return self._resampling

    @property
    def ess_threshold(self) -> float | None:
        """Resampling threshold as a fraction of ``n``, or ``None`` (always resample)."""
        return self._ess_threshold

    # -------------------------------------------------------------- internals

    def _set_log_weights(self, lw: np.ndarray) -> None:
        self._log_weights = lw
        self._weights = np.exp(lw)
        self._uniform = False
        self._moments = None


def _logsumexp(a: np.ndarray) -> float:
    peak = a.max()
    return float(peak + np.log(np.exp(a - peak).sum()))


def _finite_max(a: np.ndarray) -> float:
    """Largest finite-or-(-inf) entry, ignoring NaN and +inf (``-inf`` if none)."""
    valid = a[a < np.inf]
    return float(valid.max()) if valid.size else -np.inf
