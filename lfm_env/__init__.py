"""The world: state-space GP kernels, the generic system and latent-force model, each case
study's system, and the Gymnasium envs (``lfm_env/SineTrack-v0``,
``lfm_env/QuadrotorGust-v0``).

Both envs only terminate; ``gym.make`` truncates them with a ``TimeLimit`` after the
config's ``env.max_steps`` steps, or after ``max_episode_steps`` steps when that is given
(:class:`lfm_env.wrappers.ConfigTimeLimit`, the registrations' outermost wrapper).
"""

from gymnasium.envs.registration import WrapperSpec, register

_CONFIG_TIME_LIMIT = WrapperSpec(
    name="ConfigTimeLimit",
    entry_point="lfm_env.wrappers:ConfigTimeLimit",
    kwargs={},
)

register(
    id="lfm_env/SineTrack-v0",
    entry_point="lfm_env.worlds.sine_track.env:SineTrackEnv",
    max_episode_steps=None,  # the config's max_steps, through ConfigTimeLimit
    additional_wrappers=(_CONFIG_TIME_LIMIT,),
)
register(
    id="lfm_env/QuadrotorGust-v0",
    entry_point="lfm_env.worlds.quadrotor.env:QuadrotorGustEnv",
    max_episode_steps=None,  # the config's max_steps, through ConfigTimeLimit
    additional_wrappers=(_CONFIG_TIME_LIMIT,),
)

__all__ = ["register"]
