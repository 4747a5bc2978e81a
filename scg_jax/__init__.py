"""scg-jax: safe-control-gym in JAX. Cart-pole and 1D/2D/3D quadrotor as functional, batched environments."""

from scg_jax.env import Env, EnvParams, EnvState, StepOutput, TrajectoryParams, make, prior_params
from scg_jax.rollout import Trajectory, auto_reset_step, make_rollout, rollout
from scg_jax.systems import SYSTEMS

__version__ = "0.1.0"

__all__ = [
    "SYSTEMS",
    "Env",
    "EnvParams",
    "EnvState",
    "StepOutput",
    "Trajectory",
    "TrajectoryParams",
    "auto_reset_step",
    "make",
    "make_rollout",
    "prior_params",
    "rollout",
]
