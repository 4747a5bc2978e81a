"""TD3 (Fujimoto et al. 2018, twin delayed DDPG): DDPG with twin critics and the clipped double-Q target, target
policy smoothing (noise of std 0.2 clipped to +-0.5 on the target action) and one actor update per two critic
updates. The same learner as DDPG (``scg_algorithms.ddpg.train``) with these defaults (``training.td3``).
"""

from __future__ import annotations

from scg_algorithms.base import with_defaults
from scg_algorithms.ddpg import config, train

NAME = "td3"

Config = with_defaults(
    config.Config,
    "TD3's options: DDPG's (``scg_algorithms.ddpg.Config``) with twin critics, target policy smoothing and a delayed "
    "actor by default.",
    twin_critics=True,
    target_noise=0.2,
    target_noise_clip=0.5,
    policy_delay=2,
)
make_learner, make_train = train.learner_functions(NAME, Config)
