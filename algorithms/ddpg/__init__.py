"""DDPG and TD3 for ``scg_jax`` envs: a deterministic tanh actor and one or two Q critics with Polyak targets, on the
off-policy skeleton that SAC shares (``scg_algorithms.rl.off_policy``: collector, JAX replay buffer, warm-up).

- ``Config``: DDPG's options (``training.ddpg``); ``td3.Config`` the same options with TD3's defaults.
- ``make_learner(config, env) -> Learner`` (for ``run_training``) and ``make_train(config, env) -> train(key,
  params)`` (the whole budget in one pure function: jit, vmap over seeds); ``td3.make_learner``, ``td3.make_train``.
- ``losses``: the pure loss functions (target policy smoothing, the clipped double-Q target, the actor's loss).
"""

from scg_algorithms.ddpg import losses
from scg_algorithms.ddpg.config import Config
from scg_algorithms.ddpg.train import LOSS_METRICS, Learning, learner_functions

NAME = "ddpg"

make_learner, make_train = learner_functions(NAME, Config)

__all__ = ["LOSS_METRICS", "NAME", "Config", "Learning", "losses", "make_learner", "make_train"]
