"""PPO hyperparameters (a config file's ``training.ppo`` section).

The defaults are tuned for cart-pole stabilization (``configs/cartpole_stabilization.yaml`` trained with
``reward_type: exponential``): 4.2 M env steps on 512 copies (256 iterations) give a deterministic policy with an
RMSE of 1.2-1.7x LQR's (seeds 0-2), in about 30-60 s on 2 CPU cores, compilation included.
"""

from __future__ import annotations

import dataclasses

from scg_algorithms.base import option
from scg_algorithms.rl.config import check_budget, hidden_sizes_option, learner_option


@dataclasses.dataclass(frozen=True)
class Config:
    """PPO options; parse a mapping with ``parse_options(Config, mapping, "training.ppo")``."""

    total_env_steps: int = learner_option("total_env_steps", 4_194_304)
    num_envs: int = learner_option("num_envs", 512)
    rollout_length: int = option(
        32, "steps per copy per iteration; a batch is num_envs * rollout_length", check="positive"
    )
    num_epochs: int = option(4, "passes over each batch", check="positive")
    num_minibatches: int = option(8, "minibatches per epoch (must divide the batch)", check="positive")
    learning_rate: float = option(1e-3, "Adam step size", check="positive")
    lr_decay: bool = option(True, "decay the step size linearly to 0 over the budget")
    max_grad_norm: float = option(0.5, "clip the global gradient norm to this", check="positive")
    gamma: float = option(0.99, "discount factor", check="unit_interval")
    gae_lambda: float = option(0.95, "GAE lambda", check="unit_interval")
    clip_eps: float = option(0.2, "PPO ratio clip range", check="positive")
    value_clip_eps: float = option(
        0.0, "clip the value step to +-this around the rollout's values; 0: no clip", check="non_negative"
    )
    vf_coef: float = option(0.5, "value-loss weight", check="non_negative")
    ent_coef: float = option(0.0, "entropy-bonus weight", check="non_negative")
    init_log_std: float = option(-1.0, "initial log standard deviation of the Gaussian policy (action units)")
    normalize_observations: bool = learner_option("normalize_observations", True)
    obs_clip: float = option(10.0, "clip normalised observations to +-this", check="positive")
    normalize_advantages: bool = option(True, "normalise advantages per minibatch")
    reward_scale: float = learner_option("reward_scale", 1.0)
    actor_hidden: tuple = hidden_sizes_option((64, 64), "hidden layer sizes of the policy mean network")
    critic_hidden: tuple = hidden_sizes_option((64, 64), "hidden layer sizes of the value network")
    activation: str = learner_option("activation", "tanh")
    action_scale: float = learner_option("action_scale", 1.0)

    def _check(self, path: str) -> None:
        if self.batch_size % self.num_minibatches:
            raise ValueError(
                f"{path}.num_minibatches: must divide the batch num_envs * rollout_length = {self.batch_size}, "
                f"got {self.num_minibatches}"
            )
        check_budget(path, self.total_env_steps, self.batch_size, "num_envs * rollout_length")

    @property
    def batch_size(self) -> int:
        """Env steps per iteration, ``num_envs * rollout_length``."""
        return self.num_envs * self.rollout_length

    @property
    def num_iterations(self) -> int:
        """Iterations in the budget: ``total_env_steps // batch_size`` (the remainder is not run)."""
        return self.total_env_steps // self.batch_size
