"""The world: state-space GP kernels, the generic system and latent-force model, each case
study's system, and the Gymnasium envs (``lfm_env/SineTrack-v0``,
``lfm_env/QuadrotorGust-v0``)."""

from gymnasium.envs.registration import register

register(
    id="lfm_env/SineTrack-v0",
    entry_point="lfm_env.envs.sine_track:SineTrackEnv",
    max_episode_steps=None,  # the env truncates itself after config.max_steps
)
register(
    id="lfm_env/QuadrotorGust-v0",
    entry_point="lfm_env.envs.quadrotor_gust:QuadrotorGustEnv",
    max_episode_steps=None,  # the env truncates itself after config.max_steps
)

__all__ = ["register"]
