"""PPO: GAE and the clipped losses against worked numbers, config errors, seeds under ``jax.vmap``, and a saved policy
that acts exactly like the one trained."""

import itertools
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.stats

from scg_algorithms.ppo import Config, losses, make_learner, make_train
from scg_algorithms.rl.counter import count_value
from scg_algorithms.rl.normalization import init_stats
from tests.rl_helpers import learner_fixtures, load_saved_policy, tiny_ppo, train_tiny_run

# 4 iterations of 8 copies x 16 steps; one epoch of one minibatch, so the first (only) gradient step of an iteration
# evaluates the loss at the rollout's own parameters (ratio 1: see test_rollout_log_probs_are_recomputed_exactly).
TINY = tiny_ppo(total_env_steps=512, num_epochs=1, num_minibatches=1)
NUM_SEEDS = 4


cartpole, seeds_run = learner_fixtures(make_train, TINY, NUM_SEEDS)


# --------------------------------------------------------------------------------------------- GAE
GAMMA, LAM = 0.9, 0.8  # gamma lam = 0.72
REWARDS = [1.0, 2.0, 3.0, 4.0]
VALUES = [0.5, 1.0, 1.5, 2.0]
# V(final_obs) of each step; 10 at step 1 is the value of the observation the step 1 reached when the episode ends.
NEXT_VALUES = [1.0, 10.0, 2.0, 3.0]


def _gae(terminated, truncated):
    flags = lambda f: jnp.asarray(f, bool)  # noqa: E731
    return losses.gae(
        jnp.asarray(REWARDS),
        jnp.asarray(VALUES),
        jnp.asarray(NEXT_VALUES),
        flags(terminated),
        flags(truncated),
        GAMMA,
        LAM,
    )


def test_gae_at_a_termination_does_not_bootstrap_and_cuts_the_trace():
    # The episode terminates at step 1 and a new one starts at step 2.
    # delta_0 = 1 + 0.9 * 1.0 - 0.5 = 1.4
    # delta_1 = 2 + 0 (terminated: no bootstrap from V' = 10) - 1.0 = 1.0
    # delta_2 = 3 + 0.9 * 2.0 - 1.5 = 3.3
    # delta_3 = 4 + 0.9 * 3.0 - 2.0 = 4.7   (end of the rollout: its delta bootstraps, nothing follows)
    # A_3 = 4.7;  A_2 = 3.3 + 0.72 * 4.7 = 6.684;  A_1 = 1.0 (episode end);  A_0 = 1.4 + 0.72 * 1.0 = 2.12
    advantages, returns = _gae([0, 1, 0, 0], [0, 0, 0, 0])
    expected = [2.12, 1.0, 6.684, 4.7]
    np.testing.assert_allclose(advantages, expected, rtol=1e-6)
    np.testing.assert_allclose(returns, np.add(expected, VALUES), rtol=1e-6)


def test_gae_at_a_time_limit_bootstraps_from_the_final_observation_but_cuts_the_trace():
    # Same rollout, but step 1 is truncated (time limit): delta_1 = 2 + 0.9 * 10 - 1.0 = 10.0.
    # A_1 = 10.0 (the trace still stops: A_2 belongs to the next episode);  A_0 = 1.4 + 0.72 * 10.0 = 8.6
    advantages, returns = _gae([0, 0, 0, 0], [0, 1, 0, 0])
    expected = [8.6, 10.0, 6.684, 4.7]
    np.testing.assert_allclose(advantages, expected, rtol=1e-6)
    np.testing.assert_allclose(returns, np.add(expected, VALUES), rtol=1e-6)


def test_gae_without_episode_end_runs_the_trace_through():
    # No boundary; V'_1 = 10 is then used as the bootstrap of step 1 (within an episode V'_t is V(obs_{t+1})).
    # delta = [1.4, 10.0, 3.3, 4.7];  A_3 = 4.7;  A_2 = 6.684;  A_1 = 10 + 0.72 * 6.684 = 14.81248;
    # A_0 = 1.4 + 0.72 * 14.81248 = 12.0649856
    advantages, _ = _gae([0, 0, 0, 0], [0, 0, 0, 0])
    np.testing.assert_allclose(advantages, [12.0649856, 14.81248, 6.684, 4.7], rtol=1e-6)


