"""PPO-Lagrangian hyperparameters (a config file's ``training.ppo_lagrangian`` section): PPO's plus the cost
critic's and the multiplier's (names after OmniSafe's ``PPOLag``)."""

from __future__ import annotations

import dataclasses

from scg_algorithms.base import option
from scg_algorithms.ppo.config import Config as PPOConfig

COST_LIMIT_UNITS = ("fraction", "per_episode")
LAMBDA_OPTIMIZERS = ("adam", "sgd")
COST_ADVANTAGE_MODES = ("center", "standardize")


@dataclasses.dataclass(frozen=True)
class Config(PPOConfig):
    """PPO's options (``scg_algorithms.ppo.Config``) and the constrained-MDP ones."""

    cost_limit: float = option(
        0.01, "the limit d on the expected cost J_c (unit: cost_limit_unit)", check="non_negative"
    )
    cost_limit_unit: str = option(
        "fraction",
        "fraction: J_c is the fraction of the rollout's steps in violation (every step counts, every iteration); "
        "per_episode: J_c is the mean number of violating steps per episode finished in the rollout",
        choices=COST_LIMIT_UNITS,
    )
    lagrange_init: float = option(0.0, "initial Lagrange multiplier (>= 0)", check="non_negative")
    lambda_lr: float = option(0.035, "step size of the multiplier's projected gradient ascent", check="positive")
    lambda_optimizer: str = option(
        "adam",
        "adam: Adam on the loss -lambda (J_c - d), then lambda clipped at 0 (OmniSafe's rule: steps of about "
        "lambda_lr whatever the size of J_c - d, so lambda falls as fast as it rose); sgd: "
        "lambda <- max(0, lambda + lambda_lr (J_c - d))",
        choices=LAMBDA_OPTIMIZERS,
    )
    cost_advantage: str = option(
        "center",
        "how the cost advantages are normalised per minibatch (with normalize_advantages): center subtracts their "
        "mean only (OmniSafe), so rare violations give small advantages; standardize also divides by their std",
        choices=COST_ADVANTAGE_MODES,
    )
    cost_gamma: float = option(0.99, "discount of the cost returns", check="unit_interval")
    cost_gae_lambda: float = option(0.95, "GAE lambda of the cost advantages", check="unit_interval")
    termination_cost: str = option(
        "absorbing",
        "absorbing: a terminated episode keeps its last step's cost forever (bootstrap cost / (1 - cost_gamma)), so "
        "crashing does not end the costs; none: nothing follows a termination",
        choices=("absorbing", "none"),
    )

    def _check(self, path: str) -> None:
        super()._check(path)
        if self.termination_cost == "absorbing" and self.cost_gamma >= 1:
            raise ValueError(f"{path}.cost_gamma: must be < 1 with termination_cost absorbing, got {self.cost_gamma!r}")
        if self.cost_limit_unit == "fraction" and self.cost_limit > 1:
            raise ValueError(f"{path}.cost_limit: a fraction of steps must be in [0, 1], got {self.cost_limit!r}")
