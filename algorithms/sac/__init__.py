"""Soft actor-critic (SAC) for ``scg_jax`` envs: tanh-Gaussian actor, twin critics with Polyak targets, automatic
temperature, on the off-policy skeleton that DDPG and TD3 share (``scg_algorithms.rl.off_policy``: collector, JAX
replay buffer, warm-up), and the whole training loop as one jittable, vmappable function.

- ``Config`` / ``parse_config``: hyperparameters (``training.sac`` of a config file).
- ``make_train(config, env) -> train(key, params)``: the whole budget in one pure function (jit, vmap over seeds).
- ``make_learner(config, env) -> Learner``: for ``scg_algorithms.rl.training.run_training`` (the CLI's host driver).
- ``make_policy_from_config(config_dict, obs_size, action_size) -> (init, apply)``: rebuild a saved policy
  (``scg_algorithms.rl.policy.load_policy``).
- ``losses``: the pure loss functions (the replay buffer is the skeleton's, ``scg_algorithms.rl.replay``).
"""

from scg_algorithms.sac.config import Config, parse_config
from scg_algorithms.sac.train import (
    NAME,
    PolicyParams,
    RunnerState,
    make_learner,
    make_policy_fn,
    make_policy_from_config,
    make_train,
    policy_params,
)

__all__ = [
    "NAME",
    "Config",
    "PolicyParams",
    "RunnerState",
    "make_learner",
    "make_policy_fn",
    "make_policy_from_config",
    "make_train",
    "parse_config",
    "policy_params",
]
