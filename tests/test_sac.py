"""SAC: the losses and the tanh-Gaussian against worked numbers and a numeric change of variables, the replay buffer,
config errors, seeds under ``jax.vmap``, and a saved policy that acts exactly like the one trained."""

import itertools
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from scg_algorithms.rl.counter import count_value
from scg_algorithms.rl.normalization import init_stats
from scg_algorithms.sac import Config, losses, make_learner, make_policy_from_config, make_train, parse_config, replay
from tests.rl_helpers import learner_fixtures, load_saved_policy, train_tiny_run

# 100 iterations of 8 transitions, 2 gradient steps each after 25 warm-up iterations (200 transitions); the buffer
# holds 400 transitions, so it wraps around twice.
TINY = {
    "total_env_steps": 800,
    "num_envs": 8,
    "utd": 0.25,
    "warmup_steps": 200,
    "batch_size": 32,
    "buffer_size": 400,
    "hidden_sizes": [16, 16],
}
NUM_SEEDS = 4
WARMUP_ITERATIONS, NUM_ITERATIONS, GRAD_STEPS = 25, 100, 2


cartpole, seeds_run = learner_fixtures(make_train, TINY, NUM_SEEDS)


# --------------------------------------------------------------------------------------------- losses
def test_critic_target_with_and_without_termination_takes_the_twin_minimum():
    # next_q = [[3, 5], [4, 1]]: the minimum over the two critics is [3, 1] (a different critic per sample).
    # soft value = min Q' - alpha log pi' = [3 - 0.2 * (-1), 1 - 0.2 * 0.5] = [3.2, 0.9]
    # y = r + gamma (1 - terminated) soft value = [1 + 0.9 * 3.2, 2 + 0] = [3.88, 2.0]
    target = losses.critic_target(
        jnp.array([1.0, 2.0]),
        jnp.array([False, True]),
        jnp.array([[3.0, 5.0], [4.0, 1.0]]),
        jnp.array([-1.0, 0.5]),
        0.2,
        0.9,
    )
    np.testing.assert_allclose(target, [3.88, 2.0], rtol=1e-6)
    # Without the termination the second sample bootstraps: 2 + 0.9 * 0.9 = 2.81.
    target = losses.critic_target(
        jnp.array([1.0, 2.0]),
        jnp.array([0.0, 0.0]),
        jnp.array([[3.0, 5.0], [4.0, 1.0]]),
        jnp.array([-1.0, 0.5]),
        0.2,
        0.9,
    )
    np.testing.assert_allclose(target, [3.88, 2.81], rtol=1e-6)


def test_critic_loss_regresses_both_critics_and_stops_the_target_gradient():
    q, target = jnp.array([[1.0, 2.0], [0.0, 4.0]]), jnp.array([2.0, 2.0])
    # 0.5 (mean([1, 0]) + mean([4, 4])) = 0.5 (0.5 + 4) = 2.25
    np.testing.assert_allclose(losses.critic_loss(q, target), 2.25)
    grad_q, grad_target = jax.grad(losses.critic_loss, argnums=(0, 1))(q, target)
    np.testing.assert_allclose(grad_q, (q - target) / 2)  # d/dQ_jb of 0.5 mean_b (Q_jb - y_b)^2, B = 2
    np.testing.assert_array_equal(grad_target, 0.0)


def test_actor_loss_worked_numbers():
    # min_j Q = [1, 0]; mean(alpha log pi - min Q) = mean(0.5 * (-1) - 1, 0.5 * 2 - 0) = mean(-1.5, 1.0) = -0.25
    q, log_prob = jnp.array([[1.0, 3.0], [2.0, 0.0]]), jnp.array([-1.0, 2.0])
    np.testing.assert_allclose(losses.actor_loss(q, log_prob, 0.5), -0.25)
    grad_q, grad_log_prob, grad_alpha = jax.grad(losses.actor_loss, argnums=(0, 1, 2))(q, log_prob, 0.5)
    np.testing.assert_allclose(grad_q, [[-0.5, 0.0], [0.0, -0.5]])  # only the smaller critic gets gradient
    np.testing.assert_allclose(grad_log_prob, [0.25, 0.25])  # alpha / B
    assert grad_alpha == 0.0


