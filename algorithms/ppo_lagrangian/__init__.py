"""PPO-Lagrangian (constrained MDP) on scg-jax's PPO: ``make_learner(config, env)`` for ``run_training``;
``multiplier_update`` and ``combine_advantages`` are its pure pieces."""

from scg_algorithms.ppo_lagrangian.config import Config
from scg_algorithms.ppo_lagrangian.train import NAME, combine_advantages, make_learner, multiplier_update

__all__ = ["NAME", "Config", "combine_advantages", "make_learner", "multiplier_update"]
