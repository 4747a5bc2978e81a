"""Config checks shared by the learners' ``Config`` dataclasses (``training.<algo>`` sections of a config file).

A learner's ``Config`` declares its fields with ``scg_algorithms.base.option`` and checks them across fields in
``_check(path)``, built from the helpers here so that every learner reports a bad value the same way: a
``ValueError`` whose message starts with the dotted field name (``training.ppo.gamma: must be in [0, 1], got
1.5``). ``parse_learner_config`` is the one entry point: a mapping (or ``None`` for the defaults) or a ``Config``
built directly, checked either way.
"""

from __future__ import annotations

from collections.abc import Iterable

from scg_algorithms.base import parse_options, positive


def parse_learner_config(cls, options, path: str):
    """``cls`` (a learner's ``Config``) from a mapping, ``None`` (defaults) or an instance, always ``_check``-ed.

    Raises:
        ValueError: naming ``<path>.<field>`` and what is allowed.
    """
    config = parse_options(cls, options, path)
    config._check(path)  # parse_options returns an instance unchanged: check one built directly too
    return config


def check_fields(
    config,
    path: str,
    *,
    positive_fields: Iterable[str] = (),
    nonnegative: Iterable[str] = (),
    closed_unit: Iterable[str] = (),
) -> None:
    """Check groups of ``config``'s fields: ``> 0``, ``>= 0``, in ``[0, 1]``."""
    for name in positive_fields:
        positive(f"{path}.{name}", getattr(config, name))
    for name in nonnegative:
        if getattr(config, name) < 0:
            raise ValueError(f"{path}.{name}: must be >= 0, got {getattr(config, name)!r}")
    for name in closed_unit:
        if not 0.0 <= getattr(config, name) <= 1.0:
            raise ValueError(f"{path}.{name}: must be in [0, 1], got {getattr(config, name)!r}")


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