def test_temperature_loss_and_its_gradient_sign():
    log_prob, target_entropy = jnp.array([-1.0, 2.0]), -1.0
    # alpha = 0.5; mean(alpha (-log pi - target)) = 0.5 * mean(1 + 1, -2 + 1) = 0.5 * 0.5 = 0.25
    log_alpha = jnp.log(0.5)
    np.testing.assert_allclose(losses.temperature_loss(log_alpha, log_prob, target_entropy), 0.25, rtol=1e-6)
    # d/dlog_alpha = alpha (H_hat - target) with H_hat = -mean log pi = -0.5: 0.5 * 0.5 = 0.25 > 0, so descent lowers
    # the temperature while the entropy is above the target; a lower entropy (H_hat = -3) raises it.
    grad = jax.grad(losses.temperature_loss)(log_alpha, log_prob, target_entropy)
    np.testing.assert_allclose(grad, 0.25, rtol=1e-6)
    grad = jax.grad(losses.temperature_loss)(log_alpha, jnp.array([3.0, 3.0]), target_entropy)
    np.testing.assert_allclose(grad, 0.5 * (-3.0 + 1.0), rtol=1e-6)
    assert jax.grad(losses.temperature_loss, argnums=1)(log_alpha, log_prob, target_entropy).tolist() == [0.0, 0.0]


def test_polyak_update_numbers():
    target = {"w": jnp.array([0.0, 10.0]), "b": jnp.array(4.0)}
    online = {"w": jnp.array([1.0, 0.0]), "b": jnp.array(2.0)}
    updated = losses.polyak_update(target, online, 0.1)
    np.testing.assert_allclose(updated["w"], [0.1, 9.0], rtol=1e-6)
    np.testing.assert_allclose(updated["b"], 3.8, rtol=1e-6)
    # n updates towards a fixed online network: target_n = online + (1 - tau)^n (target_0 - online).
    n = 20
    for _ in range(n):
        target = losses.polyak_update(target, online, 0.1)
    np.testing.assert_allclose(target["w"], [1.0 - 0.9**n, 10.0 * 0.9**n], rtol=1e-5)
    np.testing.assert_array_equal(losses.polyak_update(target, online, 1.0)["w"], online["w"])


# --------------------------------------------------------------------------------------------- tanh-Gaussian
def test_tanh_gaussian_log_prob_is_the_change_of_variables():
    with jax.enable_x64(True):
        rng = np.random.default_rng(0)
        u, mean = rng.normal(size=(5, 3)) * 2, rng.normal(size=(5, 3))
        log_std = rng.normal(size=(5, 3)) * 0.5
        std = np.exp(log_std)
        log_normal = np.sum(-0.5 * ((u - mean) / std) ** 2 - np.log(std) - 0.5 * np.log(2 * np.pi), axis=-1)
        expected = log_normal - np.sum(np.log(1.0 - np.tanh(u) ** 2), axis=-1)
        np.testing.assert_allclose(losses.tanh_gaussian_log_prob(u, mean, log_std), expected, rtol=1e-12)


def test_tanh_gaussian_density_integrates_to_one_and_has_the_mean_of_tanh_u():
    with jax.enable_x64(True):
        mean, std = 0.3, 0.5
        a = np.linspace(-1.0, 1.0, 40_001)[1:-1]
        log_p = losses.tanh_gaussian_log_prob(np.arctanh(a)[:, None], np.full((1, 1), mean), np.log([[std]]))
        density = np.exp(np.asarray(log_p))
        np.testing.assert_allclose(np.trapezoid(density, a), 1.0, atol=1e-6)
        # E[a] under the density equals E[tanh(u)], u ~ N(0.3, 0.5^2), by Gauss-Hermite quadrature.
        nodes, weights = np.polynomial.hermite_e.hermegauss(60)
        expected_mean = np.sum(weights * np.tanh(mean + std * nodes)) / np.sqrt(2 * np.pi)
        np.testing.assert_allclose(np.trapezoid(a * density, a), expected_mean, atol=1e-6)


