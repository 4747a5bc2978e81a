"""DDPG and TD3 hyperparameters (a config file's ``training.ddpg`` / ``training.td3`` section).

One option set serves both: TD3 (Fujimoto et al. 2018) is DDPG (Lillicrap et al. 2016) with twin critics and the
clipped double-Q target, target policy smoothing and a delayed actor; ``Config`` has DDPG's defaults and
``scg_algorithms.ddpg.td3.Config`` the same options with TD3's. The options every off-policy learner has (budget,
replay, discount, Polyak factor, learning rates, networks) and their checks are
``scg_algorithms.rl.off_policy.Config``'s. Actions are in [-1, 1], so the noise scales are in those units.
"""

from __future__ import annotations

import dataclasses

from scg_algorithms.base import option
from scg_algorithms.rl import off_policy


@dataclasses.dataclass(frozen=True)
class Config(off_policy.Config):
    """DDPG's options (``training.ddpg``): the off-policy options and the deterministic actor-critic's."""

    exploration_noise: float = option(
        0.1, "std of the Gaussian noise added to the actor's action while collecting (then clipped to [-1, 1])",
        check="non_negative",
    )  # fmt: skip
    twin_critics: bool = option(
        False, "two critics and the clipped double-Q target min(Q1', Q2') (TD3); false: one critic (DDPG)"
    )
    target_noise: float = option(
        0.0, "target policy smoothing: std of the Gaussian noise added to the target actor's action (0: none)",
        check="non_negative",
    )  # fmt: skip
    target_noise_clip: float = option(
        0.5, "the target policy smoothing noise is clipped to +-this", check="non_negative"
    )
    policy_delay: int = option(
        1, "critic updates per actor update; the target networks move with the actor", check="positive"
    )
