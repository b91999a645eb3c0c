"""The agents' estimation step: an estimator started on an episode's first observation,
stepped with the applied input after, and restarted around the measurement when it has lost
the state; the step's values for ``last_info``.

Every agent that estimates (the filtering MPC agents, ``dompc``) runs its estimator through
:class:`EstimatorLoop`, so they detect divergence and report the estimate alike.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from scipy import special

# Divergence test: a measurement whose normalised innovation (NIS; for a particle filter the
# closest particle's) exceeds the chi^2 quantile (nx degrees of freedom) at 1 - DIVERGENCE_TAIL
# means the estimator lost the state.
DIVERGENCE_TAIL = 1.0e-6


class EstimatorLoop:
    """Mixin of the agents that own ``self.estimator`` (an
    :class:`~controllers.estimators.estimator.Estimator`), ``self.model`` (the
    :class:`~lfm_env.model.LatentForceModel`), ``self.system``, ``self.rng`` and ``self._u_prev``
    (the input applied last). Call :meth:`_init_estimator_loop` in ``__init__`` and again in
    ``reset``."""

    def _init_estimator_loop(self) -> None:
        """A new episode: the next observation starts the estimator; no restart counted."""
        # chi^2 upper quantile of the divergence test (nx dof)
        self._divergence_nis = float(special.chdtri(self.system.nx, DIVERGENCE_TAIL))
        self._started = False
        self.n_filter_resets = 0

    def _estimator_step(self, y: np.ndarray) -> tuple[dict[str, Any], np.ndarray, np.ndarray]:
        """Update the estimate with the measurement ``y`` ``(nx,)``: the step's ``last_info``
        values (estimate and its std in the states' units, the latent force's mean and std in
        its units, the estimator's name, whether it degenerated or was restarted, the
        restarts so far), and the estimate's mean ``(nx + p,)`` and covariance."""
        est = self.estimator
        if not self._started:
            rec = est.start(y, self.rng)
            self._started = True
        else:
            rec = est.step(self._u_prev, y)
        # If the measurement is a 1e-6 tail event even for the closest particle (or the UKF's
        # innovation), the estimate has lost the state (a bootstrap filter's cloud can
        # collapse far from the truth): restart around y and say so.
        diverged = rec.degenerate or rec.nis > self._divergence_nis
        if diverged:
            est.start(y, self.rng)
            self.n_filter_resets += 1
        nx = self.system.nx
        mean, cov = est.mean, est.covariance
        H = self.model.H  # (nw, p)
        info = {
            "estimate": mean.copy(),
            "estimate_std": np.sqrt(np.maximum(np.diag(cov), 0.0)),
            "latent_force": H @ mean[nx:],
            "latent_force_std": np.sqrt(np.maximum(np.diag(H @ cov[nx:, nx:] @ H.T), 0.0)),
            "estimator": est.name,
            "filter_degenerate": bool(rec.degenerate),
            "filter_reset": diverged,
            "filter_resets": self.n_filter_resets,
        }
        return info, mean, cov
