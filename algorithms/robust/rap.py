"""RAP (Vinitsky et al. 2020, robust RL with adversary populations): a protagonist trained with PPO against a
population of ``num_adversaries`` adversaries, each env copy driven by one adversary drawn uniformly at the start
of each of its episodes.

RAP is the adversarial game of ``scg_algorithms.robust.adversarial`` with its defaults, which follow the original's
RA-L configuration (``rap_cartpole.yaml``): two adversaries, the protagonist and every adversary updated from the
same rollouts each iteration (``schedule: joint``); the channel and scale are the env's (``env.adversary: {channel:
action, scale: 0.1}`` there: +-0.1 N on the cart force). Unlike the original, the copies are not reset at every
update (its agents only ever saw the first 100 steps of an episode).
"""

from __future__ import annotations

from scg_algorithms.robust import adversarial

NAME = "rap"

Config = adversarial.Config
make_learner, make_policy_learner, make_train = adversarial.learner_functions(NAME, Config)