def test_gae_matches_a_loop_over_batched_random_rollouts():
    rng = np.random.default_rng(0)
    T, N = 12, 5
    rewards, values, next_values = (rng.normal(size=(T, N)).astype(np.float32) for _ in range(3))
    terminated, truncated = rng.random((T, N)) < 0.15, rng.random((T, N)) < 0.15
    gamma, lam = 0.97, 0.9
    advantages, returns = losses.gae(
        jnp.asarray(rewards),
        jnp.asarray(values),
        jnp.asarray(next_values),
        jnp.asarray(terminated),
        jnp.asarray(truncated),
        gamma,
        lam,
    )
    expected = np.zeros((T, N))
    for n in range(N):
        following = 0.0
        for t in reversed(range(T)):
            delta = rewards[t, n] + gamma * (not terminated[t, n]) * next_values[t, n] - values[t, n]
            following = delta + gamma * lam * (not (terminated[t, n] or truncated[t, n])) * following
            expected[t, n] = following
    np.testing.assert_allclose(advantages, expected, rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(returns, expected + values, rtol=1e-5, atol=1e-5)


def test_gae_with_lambda_one_gives_discounted_returns_of_a_terminated_episode():
    # Reward 1 for 5 steps, then termination, V = 0 (the 100 at the terminal step's final observation must be
    # ignored): the return from step t is sum_{k<5-t} gamma^k.
    gamma, T = 0.9, 5
    terminated = jnp.arange(T) == T - 1
    next_values = jnp.where(terminated, 100.0, 0.0)
    _, returns = losses.gae(jnp.ones(T), jnp.zeros(T), next_values, terminated, jnp.zeros(T, bool), gamma, 1.0)
    np.testing.assert_allclose(returns, [(1 - gamma ** (T - t)) / (1 - gamma) for t in range(T)], rtol=1e-6)


def test_value_of_a_never_ending_constant_reward_is_one_over_one_minus_gamma():
    """Fit a constant value V = c to the GAE returns of reward 1 forever, cut into 4-step time-limited episodes,
    by the fixed-point iteration c <- mean(returns(c)). With the bootstrap at every time limit the fixed point is
    the infinite-horizon value 1 / (1 - gamma) = 10 (delta = 1 + gamma c - c = 0 there); treating a time limit as a
    termination would give the 4-step value (1 - gamma^4) / (1 - gamma) = 3.44 instead."""
    gamma, lam, T, episode = 0.9, 0.95, 12, 4
    truncated = (jnp.arange(T) % episode) == episode - 1
    terminated = jnp.zeros(T, bool)

    def fit(c, _):
        values = jnp.full(T, c)
        _, returns = losses.gae(jnp.ones(T), values, values, terminated, truncated, gamma, lam)
        return jnp.mean(returns), None

    c, _ = jax.lax.scan(fit, jnp.float32(0.0), None, 300)
    np.testing.assert_allclose(c, 1.0 / (1.0 - gamma), rtol=1e-4)


# --------------------------------------------------------------------------------------------- PPO losses
def test_clipped_surrogate_worked_numbers_and_gradient():
    # ratios rho and advantages A, eps = 0.2; min(rho A, clip(rho, 0.8, 1.2) A) per sample:
    #   rho 1.5, A  2: min(3.0, 2.4)  = 2.4   (clipped: no gradient)
    #   rho 1.5, A -2: min(-3.0, -2.4) = -3.0 (unclipped)
    #   rho 0.5, A  2: min(1.0, 1.6)  = 1.0   (unclipped)
    #   rho 0.5, A -2: min(-1.0, -1.6) = -1.6 (clipped: no gradient)
    #   rho 1.1, A  1: min(1.1, 1.1)  = 1.1   (inside the clip range)
    # loss = -(2.4 - 3.0 + 1.0 - 1.6 + 1.1) / 5 = 0.02; dL/dlog_prob_i = -rho_i A_i / 5 where unclipped, else 0.
    rho = np.array([1.5, 1.5, 0.5, 0.5, 1.1])
    advantages = jnp.array([2.0, -2.0, 2.0, -2.0, 1.0])
    old_log_prob = jnp.array([-1.0, 0.3, 2.0, -0.7, 0.0])
    log_prob = old_log_prob + jnp.log(jnp.asarray(rho, jnp.float32))
    (loss, info), grad = jax.value_and_grad(losses.clipped_surrogate_loss, has_aux=True)(
        log_prob, old_log_prob, advantages, 0.2
    )
    np.testing.assert_allclose(loss, 0.02, atol=1e-6)
    np.testing.assert_allclose(grad, [0.0, 0.6, -0.2, 0.0, -0.22], atol=1e-6)
    np.testing.assert_allclose(info["clip_fraction"], 0.8)
    np.testing.assert_allclose(info["approx_kl"], np.mean((rho - 1) - np.log(rho)), rtol=1e-5)


def test_value_loss_worked_numbers_with_and_without_clip():
    values, old_values, returns = jnp.array([1.0, 2.0, 3.0]), jnp.array([1.5, 2.0, 2.0]), jnp.array([0.0, 2.0, 5.0])
    # Unclipped: 0.5 mean([1, 0, 4]) = 5/6.
    np.testing.assert_allclose(losses.value_loss(values, old_values, returns), 5.0 / 6.0, rtol=1e-6)
    # eps 0.5: V_c = old + clip(V - old, +-0.5) = [1.0, 2.0, 2.5]; (V_c - R)^2 = [1, 0, 6.25];
    # max with [1, 0, 4] -> [1, 0, 6.25]; 0.5 * 7.25 / 3.
    np.testing.assert_allclose(losses.value_loss(values, old_values, returns, 0.5), 7.25 / 6.0, rtol=1e-6)


def test_gaussian_log_prob_and_entropy_match_scipy():
    mean, log_std = np.array([[0.3, -1.0], [0.0, 2.0]]), np.log([0.5, 2.0])
    action = np.array([[0.1, 0.5], [-1.0, 2.5]])
    expected = scipy.stats.norm.logpdf(action, mean, np.exp(log_std)).sum(axis=-1)
    np.testing.assert_allclose(losses.gaussian_log_prob(mean, log_std, action), expected, rtol=1e-6)
    # Closed form sum_i 0.5 (1 + log 2 pi) + log sigma_i; sigmas 0.5 and 2 cancel in the log: 1 + log(2 pi).
    entropy = losses.gaussian_entropy(jnp.asarray(log_std))
    np.testing.assert_allclose(entropy, 1.0 + math.log(2 * math.pi), rtol=1e-6)
    np.testing.assert_allclose(entropy, scipy.stats.norm(0.0, np.exp(log_std)).entropy().sum(), rtol=1e-6)


def test_advantage_normalisation():
    normalized = losses.normalize_advantages(jnp.array([1.0, 2.0, 3.0, 4.0]))
    # mean 2.5, population std sqrt(1.25)
    np.testing.assert_allclose(normalized, (np.array([1.0, 2.0, 3.0, 4.0]) - 2.5) / math.sqrt(1.25), rtol=1e-6)
    np.testing.assert_allclose([jnp.mean(normalized), jnp.std(normalized)], [0.0, 1.0], atol=1e-6)
    # A constant batch stays finite (zero) thanks to the eps.
    np.testing.assert_array_equal(losses.normalize_advantages(jnp.full(3, 7.0)), 0.0)


def test_ppo_loss_is_the_weighted_sum_and_the_entropy_bonus_raises_log_std():
    rng = np.random.default_rng(1)
    B, d = 6, 2
    mean = jnp.asarray(rng.normal(size=(B, d)), jnp.float32)
    log_std = jnp.array([-0.5, 0.2])
    actions = mean + 0.3
    old_log_prob = losses.gaussian_log_prob(mean, log_std, actions) - 0.05
    values, returns = jnp.asarray(rng.normal(size=B), jnp.float32), jnp.asarray(rng.normal(size=B), jnp.float32)
    advantages = jnp.asarray(rng.normal(size=B), jnp.float32)
    kwargs = {"clip_eps": 0.2, "value_clip_eps": None, "vf_coef": 0.5, "ent_coef": 0.01}
    args = (mean, log_std, values, actions, old_log_prob, values, advantages, returns)
    loss, info = losses.ppo_loss(*args, **kwargs)
    np.testing.assert_allclose(loss, info["policy_loss"] + 0.5 * info["value_loss"] - 0.01 * info["entropy"], rtol=1e-6)
    np.testing.assert_allclose(info["value_loss"], 0.5 * np.mean((np.asarray(values) - np.asarray(returns)) ** 2))
    # Zero advantages: the only gradient in log_std is the entropy bonus's, -ent_coef per dimension (descent
    # then raises log_std).
    zero_args = (mean, log_std, values, actions, old_log_prob, values, jnp.zeros(B), values)
    grad = jax.grad(lambda s: losses.ppo_loss(mean, s, *zero_args[2:], **kwargs)[0])(log_std)
    np.testing.assert_allclose(grad, [-0.01, -0.01], rtol=1e-5)


# --------------------------------------------------------------------------------------------- weighted losses
def test_weighted_clipped_surrogate_worked_numbers_and_gradient():
    # The samples of test_clipped_surrogate_worked_numbers_and_gradient, weights (1, 0, 1, 0, 1): the terms of the
    # kept samples are 2.4 (clipped), 1.0 and 1.1, so L = -(2.4 + 1.0 + 1.1) / 3 = -1.5; dL/dlog_prob_i is
    # -rho_i A_i / 3 for a kept, unclipped sample (-1/3, -1.1/3) and 0 for every other one.
    rho = np.array([1.5, 1.5, 0.5, 0.5, 1.1])
    advantages = jnp.array([2.0, -2.0, 2.0, -2.0, 1.0])
    old_log_prob = jnp.array([-1.0, 0.3, 2.0, -0.7, 0.0])
    log_prob = old_log_prob + jnp.log(jnp.asarray(rho, jnp.float32))
    weight = jnp.array([1.0, 0.0, 1.0, 0.0, 1.0])
    (loss, info), grad = jax.value_and_grad(losses.clipped_surrogate_loss, has_aux=True)(
        log_prob, old_log_prob, advantages, 0.2, weight
    )
    np.testing.assert_allclose(loss, -1.5, rtol=1e-6)
    np.testing.assert_allclose(grad, [0.0, 0.0, -1.0 / 3.0, 0.0, -1.1 / 3.0], atol=1e-6)
    np.testing.assert_allclose(info["clip_fraction"], 2.0 / 3.0, rtol=1e-6)  # samples 0 and 2 of the kept three
    # Weighted advantage normalisation: mean and std of the kept (2, 2, 1) are 5/3 and sqrt(2)/3.
    np.testing.assert_allclose(
        losses.normalize_advantages(advantages, weight=weight)[jnp.array([0, 2, 4])],
        (np.array([2.0, 2.0, 1.0]) - 5.0 / 3.0) / (math.sqrt(2.0) / 3.0),
        rtol=1e-5,
    )


def _loss_batch(key, n=12, d=2):
    k = jax.random.split(key, 7)
    mean, actions = jax.random.normal(k[0], (n, d)), jax.random.normal(k[1], (n, d))
    values, old_values, returns = (jax.random.normal(k[i], (n,)) for i in (2, 3, 4))
    advantages, old_log_prob = jax.random.normal(k[5], (n,)), -2.0 + 0.1 * jax.random.normal(k[6], (n,))
    return mean, jnp.array([-0.3, 0.2]), values, actions, old_log_prob, old_values, advantages, returns


LOSS_OPTIONS = {"clip_eps": 0.2, "value_clip_eps": 0.3, "vf_coef": 0.5, "ent_coef": 0.01}


def test_weights_of_one_give_the_unweighted_loss_and_zero_one_weights_the_loss_of_the_subset():
    batch = _loss_batch(jax.random.key(3))
    weighted = jax.jit(lambda weight, *b: losses.ppo_loss(*b, **LOSS_OPTIONS, weight=weight))
    unweighted = jax.jit(lambda *b: losses.ppo_loss(*b, **LOSS_OPTIONS))
    ones, reference = weighted(jnp.ones(12), *batch), unweighted(*batch)
    jax.tree.map(lambda a, b: np.testing.assert_allclose(a, b, rtol=1e-6, atol=1e-8), ones, reference)

    weight = jnp.array([1, 0, 1, 1, 0, 0, 1, 1, 0, 1, 0, 1], jnp.float32)
    keep = np.asarray(weight, bool)
    subset = [batch[0][keep], batch[1], *(x[keep] for x in batch[2:])]
    # With weights, the advantages are normalised with the weighted mean and std: those of the subset.
    subset[6] = losses.normalize_advantages(subset[6])
    masked = list(batch)
    masked[6] = losses.normalize_advantages(batch[6], weight=weight)
    loss, info = weighted(weight, *masked)
    ref_loss, ref_info = unweighted(*subset)
    np.testing.assert_allclose(loss, ref_loss, rtol=1e-5)
    for name in ("policy_loss", "value_loss", "entropy", "approx_kl", "clip_fraction"):
        np.testing.assert_allclose(info[name], ref_info[name], rtol=1e-5, atol=1e-7)


def test_all_zero_weights_give_zero_loss_and_zero_gradient():
    """An adversary that drove no copy in a minibatch: its loss, and its gradient (entropy bonus included), are 0."""
    mean, log_std, values, *rest = _loss_batch(jax.random.key(4))

    def loss(mean, log_std, values):
        return losses.ppo_loss(mean, log_std, values, *rest, **LOSS_OPTIONS, weight=jnp.zeros(12))[0]

    value, grads = jax.value_and_grad(loss, argnums=(0, 1, 2))(mean, log_std, values)
    assert float(value) == 0.0
    for grad in grads:
        np.testing.assert_array_equal(grad, 0.0)


# --------------------------------------------------------------------------------------------- config
@pytest.mark.parametrize(
    ("options", "field", "message"),
    [
        ({"learning_rat": 1e-3}, "learning_rat", "unknown key.*did you mean 'learning_rate'"),
        ({"gamma": 1.5}, "gamma", r"must be in \[0, 1\]"),
        ({"gae_lambda": -0.1}, "gae_lambda", r"must be in \[0, 1\]"),
        ({"learning_rate": "fast"}, "learning_rate", "expected a finite number"),
        ({"learning_rate": 0.0}, "learning_rate", "must be positive"),
        ({"num_envs": 0}, "num_envs", "must be positive"),
        ({"num_envs": 2.5}, "num_envs", "expected an integer"),
        ({"normalize_observations": 1}, "normalize_observations", "expected true or false"),
        ({"activation": "sigmoid"}, "activation", "allowed values are tanh, relu"),
        ({"actor_hidden": []}, "actor_hidden", "list of layer sizes"),
        ({"critic_hidden": [64, 0]}, "critic_hidden", "positive integers"),
        ({"num_envs": 8, "rollout_length": 16, "num_minibatches": 3}, "num_minibatches", "must divide the batch"),
        ({"num_envs": 8, "rollout_length": 16, "total_env_steps": 100}, "total_env_steps", "at least one batch"),
        ({"value_clip_eps": -0.1}, "value_clip_eps", "must be >= 0"),
    ],
)
def test_config_errors_name_the_field(cartpole, options, field, message):
    env, _ = cartpole
    with pytest.raises(ValueError, match=rf"^training\.ppo\.{field}: .*{message}"):
        make_learner(options, env)


def test_a_config_built_directly_is_checked_too(cartpole):
    env, _ = cartpole
    with pytest.raises(ValueError, match=r"^training\.ppo\.num_minibatches: "):
        make_train(Config(num_envs=8, rollout_length=16, total_env_steps=1024, num_minibatches=3), env)
    # The fields' own checks too (declared with option(check=...)), and their conversions: layer sizes are ints.
    with pytest.raises(ValueError, match=r"^training\.ppo\.gamma: must be in \[0, 1\], got 1\.5"):
        make_learner(Config(gamma=1.5), env)
    with pytest.raises(ValueError, match=r"^training\.ppo\.critic_hidden: expected integers, got \[64\.5\]"):
        make_learner(Config(critic_hidden=(64.5,)), env)
    config = Config(num_envs=8, rollout_length=16, total_env_steps=1000, num_minibatches=4, actor_hidden=[32.0, 16])
    learner = make_learner(config, env)
    assert learner.num_iterations == 7  # 1000 // 128: the remainder of the budget is not run
    assert learner.config.actor_hidden == (32, 16) and all(isinstance(h, int) for h in learner.config.actor_hidden)


# --------------------------------------------------------------------------------------------- whole runs
def test_vmapped_seeds_give_different_policies_and_a_repeated_seed_the_same(seeds_run):
    _, (state, metrics), (state_again, _) = seeds_run
    actor = [jax.tree.leaves(jax.tree.map(lambda x, i=i: x[i], state.params["actor"])) for i in range(NUM_SEEDS + 1)]
    # Lane 4 has lane 0's key: bit-identical, as is a second call of the compiled run.
    for a, b in zip(actor[0], actor[NUM_SEEDS], strict=True):
        np.testing.assert_array_equal(a, b)
    for a, b in zip(jax.tree.leaves(state), jax.tree.leaves(state_again), strict=True):
        np.testing.assert_array_equal(a, b)
    for i, j in itertools.combinations(range(NUM_SEEDS), 2):
        difference = max(float(np.max(np.abs(a - b))) for a, b in zip(actor[i], actor[j], strict=True))
        assert difference > 1e-3, (i, j)
        # Different seeds see different episodes: the observation statistics differ too.
        assert float(np.max(np.abs(state.obs_stats.mean[i] - state.obs_stats.mean[j]))) > 1e-4, (i, j)
    # The whole budget ran: 4 iterations of 8 x 16 steps, each copy's observations merged into the statistics.
    np.testing.assert_array_equal(count_value(metrics["env_steps"]), np.tile([128, 256, 384, 512], (NUM_SEEDS + 1, 1)))
    np.testing.assert_array_equal(state.obs_stats.count, 512.0)
    # The step size decays linearly from 1e-3 to 0 over the 4 updates (one per iteration): the metric is the
    # schedule after each update.
    np.testing.assert_allclose(metrics["learning_rate"][0], [7.5e-4, 5e-4, 2.5e-4, 0.0], atol=1e-9)
    assert np.all(np.isfinite(metrics["loss"]))


def test_training_moves_the_policy_by_adams_first_step(cartpole, seeds_run):
    """An iteration of TINY is one Adam step (one epoch of one minibatch). Adam's first step moves each parameter by
    ``lr g / (|g| + eps)`` (its moments are ``g`` and ``g^2`` after bias correction), so by at most the step size
    ``lr = 1e-3`` (the decay starts after it), and by ``lr`` to within 2% wherever ``|g| >= 50 eps = 5e-4``: the
    policy's output layer, and the state-independent ``log_std``, whose gradient sums over the whole batch (to
    within 0.1%). (The hidden layers' gradients pass through the output layer's 0.01-scale initial weights and are
    smaller.)"""
    env, params = cartpole
    keys, _, _ = seeds_run
    learner = make_learner(TINY, env)
    initial = learner.init(keys[0], params)
    after, _ = jax.jit(learner.update)(initial, params)
    step = jax.tree.map(lambda a, b: np.abs(np.asarray(b) - np.asarray(a)), initial.params, after.params)
    every = np.concatenate([np.ravel(x) for x in jax.tree.leaves(step)])
    assert every.max() <= 1e-3 + 1e-6  # float32 rounding of the parameters is about 1e-7
    np.testing.assert_allclose(step["log_std"], 1e-3, rtol=1e-3)
    output_layer = step["actor"]["params"][sorted(step["actor"]["params"])[-1]]
    for leaf in jax.tree.leaves(output_layer):
        np.testing.assert_allclose(leaf, 1e-3, rtol=2e-2)


def test_rollout_log_probs_are_recomputed_exactly(seeds_run):
    """With one epoch of one minibatch the loss is evaluated at the rollout's parameters on the stored (normalised)
    observations: the ratio is 1 up to rounding, so nothing is clipped and the KL estimate is ~0. Normalising the
    stored observations with statistics other than the rollout's would break this."""
    _, (_, metrics), _ = seeds_run
    np.testing.assert_array_equal(metrics["clip_fraction"], 0.0)
    assert float(np.max(np.abs(metrics["approx_kl"]))) < 1e-9
    # The update did something nonetheless: the gradient is not zero.
    assert float(np.min(metrics["grad_norm"])) > 0.0


@pytest.fixture(scope="module")
def trained_dir(cartpole, tmp_path_factory, seeds_run):
    """``run_training`` of the tiny config with seed 0's key; the policy parameters it saves are captured."""
    return train_tiny_run(make_learner, TINY, cartpole, tmp_path_factory, seeds_run, "ppo_run")


def test_run_training_equals_make_train(seeds_run, trained_dir):
    """The host driver runs the same iterations as ``make_train`` (a fori_loop of ``update`` vs a scan)."""
    _, (state, _), _ = seeds_run
    _, _, policy_params, result = trained_dir
    assert result["iterations"] == 4 and result["env_steps"] == 512
    lane0 = jax.tree.map(lambda x: x[0], state)
    for a, b in zip(jax.tree.leaves(policy_params["actor"]), jax.tree.leaves(lane0.params["actor"]), strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(policy_params["obs_stats"].mean, lane0.obs_stats.mean, rtol=1e-5, atol=1e-6)


def test_saved_policy_acts_like_the_trained_one(cartpole, trained_dir):
    env, _ = cartpole
    _, learner, policy_params, _ = trained_dir
    _, loaded, actions = load_saved_policy(cartpole, trained_dir, "ppo", 512)
    np.testing.assert_array_equal(loaded, actions(learner.make_policy(policy_params)))
    # Not a trivial match: the actions vary with the observation, and the saved normaliser matters.
    assert float(jnp.std(loaded)) > 1e-4
    unnormalized = actions(learner.make_policy({**policy_params, "obs_stats": init_stats(env.observation_size)}))
    assert float(jnp.max(jnp.abs(unnormalized - loaded))) > 1e-5