def test_log1m_tanh_sq_is_finite_for_saturated_inputs():
    u = jnp.array([-50.0, -20.0, -3.0, 0.0, 3.0, 20.0, 50.0])
    # log(1 - tanh^2 u) = log(sech^2 u) = log 4 - 2 |u| - 2 log(1 + exp(-2 |u|)), exact for any u.
    absu = np.abs(np.asarray(u, np.float64))
    expected = np.log(4.0) - 2 * absu - 2 * np.log1p(np.exp(-2 * absu))
    np.testing.assert_allclose(losses.log1m_tanh_sq(u), expected, rtol=1e-6)
    grad = jax.grad(lambda m: jnp.sum(losses.tanh_gaussian_log_prob(u, m, jnp.zeros_like(u))))(jnp.zeros_like(u))
    assert bool(jnp.all(jnp.isfinite(grad)))


def test_sample_tanh_gaussian_returns_the_log_prob_of_its_sample():
    key, mean, log_std = jax.random.key(3), jnp.array([[0.2, -1.0]] * 4), jnp.array([[-0.5, 0.3]] * 4)
    action, log_prob = losses.sample_tanh_gaussian(key, mean, log_std)
    u = mean + jnp.exp(log_std) * jax.random.normal(key, mean.shape)
    np.testing.assert_allclose(action, jnp.tanh(u), rtol=1e-6)
    np.testing.assert_allclose(log_prob, losses.tanh_gaussian_log_prob(u, mean, log_std), rtol=1e-6)
    assert bool(jnp.all(jnp.abs(action) <= 1.0))


# --------------------------------------------------------------------------------------------- replay buffer
def _items(values):
    values = jnp.asarray(values, jnp.float32)
    return {"obs": jnp.stack([values, -values], axis=-1), "reward": values}


def test_replay_add_wraps_around_at_capacity():
    buffer = replay.init_buffer(5, {"obs": jnp.zeros(2), "reward": jnp.zeros(())})
    buffer = replay.add(buffer, _items([0, 1, 2]))
    assert (int(buffer.position), int(buffer.size)) == (3, 3)
    # 3, 4 fill slots 3 and 4; 5, 6 overwrite the oldest, slots 0 and 1.
    buffer = jax.jit(replay.add)(buffer, _items([3, 4, 5, 6]))
    assert (int(buffer.position), int(buffer.size), buffer.capacity) == (2, 5, 5)
    np.testing.assert_array_equal(buffer.data["reward"], [5, 6, 2, 3, 4])
    np.testing.assert_array_equal(buffer.data["obs"][:, 1], [-5, -6, -2, -3, -4])
    with pytest.raises(ValueError, match="does not fit a buffer of capacity 5"):
        replay.add(buffer, _items(range(6)))
    with pytest.raises(ValueError, match="capacity: must be positive"):
        replay.init_buffer(0, {"reward": jnp.zeros(())})


def test_replay_sample_returns_only_stored_items_deterministically():
    buffer = replay.init_buffer(8, {"obs": jnp.zeros(2), "reward": jnp.zeros(())})
    buffer = replay.add(buffer, _items([10, 11, 12]))  # slots 3..7 still hold zeros
    sample = jax.jit(replay.sample, static_argnums=2)
    batch = sample(buffer, jax.random.key(0), 3000)
    assert set(np.unique(batch["reward"]).tolist()) == {10.0, 11.0, 12.0}
    np.testing.assert_array_equal(batch["obs"][:, 0], batch["reward"])  # fields stay aligned
    np.testing.assert_array_equal(batch["obs"][:, 1], -batch["reward"])
    # Uniform over the three: each count is 1000 +- 3 standard deviations (sqrt(3000 * 1/3 * 2/3) = 25.8).
    _, counts = np.unique(batch["reward"], return_counts=True)
    assert np.all(np.abs(counts - 1000) < 78), counts
    again = sample(buffer, jax.random.key(0), 3000)
    np.testing.assert_array_equal(again["reward"], batch["reward"])
    other = sample(buffer, jax.random.key(1), 3000)
    assert np.any(other["reward"] != batch["reward"])


