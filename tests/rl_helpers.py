"""Helpers shared by the PPO and SAC tests."""

import jax
import jax.numpy as jnp

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
