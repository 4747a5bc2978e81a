"""P hyperparameter settings of one JAX learner trained at once, as one vmapped program.

The hyperparameters that differ between the members (learning rates, discounts, clip and entropy coefficients,
noise scales: the ``traced`` options of ``scg_algorithms.tune.spaces``) enter the program as traced values, one per
member; everything structural (network sizes, ``num_envs``, batch sizes, the budget) is the same for every member
and fixed when the program is built. Inside the trace the learner is built from its ``Config`` with the traced
values in place (``scg_algorithms.base.parse_options`` keeps a traced field as it is), so the learner's own code
runs unchanged: a member's result equals that setting trained alone, to float rounding (the members' arithmetic is
batched).

``make_population_train(algo, config, env, names)(keys, params, values)`` is the whole budget of every member:
``values`` maps each name to a (P,) array; jit it once and it serves every population of that structure.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from scg_algorithms.base import parse_options
from scg_algorithms.learners import learner_part, learner_spec
from scg_jax.validation import FieldError

__all__ = ["check_members", "make_population_train", "member"]


def check_members(algo: str, config, members: Sequence[Mapping[str, float]]) -> list:
    """Each member's concrete ``Config``: ``config`` (the learner's, checked) with the member's values, checked.

    Raises:
        ValueError: naming ``training.<algo>.<option>`` and the member's value when a member's options are invalid.
    """
    section = learner_spec(algo).section
    cls = type(config)
    fields = {field.name: getattr(config, field.name) for field in dataclasses.fields(config)}
    return [parse_options(cls, {**fields, **dict(values)}, section) for values in members]


def make_population_train(algo: str, config, env, names: Sequence[str]) -> Callable:
    """``train(keys (P,), params, values) -> (runner_states, metrics)``, every leaf with a leading member axis.

    Args:
        algo: a JAX learner of ``scg_algorithms.learners.LEARNERS``. config: its checked ``Config`` (the structural
            options and the values of the options not in ``names``). env: the ``scg_jax.Env``.
        names: the options that differ between the members (floats; e.g. ``("learning_rate", "clip_eps")``).

    Returns:
        ``train``: ``keys`` (P,) PRNG keys (the same key for every member trains each setting on the same data
        stream as ``make_train(member_config, env)(key, params)``), ``params`` unbatched ``EnvParams``, ``values``
        ``{name: (P,) array}``. Jit it; it traces the learner once for any P.

    Raises:
        ValueError: ``names`` holds an option the learner does not have, or one that is not a float.
    """
    section = learner_spec(algo).section
    make_train = _make_train(algo)
    fields = {field.name: field for field in dataclasses.fields(config)}
    for name in names:
        if name not in fields:
            raise FieldError(f"{section}.{name}", f"unknown option; {algo} has {', '.join(fields)}")
        if not isinstance(fields[name].default, float) or isinstance(fields[name].default, bool):
            raise FieldError(f"{section}.{name}", "a population varies float options only (structural ones are fixed)")

    def train_one(key, params, values: Mapping):
        traced = dataclasses.replace(config, **{name: values[name] for name in names})
        return make_train(traced, env)(key, params)

    return jax.vmap(train_one, in_axes=(0, None, 0))


def _make_train(algo: str) -> Callable:
    """``make_train(config, env)`` of the learner: its module's own where it has one (SAC's and DDPG's keep their
    warm-up a real branch under ``jax.vmap``), else ``rl.learner.make_train`` of its ``make_learner``."""
    from scg_algorithms.learners import LEARNERS
    from scg_algorithms.registry import resolve
    from scg_algorithms.rl import learner as learner_lib

    module = resolve(LEARNERS[algo].module)
    if hasattr(module, "make_train"):
        return module.make_train
    make_learner = learner_part(algo, "make_learner")
    return lambda config, env: learner_lib.make_train(make_learner(config, env))


def stack_values(members: Sequence[Mapping[str, float]], names: Sequence[str]) -> dict:
    """``{name: (P,) float32 array}`` of the members' values of ``names``."""
    return {name: jnp.asarray(np.array([m[name] for m in members], dtype=np.float32)) for name in names}


def member(tree, index: int):
    """Member ``index`` of a population's pytree (every leaf's leading axis)."""
    return jax.tree.map(lambda x: x[index], tree)
