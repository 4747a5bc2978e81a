"""scg-jax: safe-control-gym in JAX. Cart-pole and 1D/2D/3D quadrotor as functional, batched environments."""

from scg_jax.config import Config, EnvConfig, dump_config, load_config, make_from_config
from scg_jax.env import Env, EnvParams, EnvState, StepOutput, TrajectoryParams, make, prior_params
from scg_jax.rollout import Trajectory, auto_reset_step, make_rollout, rollout
from scg_jax.systems import SYSTEMS

__version__ = "0.1.0"

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
