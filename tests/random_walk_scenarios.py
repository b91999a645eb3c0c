"""Latent-force scenarios for the solver tests: a random start plus a random walk."""

from __future__ import annotations

import numpy as np


def latent_force_scenarios(
    rng: np.random.Generator,
    n_scenarios: int,
    horizon: int,
    mean: float | np.ndarray = 0.0,
    spread: float = 2.0,
    walk_std: float = 0.3,
    n_forces: int | None = None,
) -> np.ndarray:
    """Latent-force scenarios ``W``: a random start plus a random walk, in the force's units.

    Args:
        rng: random generator.
        n_scenarios: ``Ns``.
        horizon: ``N``.
        mean: centre of the first value (scalar, ``(Ns,)``, or ``(Ns, nw)`` with
            ``n_forces``).
        spread: standard deviation of the first value around ``mean``; 2 m/s^2 is the
            stationary std of the sine track's force (``sigma^2 = 4``), a particle
            filter's posterior is narrower.
        walk_std: standard deviation of each later increment (per step).
        n_forces: ``nw``; ``None`` for one component without its axis.

    Returns:
        ``(Ns, N)``, or ``(Ns, N, n_forces)`` when ``n_forces`` is given.
    """
    nw = 1 if n_forces is None else int(n_forces)
    mean = np.asarray(mean, dtype=float)
    if n_forces is None:
        mean = mean[..., None]
    w0 = mean + spread * rng.standard_normal((n_scenarios, nw))
    steps = walk_std * rng.standard_normal((n_scenarios, horizon - 1, nw))
    W = np.concatenate([w0[:, None], w0[:, None] + np.cumsum(steps, axis=1)], axis=1)
    return W[:, :, 0] if n_forces is None else W
