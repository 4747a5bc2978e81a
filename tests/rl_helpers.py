"""Helpers shared by the PPO and SAC tests."""

import jax
import jax.numpy as jnp
import pytest

import scg_jax
from scg_algorithms.rl.envs import policy_action_to_input
from scg_algorithms.rl.policy import load_policy
from scg_algorithms.rl.training import run_training


def run_training_capturing_policy(learner, env, params, key, out_dir):
    """``run_training`` (no progress, no CSV) that also returns the policy parameters it saved.

    Returns:
        ``(policy_params, result)``: what ``learner.policy_params`` gave for the final runner state, and
        ``run_training``'s summary.
    """
    captured = []

    def policy_params(runner_state):
        captured.append(learner.policy_params(runner_state))
        return captured[-1]

    result = run_training(
        learner._replace(policy_params=policy_params), env, params, key, out_dir, progress=False, csv=False
    )
    return captured[-1], result


def run_seeds_twice(make_train, config, env, params, num_seeds: int):
    """``make_train(config, env)`` vmapped over the keys of seeds ``0..num_seeds-1`` and seed 0 again (the last
    lane), jitted once and run twice. Returns ``(keys, first, second)``."""
    train = jax.jit(jax.vmap(make_train(config, env), in_axes=(0, None)))
    keys = jnp.stack([jax.random.key(seed) for seed in (*range(num_seeds), 0)])
    return keys, train(keys, params), train(keys, params)


def train_tiny_run(make_learner, options, cartpole, tmp_path_factory, seeds_run, name: str):
    """Body of the ``trained_dir`` fixtures: ``run_training`` of ``options`` with seed 0's key (from ``seeds_run``)
    in a fresh folder ``name``, capturing the saved policy parameters.

    Returns:
        ``(out_dir, learner, policy_params, result)``.
    """
    env, params = cartpole
    keys, _, _ = seeds_run
    learner = make_learner(options, env)
    out_dir = tmp_path_factory.mktemp(name)
    policy_params, result = run_training_capturing_policy(learner, env, params, keys[0], out_dir)
    return out_dir, learner, policy_params, result


# The off-policy learners' tiny runs: 100 iterations of 8 transitions, 2 gradient steps each after 25 warm-up
# iterations (200 transitions); the buffer holds 400 transitions, so it wraps around twice.
TINY_OFF_POLICY = {
    "total_env_steps": 800,
    "num_envs": 8,
    "utd": 0.25,
    "warmup_steps": 200,
    "batch_size": 32,
    "buffer_size": 400,
    "hidden_sizes": [16, 16],
}
TINY_OFF_POLICY_SCHEDULE = (25, 100, 2)
"""Warm-up iterations, iterations and gradient steps per iteration of ``TINY_OFF_POLICY``."""


def tiny_ppo(total_env_steps: int, num_epochs: int, num_minibatches: int) -> dict:
    """A tiny PPO config: 8 copies x 16 steps an iteration, 16-unit hidden layers."""
    return {
        "total_env_steps": total_env_steps,
        "num_envs": 8,
        "rollout_length": 16,
        "num_epochs": num_epochs,
        "num_minibatches": num_minibatches,
        "actor_hidden": [16, 16],
        "critic_hidden": [16, 16],
    }


def set_options(section: str, **values) -> list[str]:
    """Command-line overrides ``--set <section>.<name>=<value>`` for each of ``values``, in order."""
    return [arg for name, value in values.items() for arg in ("--set", f"{section}.{name}={value}")]


def learner_fixtures(make_train, options, num_seeds: int):
    """The module fixtures ``cartpole`` (``(env, params)`` of cart-pole) and ``seeds_run`` (``run_seeds_twice`` of
    ``make_train`` with ``options`` over ``num_seeds`` seeds) of a learner's tests; assign both to module names."""

    @pytest.fixture(scope="module")
    def cartpole():
        env = scg_jax.make("cartpole")
        return env, env.default_params

    @pytest.fixture(scope="module")
    def seeds_run(cartpole):
        """``make_train`` vmapped over the keys of seeds 0..3 and seed 0 again (lane 4), jitted once; run twice."""
        env, params = cartpole
        return run_seeds_twice(make_train, options, env, params, num_seeds)

    return cartpole, seeds_run


def load_saved_policy(cartpole, trained_dir, name: str, env_steps: int):
    """Load the policy ``trained_dir`` saved, check its name and env steps, and act on 64 random observations.

    Returns:
        ``(obs, loaded, actions)``: the observations, the loaded controller's inputs for them, and a function
        mapping a policy (observation -> action in [-1, 1]) to its inputs for the same observations.
    """
    env, params = cartpole
    out_dir, _, _, _ = trained_dir
    controller = load_policy(out_dir, env, params)
    assert controller.name == name and controller.info["env_steps"] == env_steps
    obs = jax.random.uniform(jax.random.key(5), (64, env.observation_size), minval=-0.5, maxval=0.5)

    def actions(policy):
        return jax.jit(jax.vmap(lambda o: policy_action_to_input(env, policy(o), params.physics)))(obs)

    return obs, jax.jit(jax.vmap(lambda o: controller.act((), o, 0, None)[0]))(obs), actions


def check_run_training_equals_make_train(seeds_run, trained_dir, iterations: int, env_steps: int) -> None:
    """The host driver (a fori_loop of ``update``, warm-up chosen by ``lax.cond``) ran the same iterations as
    ``make_train`` (scans): the run's summary counts, and its saved actor and normaliser equal seed 0's lane of
    ``seeds_run`` to float rounding."""
    import numpy as np

    _, (state, _), _ = seeds_run
    _, _, policy_params, result = trained_dir
    assert result["iterations"] == iterations and result["env_steps"] == env_steps
    lane0 = jax.tree.map(lambda x: x[0], state)
    for a, b in zip(jax.tree.leaves(policy_params.actor), jax.tree.leaves(lane0.actor), strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(policy_params.obs_stats.mean, lane0.obs_stats.mean, rtol=1e-5, atol=1e-6)
