"""``scg_jax.tracing.batched_like``: values unchanged, and a vmapped loop whose carry it prepares is batched once."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax import lax

from scg_jax.tracing import batched_like


def _tree():
    return {
        "x": jnp.array([1.5, -jnp.inf, jnp.nan], jnp.float32),
        "count": jnp.int32(7),
        "flags": jnp.array([True, False]),
        "key": jax.random.key(3),
        "python": 2.0,
    }


ANCHORS = {"float": jnp.arange(3.0), "nan": jnp.array([jnp.nan]), "key": jax.random.key(0), "int": jnp.int32(5)}


@pytest.mark.parametrize("anchor", list(ANCHORS.values()), ids=list(ANCHORS))
def test_every_leaf_keeps_its_value_and_dtype(anchor):
    tree = _tree()
    out = batched_like(tree, anchor)
    assert jax.tree.structure(out) == jax.tree.structure(tree)
    for name in ("x", "count", "flags"):
        assert out[name].dtype == tree[name].dtype
        np.testing.assert_array_equal(np.asarray(out[name]), np.asarray(tree[name]))  # NaN == NaN here
    np.testing.assert_array_equal(jax.random.key_data(out["key"]), jax.random.key_data(tree["key"]))
    assert float(out["python"]) == 2.0
    assert batched_like(tree, jnp.zeros(0)) is tree  # an empty anchor leaves the tree as it is


def test_under_vmap_every_leaf_is_batched_with_the_same_values():
    def one(x):
        return batched_like((jnp.zeros(2), jnp.int32(4), jax.random.key(1)), x)

    zeros, fours, keys = jax.vmap(one)(jnp.arange(3.0))
    assert zeros.shape == (3, 2) and fours.shape == (3,) and keys.shape == (3,)
    np.testing.assert_array_equal(zeros, 0.0)
    np.testing.assert_array_equal(fours, 4)
    np.testing.assert_array_equal(jax.random.key_data(keys), np.tile(jax.random.key_data(jax.random.key(1)), (3, 1)))


@pytest.mark.parametrize("nested", [False, True], ids=["loop", "loop-in-loop"])
def test_a_vmapped_loop_whose_carry_it_prepares_is_batched_once(nested):
    """A ``custom_vmap`` function in the loop body counts how often vmap batches the body: a carry that starts the same
    for every copy (a counter, zeros) and that the body makes differ is batched three times by JAX's fixpoint (twice to
    find the batched entries, once more for the loop), once after ``batched_like``; the results are the same."""
    calls = []

    @jax.custom_batching.custom_vmap
    def double(y):
        return 2 * y

    @double.def_vmap
    def _(axis_size, in_batched, y):
        calls.append(axis_size)
        return 2 * y, in_batched[0]

    def inner(x, prepare):
        init = (jnp.zeros((), jnp.int32), jnp.zeros(()), x)
        init = batched_like(init, x) if prepare else init
        return lax.while_loop(lambda c: c[1] < 10.0, lambda c: (c[0] + 1, c[1] + double(c[2]), c[2]), init)

    def outer(x, prepare):
        init = batched_like((jnp.zeros(()), x), x) if prepare else (jnp.zeros(()), x)
        return lax.while_loop(lambda c: c[0] < 30.0, lambda c: (c[0] + inner(c[1], prepare)[1], c[1]), init)

    fn = outer if nested else inner
    results, counts = [], []
    for prepare in (False, True):
        calls.clear()
        results.append(jax.vmap(lambda x, prepare=prepare: fn(x, prepare))(jnp.arange(1.0, 4.0)))
        counts.append(len(calls))
    assert counts[0] >= 2 and counts[1] == 1, counts
    jax.tree.map(np.testing.assert_array_equal, results[0], results[1])
