"""Sharded runs on 4 simulated CPU devices, compared with the single-device runs.

Not collected by the main test run (the name does not start with ``test_``): the device count is fixed when JAX
starts its backend, which the main pytest process has long done. ``tests/test_sharding.py`` runs this file in a
fresh pytest process with ``XLA_FLAGS=--xla_force_host_platform_device_count=4``.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.sharding import PartitionSpec as P

import scg_jax
from scg_algorithms.base import JaxController
from scg_algorithms.evaluation import evaluate, make_evaluator
from scg_algorithms.lqr import make_lqr
from scg_algorithms.ppo import make_learner
from scg_algorithms.rl.collector import ActOutput, collect, init_collector
from scg_algorithms.rl.envs import make_train_env
from scg_algorithms.rl.sharding import shard_runner_state
from scg_algorithms.rl.training import run_training
from scg_jax import sharding
from scg_jax.rollout import make_rollout
from tests.rl_helpers import tiny_ppo

NUM_DEVICES = 4
NUM_ENVS = 8


def _float_leaves(tree):
    return [
        np.asarray(leaf, np.float64)
        for leaf in jax.tree.leaves(tree)
        if not jax.dtypes.issubdtype(leaf.dtype, jax.dtypes.prng_key)
    ]


def _max_difference(a, b) -> float:
    pairs = list(zip(_float_leaves(a), _float_leaves(b), strict=True))
    return max(float(np.max(np.abs(x - y), initial=0.0)) for x, y in pairs)


@pytest.fixture(scope="module")
def cartpole():
    env = scg_jax.make("cartpole")
    return env, env.default_params


@pytest.fixture(scope="module")
def mesh():
    assert jax.device_count() == NUM_DEVICES, "run with XLA_FLAGS=--xla_force_host_platform_device_count=4"
    return sharding.make_mesh("all")


def _noisy_policy(obs, state, params, key):
    return jnp.clip(-0.2 * obs[:1] + 0.3 * jax.random.normal(key, (1,)), -1.0, 1.0)


@pytest.fixture(scope="module")
def rollouts(cartpole, mesh):
    env, params = cartpole
    traces = []

    def policy(obs, state, p, key):
        traces.append(1)  # runs once per trace
        return _noisy_policy(obs, state, p, key)

    single = make_rollout(env, _noisy_policy, NUM_ENVS, 30)
    sharded = make_rollout(env, policy, NUM_ENVS, 30, mesh=mesh)
    key = jax.random.key(3)
    return single(key, params), sharded(key, params), sharded, traces


def test_sharded_rollout_equals_the_single_device_one(rollouts):
    single, sharded, _, _ = rollouts
    # Per-copy computations are identical and the random bits do not depend on the layout: bitwise equal.
    assert _max_difference(single, sharded) == 0.0
    assert float(np.std(np.asarray(single.x))) > 0.01  # the copies really move


def test_sharded_rollout_outputs_are_laid_out_over_the_devices(rollouts):
    _, sharded, _, _ = rollouts
    assert sharded.x.sharding.spec == P(None, sharding.BATCH_AXIS)  # (T, N, nx): the copy axis split
    assert sharded.final_state.x.sharding.spec == P(sharding.BATCH_AXIS)
    assert len(sharded.x.sharding.device_set) == NUM_DEVICES
    shards = sharded.final_state.x.addressable_shards
    assert sorted(s.data.shape[0] for s in shards) == [NUM_ENVS // NUM_DEVICES] * NUM_DEVICES


def test_no_retrace_when_only_params_change(rollouts, cartpole):
    env, params = cartpole
    _, first, sharded, traces = rollouts
    count = len(traces)
    heavier = params.replace(physics=params.physics.replace(pole_mass=params.physics.pole_mass * 2.0))
    second = sharded(jax.random.key(3), heavier)
    assert len(traces) == count
    assert _max_difference(first.x, second.x) > 1e-4  # the new params were used


def test_a_batch_that_does_not_divide_names_both_numbers(cartpole, mesh):
    env, _ = cartpole
    with pytest.raises(ValueError, match=r"num_envs: 6 env copies do not split evenly over 4 devices"):
        make_rollout(env, _noisy_policy, 6, 5, mesh=mesh)


def test_sharded_evaluation_equals_the_single_device_one(cartpole, mesh):
    env, params = cartpole
    controller = make_lqr(env, params)
    single = evaluate(env, params, controller, jax.random.key(1), NUM_ENVS, measure_time=False)
    sharded = evaluate(env, params, controller, jax.random.key(1), NUM_ENVS, measure_time=False, mesh=mesh)
    assert _max_difference(single.trajectory, sharded.trajectory) <= 1e-6
    for name in ("rmse", "return", "failure_rate", "length"):
        assert sharded.summary[name] == pytest.approx(single.summary[name], rel=1e-5, abs=1e-7)
    with pytest.raises(ValueError, match=r"num_episodes: 10 env copies do not split evenly over 4 devices"):
        evaluate(env, params, controller, jax.random.key(1), 10, measure_time=False, mesh=mesh)


def test_sharded_evaluator_equals_the_single_device_one(cartpole, mesh):
    env, params = cartpole
    lqr = make_lqr(env, params)

    def build(gain):  # the controller rebuilt from a traced value, as for a learner's weights
        def act(ctrl_state, obs, step, reference):
            return gain * lqr.act_fn(ctrl_state, obs, step, reference)[0], ctrl_state

        return JaxController("scaled_lqr", lqr.reset_fn, act)

    single = make_evaluator(env, build, NUM_ENVS)(jnp.float32(0.9), jax.random.key(2), params)
    sharded_fn = make_evaluator(env, build, NUM_ENVS, mesh=mesh)
    sharded = sharded_fn(jnp.float32(0.9), jax.random.key(2), params)
    assert _max_difference(single.trajectory, sharded.trajectory) <= 1e-6
    for name in ("rmse", "return", "failure_rate", "length"):
        assert sharded.summary[name] == pytest.approx(single.summary[name], rel=1e-5, abs=1e-7)
    other = sharded_fn(jnp.float32(0.5), jax.random.key(2), params)  # a new gain: no new compilation, new numbers
    assert _max_difference(other.trajectory["x"], sharded.trajectory["x"]) > 1e-4
    with pytest.raises(ValueError, match=r"num_episodes: 10 env copies do not split evenly over 4 devices"):
        make_evaluator(env, build, 10, mesh=mesh)


def test_sharded_collection_reduces_the_observation_statistics_without_gathering(cartpole, mesh):
    """The normaliser's statistics of the (T, N, obs) buffer, N sharded, are local sums plus an all-reduce of
    (obs_size,) partial sums. Flattening the buffer to (T*N, obs) first has no sharded layout, and the compiled
    collection then all-gathered the whole buffer to every device (and reduced it on each)."""
    env, params = cartpole
    train_env = make_train_env(env, NUM_ENVS)
    state = init_collector(train_env, jax.random.key(2), params)

    def act(obs, key):
        noise = 0.3 * jax.random.normal(key, (obs.shape[0], 1))
        return ActOutput(jnp.clip(-0.2 * obs[:, :1] + noise, -1.0, 1.0), {})

    def run(state):
        return collect(train_env, params, state, act, jax.random.key(3), 20)[0]

    single = jax.jit(run)(state)
    placed = shard_runner_state(state, mesh)
    compiled = jax.jit(run, out_shardings=sharding.shardings_of(placed)).lower(placed).compile()
    hlo = compiled.as_text()
    assert "all-gather" not in hlo and "all-to-all" not in hlo
    assert "all-reduce" in hlo  # the statistics and episode means are global
    sharded = compiled(placed)
    assert float(sharded.obs_stats.count) == 20 * NUM_ENVS
    assert _max_difference(single, sharded) <= 1e-5
    assert sharded.obs.sharding.spec == P(sharding.BATCH_AXIS)


@pytest.fixture(scope="module")
def ppo(cartpole, mesh):
    env, params = cartpole
    learner = make_learner(tiny_ppo(total_env_steps=2 * 128, num_epochs=1, num_minibatches=2), env)
    state = jax.jit(learner.init)(jax.random.key(0), params)
    return learner, state, jax.jit(learner.update)


def test_sharded_ppo_training_equals_single_device_iterations(cartpole, mesh, ppo, tmp_path):
    env, params = cartpole
    learner, state, single_update = ppo
    placed = shard_runner_state(state, mesh)
    assert placed.collector.obs.sharding.spec == P(sharding.BATCH_AXIS)
    assert placed.params["log_std"].sharding.spec == P()
    single = state
    for _ in range(learner.num_iterations):
        single, metrics = single_update(single, params)
    final_states = []

    def policy_params(runner_state):  # run_training hands its final runner state here
        final_states.append(runner_state)
        return learner.policy_params(runner_state)

    sharded_learner = learner._replace(policy_params=policy_params)
    result = run_training(
        sharded_learner, env, params, jax.random.key(0), tmp_path, progress=False, csv=False, mesh=mesh
    )
    final = final_states[-1]
    assert result["iterations"] == learner.num_iterations == 2
    # Gradients are the full batch's mean, reduced across devices by the compiler (once: not N_devices times).
    assert _max_difference(single.params, final.params) <= 1e-5
    assert _max_difference(state.params, final.params) > 1e-5  # training did change the weights
    for name in ("loss", "grad_norm", "mean_reward", "policy_std", "explained_variance"):
        assert result["final_metrics"][name] == pytest.approx(float(metrics[name]), rel=1e-4, abs=1e-6)
    assert final.collector.env_state.x.sharding.spec == P(sharding.BATCH_AXIS)  # the layout kept chunk to chunk
    assert len(final.collector.env_state.x.sharding.device_set) == NUM_DEVICES
    assert final.params["log_std"].sharding.spec == P()


def test_training_with_copies_that_do_not_divide_names_the_option(cartpole, mesh, tmp_path):
    env, params = cartpole
    options = {**tiny_ppo(total_env_steps=6 * 16, num_epochs=1, num_minibatches=1), "num_envs": 6}
    learner = make_learner(options, env)
    with pytest.raises(ValueError, match=r"training.ppo.num_envs: 6 env copies do not split evenly over 4 devices"):
        run_training(learner, env, params, jax.random.key(0), tmp_path, progress=False, csv=False, mesh=mesh)


def test_rollout_devices_are_recorded_in_metrics_json(mesh, tmp_path):
    """``scg-jax rollout --devices 2`` lays its copies out over the first 2 devices and says so in metrics.json (that a
    sharded rollout gives the single-device numbers is ``test_sharded_rollout_equals_the_single_device_one``)."""
    import json

    from scg_cli import main

    args = ["rollout", "--system", "cartpole", "--episode-len", "0.5", "--num-envs", str(NUM_ENVS), "--devices", "2"]
    assert main([*args, "--out", str(tmp_path)]) == 0
    record = json.loads((tmp_path / "metrics.json").read_text())
    assert record["devices"] == [str(device) for device in jax.devices()[:2]] and len(set(record["devices"])) == 2
    assert record["summary"]["failure_rate"] == 0.0 and len(record["per_copy"]["rmse"]) == NUM_ENVS
