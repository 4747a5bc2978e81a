"""``scg_jax.tracing``: ``batched_like`` leaves values unchanged and a vmapped loop whose carry it prepares is batched
once; ``where_needed`` gives ``fn`` where needed and ``otherwise`` elsewhere, and ``compacted_while_loop`` the plain
loop's result, copy by copy under any vmap, each running only the passes the copies need."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax import lax

from scg_jax.tracing import batched_like, compacted_while_loop, where_needed


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


def _halvings(x, a):
    # A loop whose length depends on the copy: x halvings towards a, floor(x) of them (x = 7: 7 passes).
    def body(carry):
        i, v = carry
        return i + 1, 0.5 * v + a

    return lax.while_loop(lambda carry: carry[0] < x.astype(jnp.int32), body, (jnp.int32(0), x))[1]


def _expected_halvings(x, a):
    v = x
    for _ in range(int(x)):
        v = 0.5 * v + a
    return v


def test_where_needed_gives_fn_where_needed_and_otherwise_elsewhere_in_chunks_and_nested():
    # Worked numbers: x = 3 with a = 1 halves 3 times: 3 -> 2.5 -> 2.25 -> 2.125. The copies with x > 2 need fn;
    # chunks of 3 split the 7 that need it as 3 + 3 + 1 (the last chunk's two spare lanes write nothing).
    def one(x, a):
        return where_needed(_halvings, x > 2.0, (x, a), -x, chunk=3)

    xs = jnp.arange(10.0)
    out = np.asarray(jax.jit(jax.vmap(one, in_axes=(0, None)))(xs, 1.0))
    expected = [_expected_halvings(x, 1.0) if x > 2 else -x for x in range(10)]
    np.testing.assert_allclose(out, expected, rtol=1e-6)
    plain = jax.vmap(lambda x, a: where_needed(_halvings, x > 2.0, (x, a), -x, chunk=None), in_axes=(0, None))
    np.testing.assert_array_equal(np.asarray(jax.jit(plain)(xs, 1.0)), out)  # no gathering: the same values
    assert out[3] == pytest.approx(2.125)
    # One copy, no vmap (a cond); no copy needs it; every copy does.
    assert float(jax.jit(one)(jnp.float32(3.0), 1.0)) == pytest.approx(2.125)
    assert float(jax.jit(one)(jnp.float32(1.0), 1.0)) == -1.0
    np.testing.assert_array_equal(np.asarray(jax.vmap(one, in_axes=(0, None))(xs[:3], 1.0)), -np.arange(3.0))
    np.testing.assert_allclose(np.asarray(jax.vmap(one, in_axes=(0, None))(xs[3:], 1.0)), expected[3:], rtol=1e-6)
    # Nested: an outer vmap over a (batched) and the reversed order.
    nested = jax.jit(jax.vmap(jax.vmap(one, in_axes=(0, None)), in_axes=(0, 0)))
    out = np.asarray(nested(jnp.stack([xs, xs[::-1]]), jnp.array([1.0, 2.0])))
    for row, (order, a) in enumerate(((range(10), 1.0), (range(9, -1, -1), 2.0))):
        np.testing.assert_allclose(out[row], [_expected_halvings(x, a) if x > 2 else -x for x in order], rtol=1e-6)


def test_where_needed_runs_fn_only_for_the_copies_that_need_it():
    # Each pass of fn's loop reports itself. The copies x = 1, 4, 2 need 1 + 4 + 2 = 7 passes; under vmap a plain
    # cond would run the loop for all 5 copies until the slowest is done (20 passes). Chunks of 1 copy: 7.
    passes = []

    def counted(x):
        def body(carry):
            i, v = carry
            jax.debug.callback(lambda i: passes.append(int(i)), i)
            return i + 1, 0.5 * v

        return lax.while_loop(lambda carry: carry[0] < x.astype(jnp.int32), body, (jnp.int32(0), x))[1]

    def one(x):
        return where_needed(counted, x > 0.0, (x,), jnp.float32(-1.0), chunk=1)

    xs = jnp.array([0.0, 1.0, 4.0, 0.0, 2.0])
    np.testing.assert_allclose(np.asarray(jax.jit(jax.vmap(one))(xs)), [-1.0, 0.5, 0.25, -1.0, 0.5], rtol=1e-6)
    assert sorted(passes) == [0, 0, 0, 1, 1, 2, 3]
    with pytest.raises(ValueError, match=r"chunk: must be at least 1 \(or None\), got 0"):
        where_needed(_halvings, True, (jnp.float32(1.0), 1.0), jnp.float32(0.0), chunk=0)


def _count_cond(args, carry):
    return carry[0] < args[0].astype(jnp.int32)


def _halve_towards(args, carry):
    i, v = carry
    return i + 1, 0.5 * v + args[1]


def test_compacted_while_loop_gives_the_plain_loops_result_copy_by_copy():
    # Each copy halves towards a floor(x) times (x = 3, a = 1: 3 -> 2.5 -> 2.25 -> 2.125), as the plain loop does,
    # vmapped in passes of 3 copies, nested under a second vmap (a batched), and without vmap.
    def one(x, a):
        return compacted_while_loop(_count_cond, _halve_towards, (x, a), (jnp.int32(0), x), chunk=3)

    def plain(x, a):
        return lax.while_loop(lambda c: _count_cond((x, a), c), lambda c: _halve_towards((x, a), c), (jnp.int32(0), x))

    xs = jnp.array([0.0, 5.0, 1.0, 7.0, 3.0, 0.0, 2.0, 9.0])
    count, value = jax.jit(jax.vmap(one, in_axes=(0, None)))(xs, 1.0)
    unchunked = jax.vmap(
        lambda x: compacted_while_loop(_count_cond, _halve_towards, (x, 1.0), (jnp.int32(0), x), None)
    )(xs)
    np.testing.assert_array_equal(np.asarray(unchunked[1]), np.asarray(value))  # chunk None: the plain loop
    np.testing.assert_array_equal(np.asarray(count), [0, 5, 1, 7, 3, 0, 2, 9])
    np.testing.assert_allclose(np.asarray(value), [_expected_halvings(x, 1.0) for x in [0, 5, 1, 7, 3, 0, 2, 9]])
    assert float(value[4]) == pytest.approx(2.125)
    for got, want in zip(jax.jit(one)(jnp.float32(3.0), 1.0), plain(jnp.float32(3.0), 1.0), strict=True):
        assert float(got) == float(want)
    xs2, a2 = jnp.stack([xs, xs[::-1]]), jnp.array([1.0, 2.0])
    nested = jax.jit(jax.vmap(jax.vmap(one, in_axes=(0, None)), in_axes=(0, 0)))(xs2, a2)
    expected = jax.vmap(jax.vmap(plain, in_axes=(0, None)), in_axes=(0, 0))(xs2, a2)
    for got, want in zip(nested, expected, strict=True):
        np.testing.assert_array_equal(np.asarray(got), np.asarray(want))


def test_compacted_while_loop_runs_only_the_passes_the_copies_need():
    # The copies x = 1, 4, 2 (and five at 0) need 1 + 4 + 2 = 7 passes; the plain vmapped loop runs all 8 copies
    # through the slowest's 4 (32 passes). With at most half of the batch running and one copy per pass, the body
    # runs 7 times. With more than half running, a pass covers the whole batch: x = 1, 1, 1, 3 run one whole pass
    # (4 copies at i = 0), then the last copy alone (i = 1, 2): 6, where the plain loop runs 12.
    passes = []

    def body(args, carry):
        jax.debug.callback(lambda i: passes.append(int(i)), carry[0])
        return _halve_towards(args, carry)

    def one(x):
        return compacted_while_loop(_count_cond, body, (x, 0.0), (jnp.int32(0), x), chunk=1)[1]

    run = jax.jit(jax.vmap(one))
    xs = jnp.array([0.0, 1.0, 4.0, 0.0, 2.0, 0.0, 0.0, 0.0])
    np.testing.assert_allclose(np.asarray(run(xs)), [0.0, 0.5, 0.25, 0.0, 0.5, 0.0, 0.0, 0.0])
    assert sorted(passes) == [0, 0, 0, 1, 1, 2, 3]
    passes.clear()
    np.testing.assert_allclose(np.asarray(run(jnp.array([1.0, 1.0, 1.0, 3.0]))), [0.5, 0.5, 0.5, 0.375])
    assert sorted(passes) == [0, 0, 0, 0, 1, 2]
    with pytest.raises(ValueError, match=r"chunk: must be at least 1 \(or None\), got 0"):
        compacted_while_loop(_count_cond, _halve_towards, (jnp.float32(1.0), 1.0), (jnp.int32(0), 1.0), chunk=0)