# --------------------------------------------------------------------------------------------- config
@pytest.mark.parametrize(
    ("options", "field", "message"),
    [
        ({"learning_rate": 1e-3}, "learning_rate", "unknown key"),
        ({"gamma": 1.0}, "gamma", r"must be in \(0, 1\)"),
        ({"tau": 0.0}, "tau", r"must be in \(0, 1\]"),
        ({"actor_lr": -1.0}, "actor_lr", "must be positive"),
        ({"warmup_steps": -1}, "warmup_steps", "must be >= 0"),
        ({"batch_size": 0.5}, "batch_size", "expected an integer"),
        ({"autotune_alpha": "yes"}, "autotune_alpha", "expected true or false"),
        ({"activation": "sigmoid"}, "activation", "allowed values are tanh, relu"),
        ({"hidden_sizes": [16, 0]}, "hidden_sizes", "positive integers"),
        ({"log_std_min": 3.0}, "log_std_min", "below log_std_max"),
        ({"num_envs": 8, "utd": 0.3}, "utd", "must be a positive integer"),
        ({"num_envs": 8, "total_env_steps": 4}, "total_env_steps", "one iteration"),
        ({"num_envs": 8, "rollout_steps": 4, "buffer_size": 16}, "buffer_size", "must hold one iteration"),
    ],
)
def test_config_errors_name_the_field(cartpole, options, field, message):
    env, _ = cartpole
    with pytest.raises(ValueError, match=rf"^training\.sac\.{field}: .*{message}"):
        make_learner(options, env)


def test_config_derived_numbers_and_round_trip():
    config = parse_config(TINY)
    assert config.num_iterations == NUM_ITERATIONS and config.warmup_iterations == WARMUP_ITERATIONS
    assert config.grad_steps_per_iteration == GRAD_STEPS and config.capacity == 400 and config.hidden_sizes == (16, 16)
    assert parse_config(config.to_dict()) == config
    # The warm-up covers at least one batch and is clipped to the budget; the buffer to the budget.
    assert parse_config({"num_envs": 8, "warmup_steps": 0, "batch_size": 20}).warmup_iterations == 3
    small = parse_config({"num_envs": 8, "total_env_steps": 16, "warmup_steps": 100, "buffer_size": 1000})
    assert (small.warmup_iterations, small.capacity) == (2, 16)
    assert isinstance(config, Config)


# --------------------------------------------------------------------------------------------- whole runs
def _leaves(tree):
    """Leaves as numpy arrays (typed PRNG keys as their raw data)."""
    is_key = lambda x: jax.dtypes.issubdtype(x.dtype, jax.dtypes.prng_key)  # noqa: E731
    return [np.asarray(jax.random.key_data(x) if is_key(x) else x) for x in jax.tree.leaves(tree)]


def test_vmapped_seeds_give_different_policies_and_a_repeated_seed_the_same(seeds_run):
    _, (state, _), (state_again, _) = seeds_run
    actor = [jax.tree.leaves(jax.tree.map(lambda x, i=i: x[i], state.actor)) for i in range(NUM_SEEDS + 1)]
    for a, b in zip(actor[0], actor[NUM_SEEDS], strict=True):
        np.testing.assert_array_equal(a, b)
    for a, b in zip(_leaves(state), _leaves(state_again), strict=True):
        np.testing.assert_array_equal(a, b)
    for i, j in itertools.combinations(range(NUM_SEEDS), 2):
        difference = max(float(np.max(np.abs(a - b))) for a, b in zip(actor[i], actor[j], strict=True))
        assert difference > 1e-3, (i, j)
        assert float(np.max(np.abs(state.obs_stats.mean[i] - state.obs_stats.mean[j]))) > 1e-4, (i, j)


