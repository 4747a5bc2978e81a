"""RAP (Vinitsky et al. 2020, robust RL with adversary populations): a protagonist trained with PPO against a
population of ``num_adversaries`` adversaries, each env copy driven by one adversary drawn uniformly at the start
of each of its episodes.

Defaults follow the original's RA-L configuration (``rap_cartpole.yaml``): two adversaries, the protagonist and
every adversary updated from the same rollouts each iteration (``schedule: joint``); the channel and scale are the
env's (``env.adversary: {channel: action, scale: 0.1}`` there: +-0.1 N on the cart force). Unlike the original, the
copies are not reset at every update (its agents only ever saw the first 100 steps of an episode). See
``scg_algorithms.robust.adversarial`` for the loop; PPO's options are those of ``scg_algorithms.ppo``.
"""

from __future__ import annotations

import dataclasses

from scg_algorithms.base import option
from scg_algorithms.ppo.config import Config as PPOConfig
from scg_algorithms.rl.config import parse_learner_config
from scg_algorithms.rl.training import Learner
from scg_algorithms.robust import adversarial

NAME = "rap"


@dataclasses.dataclass(frozen=True)
class Config(PPOConfig):
    """RAP options: PPO's (the protagonist's, and the adversaries' unless named here) plus the population's."""

    num_adversaries: int = option(2, "adversaries in the population (each copy draws one per episode)")
    schedule: str = adversarial.schedule_option("joint")
    protagonist_iterations: int = adversarial.protagonist_iterations_option()
    adversary_iterations: int = adversarial.adversary_iterations_option()
    adversary_learning_rate: float = adversarial.adversary_learning_rate_option()
    adversary_init_log_std: float = adversarial.adversary_init_log_std_option()
    adversary_hidden: tuple = adversarial.adversary_hidden_option()

    def _check(self, path: str) -> None:
        super()._check(path)
        adversarial.check_robust_fields(self, path)


def make_learner(config, env) -> Learner:
    """RAP as a ``Learner`` for ``run_training``.

    Args:
        config: a ``Config``, a mapping (the ``training.rap`` section) or ``None`` for the defaults.
        env: an ``scg_jax.Env`` made with an adversary input on the ``action`` or ``dynamics`` channel.

    Raises:
        ValueError: a bad option (``training.rap.<field>``), or an env without a supported adversary channel
            (``env.adversary``).
    """
    config = parse_learner_config(Config, config, f"training.{NAME}")
    return adversarial.make_adversarial_learner(NAME, config, env, config.num_adversaries)


def make_policy_learner(config, env) -> Learner:
    """The protagonist alone (for ``scg_algorithms.rl.policy.load_policy`` on any env, adversary input or not)."""
    config = parse_learner_config(Config, config, f"training.{NAME}")
    return adversarial.make_protagonist_learner(NAME, config, env)


def make_train(config, env):
    """The whole RAP run as one pure function ``train(key, params) -> (runner_state, metrics)``."""
    return adversarial.make_train(make_learner, config, env)
