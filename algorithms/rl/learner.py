"""A whole training run of any ``Learner`` as one pure function, to ``jax.jit`` and ``jax.vmap`` over seeds."""

from __future__ import annotations

from collections.abc import Callable

import jax
import jax.numpy as jnp

from scg_algorithms.rl.training import Learner


def make_train(learner: Learner, update_at: Callable | None = None) -> Callable:
    """The whole run of ``learner``: ``init``, then ``num_iterations`` updates in one ``lax.scan``.

    Args:
        learner: any ``Learner`` (PPO, SAC, the safe and robust variants).
        update_at: ``update_at(runner_state, params, i) -> (runner_state, metrics)``, the update of iteration ``i``
            (an int32 from the scan, so unbatched under ``jax.vmap`` over keys: a learner that branches on the
            iteration, such as SAC's warm-up or RARL's alternating schedule, keeps a real ``lax.cond`` instead of
            computing both branches for every seed); default ``learner.update``, which reads its clock from the
            runner state.

    Returns:
        ``train(key, params) -> (runner_state, metrics)``: ``metrics`` a dict of (num_iterations, ...) arrays (see
        the learner's ``update``; step counts are ``scg_algorithms.rl.counter.Count``s, ``count_value`` gives the
        integers). Jit it once and ``jax.vmap`` it over keys for several seeds (``params`` unbatched, or batched
        with ``in_axes`` for sweeps).
    """

    def train(key, params):
        runner = learner.init(key, params)
        if update_at is None:
            return jax.lax.scan(lambda state, _: learner.update(state, params), runner, None, learner.num_iterations)
        return jax.lax.scan(lambda state, i: update_at(state, params, i), runner, jnp.arange(learner.num_iterations))

    return train
