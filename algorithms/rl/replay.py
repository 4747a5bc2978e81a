"""A fixed-capacity circular replay buffer as a pytree (jit-, vmap- and checkpoint-friendly).

The buffer holds one array per field with a leading ``capacity`` axis, a write ``position`` and the number of
filled slots ``size``. ``add`` writes a batch at ``position, position + 1, ...`` modulo ``capacity`` (the oldest
transitions are overwritten first); ``sample`` draws indices uniformly (with replacement) from the filled slots
``[0, size)``.
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp

from scg_jax._pytree import pytree_dataclass


@pytree_dataclass
class ReplayBuffer:
    """Attributes:
    data: pytree of arrays, each (capacity, ...).
    position: int32 scalar, the slot the next transition goes to.
    size: int32 scalar, filled slots (``<= capacity``).
    """

    data: Any
    position: Any
    size: Any

    @property
    def capacity(self) -> int:
        return jax.tree.leaves(self.data)[0].shape[0]


def init_buffer(capacity: int, example) -> ReplayBuffer:
    """An empty buffer for transitions shaped like ``example`` (a pytree of one transition's arrays)."""
    if capacity < 1:
        raise ValueError(f"capacity: must be positive, got {capacity}")
    data = jax.tree.map(lambda x: jnp.zeros((capacity, *jnp.shape(x)), jnp.asarray(x).dtype), example)
    return ReplayBuffer(data=data, position=jnp.zeros((), jnp.int32), size=jnp.zeros((), jnp.int32))


def add(buffer: ReplayBuffer, batch) -> ReplayBuffer:
    """Write a batch of B transitions (every leaf (B, ...)), wrapping around at the capacity.

    Raises:
        ValueError: when B exceeds the capacity (slots would be written twice in one call).
    """
    capacity = buffer.capacity
    count = jax.tree.leaves(batch)[0].shape[0]
    if count > capacity:
        raise ValueError(f"add: a batch of {count} transitions does not fit a buffer of capacity {capacity}")
    index = (buffer.position + jnp.arange(count)) % capacity
    data = jax.tree.map(lambda store, new: store.at[index].set(new.astype(store.dtype)), buffer.data, batch)
    return ReplayBuffer(
        data=data,
        position=(buffer.position + count) % capacity,
        size=jnp.minimum(buffer.size + count, capacity),
    )


def sample(buffer: ReplayBuffer, key, batch_size: int):
    """``batch_size`` transitions drawn uniformly with replacement from the filled slots.

    Sampling an empty buffer returns slot 0 (zeros); callers sample only once ``size > 0``.
    """
    index = jax.random.randint(key, (batch_size,), 0, jnp.maximum(buffer.size, 1))
    return jax.tree.map(lambda store: store[index], buffer.data)
