"""RARL (Pinto et al. 2017, robust adversarial reinforcement learning): a protagonist and one adversary trained
with PPO in a zero-sum game, the adversary acting through the env's adversary input.

Defaults follow the original's RA-L configuration (``cartpole_robustness/config_overrides/rarl_cartpole.yaml``):
alternating updates, one protagonist iteration then one adversary iteration, each on fresh rollouts; the channel
and scale are the env's (``env.adversary: {channel: dynamics, scale: 0.1}`` there: a force on the pole's centre of
mass). See ``scg_algorithms.robust.adversarial`` for the loop; PPO's options are those of ``scg_algorithms.ppo``.
"""

from __future__ import annotations

import dataclasses

from scg_algorithms.ppo.config import Config as PPOConfig
from scg_algorithms.rl.config import parse_learner_config
from scg_algorithms.rl.training import Learner
from scg_algorithms.robust import adversarial

NAME = "rarl"


@dataclasses.dataclass(frozen=True)
class Config(PPOConfig):
    """RARL options: PPO's (the protagonist's, and the adversary's unless named here) plus the game's."""

    schedule: str = adversarial.schedule_option("alternating")
    protagonist_iterations: int = adversarial.protagonist_iterations_option()
    adversary_iterations: int = adversarial.adversary_iterations_option()
    adversary_learning_rate: float = adversarial.adversary_learning_rate_option()
    adversary_init_log_std: float = adversarial.adversary_init_log_std_option()
    adversary_hidden: tuple = adversarial.adversary_hidden_option()

    @property
    def num_adversaries(self) -> int:
        """RARL has one adversary."""
        return 1

    def _check(self, path: str) -> None:
        super()._check(path)
        adversarial.check_robust_fields(self, path)


def make_learner(config, env) -> Learner:
    """RARL as a ``Learner`` for ``run_training``.

    Args:
        config: a ``Config``, a mapping (the ``training.rarl`` section) or ``None`` for the defaults.
        env: an ``scg_jax.Env`` made with an adversary input on the ``action`` or ``dynamics`` channel.

    Raises:
        ValueError: a bad option (``training.rarl.<field>``), or an env without a supported adversary channel
            (``env.adversary``).
    """
    config = parse_learner_config(Config, config, f"training.{NAME}")
    return adversarial.make_adversarial_learner(NAME, config, env, 1)


def make_policy_learner(config, env) -> Learner:
    """The protagonist alone (for ``scg_algorithms.rl.policy.load_policy`` on any env, adversary input or not)."""
    config = parse_learner_config(Config, config, f"training.{NAME}")
    return adversarial.make_protagonist_learner(NAME, config, env)


def make_train(config, env):
    """The whole RARL run as one pure function ``train(key, params) -> (runner_state, metrics)``."""
    return adversarial.make_train(make_learner, config, env)
