"""The one compile cache (``scg_jax.caching``): bounded, never keeps an owner alive, and a hit does not compile."""

import gc
import weakref

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import scg_jax
from scg_algorithms import evaluation
from scg_algorithms.base import JaxController
from scg_algorithms.evaluation import evaluate
from scg_jax.caching import CompileCache
from scg_jax.render import render_frame


class _Owner:
    """Something a cache entry belongs to (weak-referenceable, compared by identity)."""


def test_a_hit_does_not_build_again_and_owners_are_told_apart_by_identity():
    cache = CompileCache(maxsize=4)
    builds = []
    first, second = _Owner(), _Owner()

    def build(value):
        builds.append(value)
        return value

    assert cache.get("k", lambda: build(1), owners=(first,)) == 1
    assert cache.get("k", lambda: build(2), owners=(first,)) == 1  # hit
    assert cache.get("k", lambda: build(3), owners=(second,)) == 3  # same key, another owner
    assert cache.get("other", lambda: build(4), owners=(first,)) == 4
    assert cache.get("k", lambda: build(5)) == 5  # no owner: the key alone
    assert builds == [1, 3, 4, 5] and len(cache) == 4


def test_the_cache_is_bounded_and_evicts_the_least_recently_used():
    cache = CompileCache(maxsize=2)
    builds = []
    cache.get("a", lambda: builds.append("a"))
    cache.get("b", lambda: builds.append("b"))
    cache.get("a", lambda: builds.append("a again"))  # a is now the most recent
    cache.get("c", lambda: builds.append("c"))  # evicts b
    cache.get("a", lambda: builds.append("a again"))
    cache.get("b", lambda: builds.append("b again"))
    assert builds == ["a", "b", "c", "b again"] and len(cache) == 2


def test_an_entry_never_keeps_its_owner_alive_and_dies_with_it():
    cache = CompileCache(maxsize=8)
    owner = _Owner()
    cache.get("k", lambda: np.zeros(3), owners=(owner,))
    ref = weakref.ref(owner)
    del owner
    gc.collect()
    assert ref() is None
    assert len(cache) == 0


def test_maxsize_must_be_a_positive_integer():
    with pytest.raises(ValueError, match=r"maxsize: must be a positive integer, got 0"):
        CompileCache(maxsize=0)


def test_evaluate_compiles_once_per_env_and_controller_and_releases_both():
    env = scg_jax.make("cartpole", episode_len_sec=0.2)
    params = env.default_params
    traces = []

    def act(ctrl_state, obs, step, reference):
        traces.append(1)  # runs once per trace, not per call
        return jnp.array([-2.0]) * obs[2:3], ctrl_state

    controller = JaxController("p", lambda key, reference: (), act)
    first = evaluate(env, params, controller, jax.random.key(0), 3, measure_time=False)
    second = evaluate(env, params, controller, jax.random.key(1), 3, measure_time=False)
    assert len(traces) == 1
    assert first.timing["compile_s"] > 0 and second.timing["compile_s"] == 0.0
    assert not np.allclose(first.per_episode["rmse"], second.per_episode["rmse"])  # new key, new episodes

    env_ref, controller_ref = weakref.ref(env), weakref.ref(controller)
    del env, params, controller, act
    gc.collect()
    assert env_ref() is None and controller_ref() is None


def test_host_functions_are_made_once_per_env_and_the_cache_stays_bounded():
    # Their jitted bound methods refer to the env, so here the bound is what releases it.
    first = scg_jax.make("cartpole")
    functions = evaluation._host_functions(first, False)
    assert evaluation._host_functions(first, False) is functions
    assert evaluation._host_functions(first, True) is not functions
    ref = weakref.ref(first)
    del first, functions
    for _ in range(evaluation._HOST_FUNCTIONS.maxsize):
        evaluation._host_functions(scg_jax.make("cartpole"), False)
    gc.collect()
    assert ref() is None
    assert len(evaluation._HOST_FUNCTIONS) <= evaluation._HOST_FUNCTIONS.maxsize


def test_render_keeps_a_scene_per_env_without_keeping_the_env():
    env = scg_jax.make("cartpole")
    x = np.zeros(4)
    frame = render_frame(env, x, width=64, height=48)
    assert frame.shape == (48, 64, 3)
    np.testing.assert_array_equal(render_frame(env, x, width=64, height=48), frame)  # the cached scene draws the same
    ref = weakref.ref(env)
    del env
    gc.collect()
    assert ref() is None