def test_warm_up_then_learning_and_the_buffer_wraps(seeds_run):
    _, (state, metrics), _ = seeds_run
    iteration = np.arange(1, NUM_ITERATIONS + 1)
    expected_grad_steps = GRAD_STEPS * np.maximum(iteration - WARMUP_ITERATIONS, 0)
    grad_steps = count_value(metrics["grad_steps"])
    np.testing.assert_array_equal(grad_steps, np.tile(expected_grad_steps, (NUM_SEEDS + 1, 1)))
    np.testing.assert_array_equal(count_value(metrics["env_steps"])[:, -1], 800)
    warmup, learning = metrics["critic_loss"][:, :WARMUP_ITERATIONS], metrics["critic_loss"][:, WARMUP_ITERATIONS:]
    np.testing.assert_array_equal(warmup, 0.0)
    assert np.all(learning > 0) and np.all(np.isfinite(learning))
    # The temperature starts at init_alpha = 0.1 and is tuned once learning starts. The metric is the mean of the
    # temperature each gradient step used: in the first learning iteration 0.1, then 0.1 exp(-1e-3) after Adam's
    # first step (a step of -lr in log alpha: the initial policy's entropy is above the target -1).
    np.testing.assert_allclose(metrics["alpha"][:, :WARMUP_ITERATIONS], 0.1, rtol=1e-6)
    np.testing.assert_allclose(metrics["alpha"][:, WARMUP_ITERATIONS], 0.1 * (1 + math.exp(-1e-3)) / 2, rtol=1e-6)
    assert np.all(np.abs(np.exp(state.log_alpha) - 0.1) > 1e-4)
    # 800 transitions through a 400-slot buffer: full, and the write position back at slot 0.
    np.testing.assert_array_equal(state.buffer.size, 400)
    np.testing.assert_array_equal(state.buffer.position, 0)
    np.testing.assert_array_equal(state.obs_stats.count, 800.0)
    assert set(np.unique(state.buffer.data["terminated"]).tolist()) <= {0.0, 1.0}


@pytest.fixture(scope="module")
def trained_dir(cartpole, tmp_path_factory, seeds_run):
    """``run_training`` of the tiny config with seed 0's key; the policy parameters it saves are captured."""
    return train_tiny_run(make_learner, TINY, cartpole, tmp_path_factory, seeds_run, "sac_run")


def test_run_training_equals_make_train(seeds_run, trained_dir):
    """The host driver (a fori_loop of ``update``, warm-up chosen by ``lax.cond``) runs the same iterations as
    ``make_train`` (two scans)."""
    _, (state, _), _ = seeds_run
    _, _, policy_params, result = trained_dir
    assert result["iterations"] == NUM_ITERATIONS and result["env_steps"] == 800
    lane0 = jax.tree.map(lambda x: x[0], state)
    for a, b in zip(jax.tree.leaves(policy_params.actor), jax.tree.leaves(lane0.actor), strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(policy_params.obs_stats.mean, lane0.obs_stats.mean, rtol=1e-5, atol=1e-6)


def test_saved_policy_acts_like_the_trained_one(cartpole, trained_dir):
    env, _ = cartpole
    _, learner, policy_params, _ = trained_dir
    obs, loaded, actions = load_saved_policy(cartpole, trained_dir, "sac", 800)
    np.testing.assert_array_equal(loaded, actions(learner.make_policy(policy_params)))
    # make_policy_from_config rebuilds the same deterministic policy from the saved config.
    _, apply = make_policy_from_config(parse_config(TINY).to_dict(), env.observation_size, env.action_size)
    np.testing.assert_array_equal(loaded, actions(lambda o: apply(policy_params, o)))
    # Not a trivial match: the actions vary with the observation, and the saved normaliser matters.
    assert float(jnp.std(loaded)) > 1e-4
    unnormalized = actions(learner.make_policy(policy_params._replace(obs_stats=init_stats(env.observation_size))))
    assert float(jnp.max(jnp.abs(unnormalized - loaded))) > 1e-5
    # A sampled action differs from the mean action but stays in [-1, 1].
    sampled = learner.make_policy(policy_params)(obs, jax.random.key(0))
    assert float(jnp.max(jnp.abs(sampled - learner.make_policy(policy_params)(obs)))) > 1e-2
    assert bool(jnp.all(jnp.abs(sampled) <= 1.0))
