"""scg-jax: safe-control-gym in JAX. Cart-pole and 1D/2D/3D quadrotor as functional, batched environments."""

from scg_jax.config import Config, EnvConfig, dump_config, load_config, make_from_config
from scg_jax.env import Env, EnvParams, EnvState, StepOutput, TrajectoryParams, make, prior_params
from scg_jax.rollout import Trajectory, auto_reset_step, make_rollout, rollout
from scg_jax.systems import SYSTEMS

__version__ = "0.1.0"

# Gymnasium ids (scg_jax/CartPole-v0, ...), registered only when the optional `gym` extra is installed.
try:
    import gymnasium as _gymnasium  # noqa: F401
except ImportError:
    pass
else:
    from scg_jax.adapters import register_gymnasium_envs as _register_gymnasium_envs

    _register_gymnasium_envs()

__all__ = [
    "SYSTEMS",
    "Config",
    "Env",
    "EnvConfig",
    "EnvParams",
    "EnvState",
    "StepOutput",
    "Trajectory",
    "TrajectoryParams",
    "auto_reset_step",
    "dump_config",
    "load_config",
    "make",
    "make_from_config",
    "make_rollout",
    "prior_params",
    "rollout",
]
