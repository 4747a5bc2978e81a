"""PPO hyperparameters (a config file's ``training.ppo`` section).

The defaults are tuned for cart-pole stabilization (``configs/cartpole_stabilization.yaml`` trained with
``reward_type: exponential``): 4.2 M env steps on 512 copies (256 iterations) give a deterministic policy with an
RMSE of 1.2-1.7x LQR's (seeds 0-2), in about 30-60 s on 2 CPU cores, compilation included.
"""

from __future__ import annotations

import dataclasses

from scg_algorithms.base import option
from scg_algorithms.rl.config import action_scale_option, check_budget, check_learner_fields, layer_sizes
from scg_algorithms.rl.networks import ACTIVATIONS


@dataclasses.dataclass(frozen=True)
class Config:
    """PPO options; parse a mapping with ``parse_options(Config, mapping, "training.ppo")``."""

    total_env_steps: int = option(4_194_304, "training budget in env steps (all copies together)")
    num_envs: int = option(512, "parallel env copies")
    rollout_length: int = option(32, "steps per copy per iteration; a batch is num_envs * rollout_length")
    num_epochs: int = option(4, "passes over each batch")
    num_minibatches: int = option(8, "minibatches per epoch (must divide the batch)")
    learning_rate: float = option(1e-3, "Adam step size")
    lr_decay: bool = option(True, "decay the step size linearly to 0 over the budget")
    max_grad_norm: float = option(0.5, "clip the global gradient norm to this")
    gamma: float = option(0.99, "discount factor")
    gae_lambda: float = option(0.95, "GAE lambda")
    clip_eps: float = option(0.2, "PPO ratio clip range")
    value_clip_eps: float = option(0.0, "clip the value step to +-this around the rollout's values; 0: no clip")
    vf_coef: float = option(0.5, "value-loss weight")
    ent_coef: float = option(0.0, "entropy-bonus weight")
    init_log_std: float = option(-1.0, "initial log standard deviation of the Gaussian policy (action units)")
    normalize_observations: bool = option(True, "normalise observations with running mean and variance")
    obs_clip: float = option(10.0, "clip normalised observations to +-this")
    normalize_advantages: bool = option(True, "normalise advantages per minibatch")
    reward_scale: float = option(1.0, "multiply rewards by this before learning")
    actor_hidden: tuple = option((64, 64), "hidden layer sizes of the policy mean network")
    critic_hidden: tuple = option((64, 64), "hidden layer sizes of the value network")
    activation: str = option("tanh", "hidden activation", choices=tuple(ACTIVATIONS))
    action_scale: float = action_scale_option()

    def _check(self, path: str) -> None:
        check_learner_fields(
            self,
            path,
            positive_fields=(
                "rollout_length",
                "num_epochs",
                "num_minibatches",
                "learning_rate",
                "max_grad_norm",
                "clip_eps",
                "obs_clip",
            ),
            nonnegative=("value_clip_eps", "vf_coef", "ent_coef"),
            closed_unit=("gamma", "gae_lambda"),
        )
        if self.batch_size % self.num_minibatches:
            raise ValueError(
                f"{path}.num_minibatches: must divide the batch num_envs * rollout_length = {self.batch_size}, "
                f"got {self.num_minibatches}"
            )
        check_budget(path, self.total_env_steps, self.batch_size, "num_envs * rollout_length")
        # Layer sizes parse as floats (a tuple option); store them as ints.
        object.__setattr__(self, "actor_hidden", layer_sizes(f"{path}.actor_hidden", self.actor_hidden))
        object.__setattr__(self, "critic_hidden", layer_sizes(f"{path}.critic_hidden", self.critic_hidden))

    @property
    def batch_size(self) -> int:
        """Env steps per iteration, ``num_envs * rollout_length``."""
        return self.num_envs * self.rollout_length

    @property
    def num_iterations(self) -> int:
        """Iterations in the budget: ``total_env_steps // batch_size`` (the remainder is not run)."""
        return self.total_env_steps // self.batch_size
