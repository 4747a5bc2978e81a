"""A learner's runner state laid out over a device mesh (``scg_jax.sharding``): the env copies split, the rest
replicated."""

from __future__ import annotations

import jax
from jax.sharding import Mesh

from scg_algorithms.rl.collector import CollectorState
from scg_jax.sharding import replicate, shard_batch


def shard_runner_state(runner_state, mesh: Mesh | None):
    """A learner's runner state with its env copies sharded over ``mesh`` and everything else replicated.

    The batched part of every learner's state is its ``collector`` (``CollectorState``:
    env states, observations and episode sums of the N copies, axis 0); its ``last_episode`` means and
    ``obs_stats`` are global, hence replicated, as are networks, optimiser states, replay buffers and keys.
    """
    if mesh is None:
        return runner_state

    def place(node):
        if isinstance(node, CollectorState):
            batched = shard_batch((node.env_state, node.obs, node.episode_stats), mesh)
            rest = replicate((node.last_episode, node.obs_stats), mesh)
            return CollectorState(*batched, *rest)
        return replicate(node, mesh)

    return jax.tree.map(place, runner_state, is_leaf=lambda node: isinstance(node, CollectorState))
