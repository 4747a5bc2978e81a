"""Safety-layer PPO (Dalal et al. 2018) on scg-jax's PPO: ``make_learner(config, env)`` for ``run_training``;
``layer.project_mean`` and ``layer.pretrain`` are the layer's pure pieces."""

from scg_algorithms.safe_ppo.config import Config
from scg_algorithms.safe_ppo.layer import project_mean, state_constraint_rows
from scg_algorithms.safe_ppo.train import NAME, make_learner

__all__ = ["NAME", "Config", "make_learner", "project_mean", "state_constraint_rows"]
