"""The option declarations every learner shares (``training.<algo>`` sections of a config file).

A learner's ``Config`` is a frozen dataclass of ``scg_algorithms.base.option`` fields, parsed and checked by
``scg_algorithms.base.parse_options`` like a controller's ``Options``: every bad value is a ``ValueError`` whose
message starts with the dotted field name (``training.ppo.gamma: must be in [0, 1], got 1.5``). The fields most
learners have are declared once here (``learner_option``), with one doc and one check whatever the learner; a
learner gives only its default. Hidden layer sizes are tuples of ints everywhere (``hidden_sizes_option``).
"""

from __future__ import annotations

from scg_algorithms.base import option
from scg_algorithms.rl.networks import ACTIVATIONS

__all__ = ["LEARNER_OPTIONS", "check_budget", "hidden_sizes_option", "learner_option"]

# name -> (doc, check) of the options learners share; ``learner_option(name, default)`` declares one.
LEARNER_OPTIONS = {
    "total_env_steps": ("training budget: env steps (transitions) of all copies together", "positive"),
    "num_envs": ("parallel env copies", "positive"),
    "reward_scale": ("multiply rewards by this before learning", "positive"),
    "action_scale": (
        "factor on the policy's action in [-1, 1] before the env's normalised-action conversion "
        "(10: a quadrotor policy spans 0-2x hover thrust)",
        "positive",
    ),
    "normalize_observations": ("normalise observations with running mean and variance", None),
    "activation": ("hidden activation of the networks", None),
}


def learner_option(name: str, default):
    """The shared declaration of the learner option ``name`` (a key of ``LEARNER_OPTIONS``) with ``default``."""
    doc, check = LEARNER_OPTIONS[name]
    return option(default, doc, choices=tuple(ACTIVATIONS) if name == "activation" else None, check=check)


def hidden_sizes_option(default: tuple[int, ...], doc: str):
    """Hidden layer sizes: a non-empty tuple of positive ints (``[64, 64]`` in a config file)."""
    return option(default, doc, check="layer_sizes")


def check_budget(path: str, total_env_steps: int, per_iteration: int, what: str) -> None:
    """``total_env_steps`` must cover at least one iteration of ``per_iteration`` env steps (described by
    ``what``, e.g. ``"num_envs * rollout_length"``)."""
    if total_env_steps < per_iteration:
        raise ValueError(
            f"{path}.total_env_steps: must be at least one batch (one iteration) of {what} = {per_iteration} "
            f"env steps, got {total_env_steps}"
        )
