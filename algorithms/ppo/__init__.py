"""PPO (clipped objective) in JAX: ``make_train(config, env)(key, params)`` is a whole jittable, vmappable run;
``make_learner(config, env)`` the same iterations for the host driver ``scg_algorithms.rl.training.run_training``."""

from scg_algorithms.ppo.config import Config
from scg_algorithms.ppo.train import NAME, RunnerState, Transition, make_learner, make_train

__all__ = ["NAME", "Config", "RunnerState", "Transition", "make_learner", "make_train"]
