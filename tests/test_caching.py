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


def test_learned_cbf_rounds_take_their_data_as_arguments():
    """The blending episode and the held-out RMSE compile once and take the plant and the data as arguments: with
    the plant equal to the filter's prior the barrier residual vanishes, with the true plant it does not, and both
    run on one executable; the RMSE over any subset of an episode's rows is one executable too."""
    from scg_algorithms.base import parse_options
    from scg_algorithms.controller_setup import prior_step_fn
    from scg_algorithms.safety_filters import learned_cbf
    from scg_algorithms.safety_filters.uncertified import random_input

    env = scg_jax.make(
        "quadrotor_1d",
        episode_len_sec=0.2,
        init_state={"type": "uniform", "low": [0.5, -0.01], "high": [1.0, 0.01]},
        constraints=[{"type": "bounded", "on": "state", "active_dims": [0], "low": [-10.0], "high": [1.5]}],
    )
    params = env.default_params
    prior = scg_jax.prior_params(env, params, 1.5)
    opts = parse_options(learned_cbf.Options, {"barrier": "ceiling", "hidden_sizes": [8]}, learned_cbf.PATH)
    flt = learned_cbf.make_learned_cbf(env, prior, opts)
    net_params = flt.params["correction"]
    collect = learned_cbf._collector(env, flt, prior_step_fn(env, prior, "env"), random_input(env, prior))
    keys = jax.random.split(jax.random.key(0), 4)
    *_, residual_prior = collect(net_params, 0.0, keys, prior, flt.params)
    x, u, valid, residual_true = collect(net_params, 0.0, keys, params, flt.params)
    assert collect._cache_size() == 1
    assert np.max(np.abs(residual_prior)) < 1e-3  # the prior's own step predicts its plant (barrier units/s)
    # The true plant is lighter: under any thrust it climbs faster than predicted, closer to the ceiling (h smaller).
    assert np.all(np.asarray(residual_true) < -0.01)

    _, _, rmse = learned_cbf._trainer(learned_cbf._network(opts, 1, 1), 1, 1, opts)
    x, u, r = (np.asarray(a).reshape(-1, a.shape[-1]) for a in (x, u, residual_true))
    for mask in (np.arange(len(x)) % 2 == 0, np.arange(len(x)) < 5):
        # The network starts at zero (the prior CBF), so the RMSE is that of the residual itself.
        expected = np.sqrt(np.mean(np.square(r[mask])))
        np.testing.assert_allclose(float(rmse(net_params, x, u, r, mask)), expected, rtol=1e-5)
    assert rmse._cache_size() == 1
