"""Helpers that keep tracing cheap under ``jax.vmap``.

``jax.vmap`` batches a loop (``lax.scan``, ``lax.while_loop``, ``lax.fori_loop``) by tracing its body to find which
carry entries differ between copies: an entry that starts the same for every copy (a constant, zeros, a counter) but
that the body makes differ is found only by a second trace of the body with it batched, and a loop nested in that body
is traced again each time. ``batched_like`` makes every entry of an initial carry differ between copies from the start,
so each loop body is traced once: the vmapped closed loop of an SQP-RTI cart-pole controller traces in about 3.7 s
instead of about 7 s.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp


def batched_like(tree, anchor):
    """``tree``, each array leaf unchanged in value but made to depend on ``anchor``.

    Under ``vmap`` with ``anchor`` batched (any value of one copy: its state, its key), every leaf comes out batched;
    outside ``vmap`` or with ``anchor`` unbatched nothing changes but a select of each leaf with itself, which XLA
    removes. Pass a loop's initial carry through it (see the module docstring).

    Args:
        tree: a pytree of arrays (any dtype, PRNG keys included) or Python scalars.
        anchor: an array (a PRNG key is read through its key data); an empty one leaves ``tree`` as it is.
    """
    anchor = jnp.asarray(anchor)
    if jax.dtypes.issubdtype(anchor.dtype, jax.dtypes.prng_key):
        anchor = jax.random.key_data(anchor)
    if anchor.size == 0:
        return tree
    first = jnp.ravel(anchor)[0]
    keep = first == first  # False for NaN: either way the select returns the leaf itself
    return jax.tree.map(lambda leaf: jnp.where(keep, leaf, leaf), tree)


__all__ = ["batched_like"]
