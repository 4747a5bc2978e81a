"""Config checks shared by the learners' ``Config`` dataclasses (``training.<algo>`` sections of a config file).

A learner's ``Config`` declares its fields with ``scg_algorithms.base.option`` and checks them across fields in
``_check(path)``, built from the helpers here so that every learner reports a bad value the same way: a
``ValueError`` whose message starts with the dotted field name (``training.ppo.gamma: must be in [0, 1], got
1.5``). ``parse_learner_config`` is the one entry point: a mapping (or ``None`` for the defaults) or a ``Config``
built directly, checked either way.
"""

from __future__ import annotations

from collections.abc import Iterable

from scg_algorithms.base import check_fields, option, parse_options

__all__ = [
    "action_scale_option",
    "check_budget",
    "check_fields",
    "check_learner_fields",
    "layer_sizes",
    "parse_learner_config",
]


def parse_learner_config(cls, options, path: str):
    """``cls`` (a learner's ``Config``) from a mapping, ``None`` (defaults) or an instance, always ``_check``-ed.

    Raises:
        ValueError: naming ``<path>.<field>`` and what is allowed.
    """
    config = parse_options(cls, options, path)
    config._check(path)  # parse_options returns an instance unchanged: check one built directly too
    return config


def layer_sizes(path: str, value) -> tuple[int, ...]:
    """Hidden layer sizes as ints (a tuple option parses them as floats); ValueError unless a non-empty list of
    positive integers."""
    if value is None or len(value) == 0:
        raise ValueError(f"{path}: expected a list of layer sizes, e.g. [64, 64]")
    if any(v < 1 or not float(v).is_integer() for v in value):
        raise ValueError(f"{path}: layer sizes must be positive integers, got {list(value)}")
    return tuple(int(v) for v in value)


def check_budget(path: str, total_env_steps: int, per_iteration: int, what: str) -> None:
    """``total_env_steps`` must cover at least one iteration of ``per_iteration`` env steps (described by
    ``what``, e.g. ``"num_envs * rollout_length"``)."""
    if total_env_steps < per_iteration:
        raise ValueError(
            f"{path}.total_env_steps: must be at least one batch (one iteration) of {what} = {per_iteration} "
            f"env steps, got {total_env_steps}"
        )


def action_scale_option():
    """The ``action_scale`` field every learner's ``Config`` declares (one default and doc for all)."""
    return option(
        1.0,
        "factor on the policy's action in [-1, 1] before the env's normalised-action conversion "
        "(10: a quadrotor policy spans 0-2x hover thrust)",
    )


def check_learner_fields(config, path: str, *, positive_fields: Iterable[str] = (), **groups) -> None:
    """``check_fields`` with the fields every learner has: ``total_env_steps`` and ``num_envs`` (checked first),
    ``reward_scale`` and ``action_scale`` (checked after ``positive_fields``) must be > 0; ``groups``:
    ``check_fields``'s ``nonnegative`` and ``closed_unit``."""
    learner_positive = ("total_env_steps", "num_envs", *positive_fields, "reward_scale", "action_scale")
    check_fields(config, path, positive_fields=learner_positive, **groups)
