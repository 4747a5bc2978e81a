"""PPO-Lagrangian: the multiplier update, the combined advantage and the cost advantage on worked numbers; bad
input; and, on the constraint task, PPO's parameters (to float32 rounding) while the multiplier stays 0, but not
otherwise."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from scg_algorithms import ppo
from scg_algorithms.base import parse_options
from scg_algorithms.ppo_lagrangian import Config, combine_advantages, make_learner, multiplier_update
from scg_algorithms.ppo_lagrangian.train import (
    center_advantages,
    cost_gae,
    multiplier_adam_update,
    multiplier_optimizer,
)
from scg_jax.config import load_config, make_from_config
from tests.rl_helpers import tiny_ppo

CONFIG = "configs/paper_cartpole_constraint_rl.yaml"
CHEAP = ["env.physics_freq=50", "env.integrator=euler"]  # one Euler substep a control step: quick to compile
TINY = tiny_ppo(total_env_steps=384, num_epochs=2, num_minibatches=2)  # 3 iterations of 8 copies x 16 steps


def test_multiplier_update_worked_numbers():
    # lambda + lr (J_c - d), floored at 0: 0.5 + 0.035 * (0.03 - 0.01) = 0.5007; 0.001 + 0.035 * (0 - 0.01) = 0.00065;
    # 0.0001 - 0.00035 < 0 -> 0; no measurement (NaN) -> unchanged.
    lam = jnp.array([0.5, 0.001, 0.0001, 0.2])
    cost = jnp.array([0.03, 0.0, 0.0, jnp.nan])
    np.testing.assert_allclose(multiplier_update(lam, cost, 0.01, 0.035), [0.5007, 0.00065, 0.0, 0.2], rtol=1e-5)


def test_multiplier_adam_update_worked_numbers():
    # Adam's first step is lr * g / |g| (bias-corrected moments m = g, v = g^2, eps negligible) against the gradient
    # g = -(J_c - d): over the limit lambda rises by lr whatever J_c - d is, under it it falls by lr (floored at 0).
    lr, d = 0.035, 0.01
    for lam, cost, expected in [(0.5, 0.3, 0.535), (0.5, 0.011, 0.535), (0.5, 0.0, 0.465), (0.01, 0.0, 0.0)]:
        state = multiplier_optimizer(lr).init(jnp.float32(lam))
        new, state = multiplier_adam_update(jnp.float32(lam), state, jnp.float32(cost), d, lr)
        np.testing.assert_allclose(new, expected, rtol=1e-4, atol=1e-6)
    # Second step, same sign: m and v of two equal gradients give again a step of lr: 0.5 -> 0.535 -> 0.57.
    state = multiplier_optimizer(lr).init(jnp.float32(0.5))
    lam, state = multiplier_adam_update(jnp.float32(0.5), state, jnp.float32(0.3), d, lr)
    lam, state = multiplier_adam_update(lam, state, jnp.float32(0.3), d, lr)
    np.testing.assert_allclose(lam, 0.57, rtol=1e-4)
    # No measurement (NaN): lambda and Adam's moments unchanged.
    kept, kept_state = multiplier_adam_update(lam, state, jnp.float32(jnp.nan), d, lr)
    assert float(kept) == float(lam)
    jax.tree.map(lambda a, b: np.testing.assert_array_equal(a, b), kept_state, state)


def test_cost_advantages_are_centred_not_scaled():
    # (0, 0, 0, 0.4) -> mean 0.1 subtracted, the spread kept: (-0.1, -0.1, -0.1, 0.3); standardising would give
    # (-0.577, -0.577, -0.577, 1.732) whatever the violations' size.
    np.testing.assert_allclose(center_advantages(jnp.array([0.0, 0.0, 0.0, 0.4])), [-0.1, -0.1, -0.1, 0.3], atol=1e-7)


def test_combined_advantage_worked_numbers():
    # lambda = 1: ((1 - 3) / 2, (2 + 1) / 2); lambda = 0: A_r unchanged.
    np.testing.assert_allclose(combine_advantages(jnp.array([1.0, 2.0]), jnp.array([3.0, -1.0]), 1.0), [-1.0, 1.5])
    np.testing.assert_array_equal(combine_advantages(jnp.array([1.0, 2.0]), jnp.array([3.0, -1.0]), 0.0), [1.0, 2.0])


def test_cost_advantage_worked_numbers():
    # Costs (0, 1, 1, 0), V_c = 0.5 everywhere, cost_gamma 0.5, cost_gae_lambda 0.5; step 2 terminates.
    # delta = c + gamma (1 - term) V'_c - V_c = (0 + 0.25 - 0.5, 1 + 0.25 - 0.5, 1 + 0 - 0.5, 0 + 0.25 - 0.5)
    #       = (-0.25, 0.75, 0.5, -0.25);  A_3 = -0.25;  A_2 = 0.5 (episode end);  A_1 = 0.75 + 0.25 * 0.5 = 0.875;
    # A_0 = -0.25 + 0.25 * 0.875 = -0.03125; targets A + 0.5.
    options = {"cost_gamma": 0.5, "cost_gae_lambda": 0.5, "termination_cost": "none"}
    config = parse_options(Config, options, "training.ppo_lagrangian")
    values = jnp.full(4, 0.5)
    terminated = jnp.array([False, False, True, False])
    adv, targets = cost_gae(jnp.array([0.0, 1.0, 1.0, 0.0]), values, values, terminated, jnp.zeros(4, bool), config)
    np.testing.assert_allclose(adv, [-0.03125, 0.875, 0.5, -0.25], rtol=1e-6)
    np.testing.assert_allclose(targets, [0.46875, 1.375, 1.0, 0.25], rtol=1e-6)
    # Absorbing termination: the terminating step (cost 1) is followed by cost 1 forever, worth 1 / (1 - 0.5) = 2:
    # delta_2 = 1 + 0.5 * 2 - 0.5 = 1.5 = A_2;  A_1 = 0.75 + 0.25 * 1.5 = 1.125;  A_0 = -0.25 + 0.25 * 1.125 = 0.03125.
    config = parse_options(Config, {**options, "termination_cost": "absorbing"}, "training.ppo_lagrangian")
    adv, _ = cost_gae(jnp.array([0.0, 1.0, 1.0, 0.0]), values, values, terminated, jnp.zeros(4, bool), config)
    np.testing.assert_allclose(adv, [0.03125, 1.125, 1.5, -0.25], rtol=1e-6)


def test_bad_cost_limits_are_named():
    env, _ = make_from_config(load_config(CONFIG, CHEAP))
    with pytest.raises(ValueError, match=r"training.ppo_lagrangian.cost_limit: must be >= 0, got -0.5"):
        make_learner({**TINY, "cost_limit": -0.5}, env)
    with pytest.raises(ValueError, match=r"training.ppo_lagrangian.cost_limit: a fraction of steps must be in"):
        make_learner({**TINY, "cost_limit": 2.0}, env)
    with pytest.raises(ValueError, match=r"training.ppo_lagrangian.cost_limit_unit"):
        make_learner({**TINY, "cost_limit_unit": "percent"}, env)


def _runner(learner, env_params):
    """``run(multiplier=None)``: the whole run from seed 0 (init and iterations jitted once, reused), optionally
    starting the Lagrange multiplier at ``multiplier``."""
    init = jax.jit(learner.init)
    iterate = jax.jit(
        lambda r: jax.lax.scan(lambda r, _: learner.update(r, env_params), r, None, learner.num_iterations)
    )

    def run(multiplier=None):
        runner = init(jax.random.key(0), env_params)
        if multiplier is not None:
            runner = runner._replace(aux={**runner.aux, "multiplier": jnp.asarray(multiplier, jnp.float32)})
        return iterate(runner)

    run.init = init
    return run


@pytest.fixture(scope="module")
def constraint_runs():
    # The constraint task: the tiny untrained policies violate on about a third of their steps, so the cost
    # critic and cost advantages are exercised in every run. A limit of 1 (every step in violation) is above
    # anything reachable: with the plain ascent rule (lambda_optimizer: sgd) the multiplier decreases by
    # lambda_lr (1 - J_c) an iteration, floored at 0, so from 0 it stays 0 and from 5 it falls by that. Both runs
    # share one compiled program (the multiplier is a runner-state value); PPO is the second.
    env, params = make_from_config(load_config(CONFIG, CHEAP))
    run_ppo = _runner(ppo.make_learner(TINY, env), params)
    sgd = _runner(make_learner({**TINY, "cost_limit": 1.0, "lambda_lr": 0.5, "lambda_optimizer": "sgd"}, env), params)
    return run_ppo(), sgd(multiplier=0.0), sgd(multiplier=5.0), run_ppo.init(jax.random.key(0), params)


def _max_difference(a, b) -> float:
    return max(float(jnp.max(jnp.abs(x - y))) for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True))


def test_with_the_multiplier_at_zero_learning_is_ppo(constraint_runs):
    (plain_runner, plain_metrics), (runner, metrics), _, initial = constraint_runs
    assert float(jnp.max(metrics["cost_estimate"])) > 0.05  # costs were incurred, the cost critic trained
    np.testing.assert_array_equal(metrics["lagrange_multiplier"], 0.0)
    # PPO and PPO-Lagrangian are two compiled programs, which XLA may round in different orders: the parameters
    # agree to float32 rounding (measured 5e-6 of how far training moved them), not bit for bit. A cost term that
    # leaked into the update at lambda = 0 moves them by about as much as training does (the active run below).
    moved = _max_difference(plain_runner.params, initial.params)
    assert _max_difference(plain_runner.params, runner.params) < 1e-4 * moved
    np.testing.assert_allclose(plain_metrics["episode_return"], metrics["episode_return"], rtol=1e-5)
    assert np.all(np.isfinite(metrics["cost_value_loss"]))


def test_an_active_multiplier_follows_the_update_and_changes_learning(constraint_runs):
    (plain_runner, _), _, (runner, metrics), initial = constraint_runs
    lam, cost = np.asarray(metrics["lagrange_multiplier"]), np.asarray(metrics["cost_estimate"])
    # lambda_k = max(0, lambda_{k-1} + 0.5 (J_c,k - 1)) from 5 (the update comes before each iteration's SGD epochs).
    expected = 5.0 + np.cumsum(0.5 * (cost - 1.0))
    np.testing.assert_allclose(lam, expected, rtol=1e-5)
    assert np.all(lam > 0)
    # The multiplier changes learning by as much as training moves the policy (measured 2x), far above rounding.
    moved = _max_difference(plain_runner.params, initial.params)
    assert _max_difference(plain_runner.params["actor"], runner.params["actor"]) > 0.2 * moved
