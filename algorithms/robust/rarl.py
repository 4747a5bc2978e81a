"""RARL (Pinto et al. 2017, robust adversarial reinforcement learning): a protagonist and one adversary trained
with PPO in a zero-sum game, the adversary acting through the env's adversary input.

RARL is RAP with one adversary: the adversarial game of ``scg_algorithms.robust.adversarial`` with other defaults,
which follow the original's RA-L configuration (``cartpole_robustness/config_overrides/rarl_cartpole.yaml``): one
adversary and alternating updates, one protagonist iteration then one adversary iteration, each on fresh rollouts;
the channel and scale are the env's (``env.adversary: {channel: dynamics, scale: 0.1}`` there: a force on the
pole's centre of mass).
"""

from __future__ import annotations

from scg_algorithms.base import with_defaults
from scg_algorithms.robust import adversarial

NAME = "rarl"

Config = with_defaults(
    adversarial.Config,
    "RARL's options: the game's (``adversarial.Config``) with one adversary and the alternating schedule by default.",
    num_adversaries=1,
    schedule="alternating",
)
make_learner, make_policy_learner, make_train = adversarial.learner_functions(NAME, Config)
