"""Safety-layer PPO hyperparameters (a config file's ``training.safe_ppo`` section): every PPO option plus the
safety layer's, named as in the original suite's ``safe_ppo.yaml``."""

from __future__ import annotations

import dataclasses

from scg_algorithms.base import option
from scg_algorithms.ppo.config import Config as PPOConfig
from scg_algorithms.rl.config import hidden_sizes_option


@dataclasses.dataclass(frozen=True)
class Config(PPOConfig):
    """PPO's options (``scg_algorithms.ppo.Config``) and the safety layer's; parse a mapping with
    ``parse_options(Config, mapping, "training.safe_ppo")``."""

    constraint_hidden_dim: tuple = hidden_sizes_option(
        (10,), "hidden layer sizes of each constraint row's model g_i(obs)"
    )
    constraint_lr: float = option(1e-3, "Adam step size of the constraint models", check="positive")
    constraint_batch_size: int = option(256, "minibatch of the constraint models' regression", check="positive")
    constraint_steps_per_epoch: int = option(
        6400, "random-action env steps collected per pretraining epoch", check="positive"
    )
    constraint_epochs: int = option(
        20, "pretraining epochs (one pass over that epoch's fresh data each)", check="positive"
    )
    constraint_eval_steps: int = option(6400, "held-out random-action env steps for the reported MSE", check="positive")
    constraint_slack: tuple = option(
        (0.0,),
        "margin per state-constraint row (one value for all, or one per row in the env's row order): the layer "
        "keeps the predicted next constraint value at or below -slack",
    )

    def _check(self, path: str) -> None:
        super()._check(path)
        for name in ("constraint_steps_per_epoch", "constraint_eval_steps"):
            if getattr(self, name) < max(self.num_envs, self.constraint_batch_size):
                raise ValueError(
                    f"{path}.{name}: must be at least num_envs ({self.num_envs}) and constraint_batch_size "
                    f"({self.constraint_batch_size}), got {getattr(self, name)}"
                )
        slack = self.constraint_slack
        if slack is None or len(slack) == 0:
            raise ValueError(f"{path}.constraint_slack: expected one value or one per state-constraint row, got []")
        if any(not s >= 0 for s in slack):  # also rejects NaN
            raise ValueError(f"{path}.constraint_slack: every slack must be >= 0, got {list(slack)}")
