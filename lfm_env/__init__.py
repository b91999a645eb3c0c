"""The world: state-space GP kernels, the generic system and latent-force model, each case
study's world (system, config, env), and the Gymnasium envs (``lfm_env/SineTrack-v0``,
``lfm_env/QuadrotorGust-v1``), registered here through :func:`register_world`.

Both envs only terminate; ``gym.make`` truncates them with a ``TimeLimit`` after the
config's ``env.max_steps`` steps, or after ``max_episode_steps`` steps when that is given
(:class:`lfm_env.wrappers.ConfigTimeLimit`, the registrations' outermost wrapper).
"""

from lfm_env.worlds.registry import register_world

register_world(
    "lfm_env/SineTrack-v0",
    config="lfm_env.worlds.sine_track.config:SineTrackConfig",
    env="lfm_env.worlds.sine_track.env:SineTrackEnv",
)
register_world(
    "lfm_env/QuadrotorGust-v1",
    config="lfm_env.worlds.quadrotor.config:QuadrotorGustConfig",
    env="lfm_env.worlds.quadrotor.env:QuadrotorGustEnv",
)

__all__ = ["register_world"]
