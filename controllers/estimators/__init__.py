"""State estimators of the latent-force model: the bootstrap particle filter and its resampling."""

from controllers.estimators.particle_filter import ParticleFilter, gaussian_log_likelihood

__all__ = ["ParticleFilter", "gaussian_log_likelihood"]
