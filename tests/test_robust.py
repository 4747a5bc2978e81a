"""RARL and RAP (scg_algorithms.robust): the adversary's reward sign, the per-copy adversary assignment, the
alternating schedule, RARL as RAP with one adversary, bad input, and a tiny training run of each learner through
run_training. (The adversaries' weighted PPO loss is tested with PPO's losses, tests/test_ppo.py.)"""

import csv
import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import scg_jax
from scg_algorithms.evaluation import evaluate
from scg_algorithms.ppo import losses
from scg_algorithms.rl.checkpoint import load_checkpoint
from scg_algorithms.rl.policy import load_policy
from scg_algorithms.rl.training import run_training
from scg_algorithms.robust import adversarial, rap, rarl

# Cheap plant for the learning tests: one physics substep per control step, 0.4 s episodes (20 steps).
ENV_OPTIONS = dict(physics_freq=50, integrator="euler", episode_len_sec=0.4, reward_type="exponential")
TINY = dict(
    num_envs=32,
    rollout_length=10,
    num_epochs=2,
    num_minibatches=2,
    actor_hidden=[16],
    critic_hidden=[16],
    adversary_hidden=[16],
)


# --------------------------------------------------------------------------------------------- worked numbers
def test_adversary_reward_is_minus_the_protagonists_and_so_are_its_advantages():
    # Two steps, the second truncated, gamma = 0.5, lambda = 1, zero values: A_1 = r_1 = 0.5, A_0 = r_0 + 0.5 A_1.
    reward = jnp.array([1.0, 0.5])
    zeros = jnp.zeros(2)
    no, end = jnp.array([False, False]), jnp.array([False, True])
    gae = jax.jit(lambda r: losses.gae(r, zeros, zeros, no, end, 0.5, 1.0))
    adv_p, ret_p = gae(reward)
    adv_a, ret_a = gae(adversarial.adversary_rewards(reward))
    np.testing.assert_allclose(adversarial.adversary_rewards(reward), [-1.0, -0.5])
    np.testing.assert_allclose(adv_p, [1.25, 0.5])
    np.testing.assert_allclose(adv_a, [-1.25, -0.5])
    np.testing.assert_allclose(ret_a, -np.asarray(ret_p))


def test_alternating_schedule_cycles_protagonist_then_adversary_iterations():
    config = rarl.Config(protagonist_iterations=2, adversary_iterations=3)
    flags = [tuple(bool(f) for f in adversarial.update_flags(jnp.int32(i), config)) for i in range(10)]
    protagonist = [p for p, _ in flags]
    assert protagonist == [True, True, False, False, False, True, True, False, False, False]
    assert all(p != a for p, a in flags)
    joint = rap.Config()
    assert all(bool(f) for f in adversarial.update_flags(jnp.int32(7), joint))
    assert adversarial.update_counts(rarl.Config(total_env_steps=16384 * 10, protagonist_iterations=2,
                                                 adversary_iterations=3)) == (4, 6)  # fmt: skip


def test_rarl_is_rap_with_one_adversary_and_the_alternating_schedule():
    """One option declaration: RARL's options are RAP's with other defaults, and parse to the same values."""
    env = scg_jax.make("cartpole", adversary={"channel": "action"})
    options = {"num_envs": 8, "rollout_length": 16, "total_env_steps": 128, "adversary_hidden": [8]}
    rarl_config = rarl.make_learner(options, env).config
    rap_config = rap.make_learner({**options, "num_adversaries": 1, "schedule": "alternating"}, env).config
    assert dataclasses.asdict(rarl_config) == dataclasses.asdict(rap_config)
    assert (rarl.Config().num_adversaries, rarl.Config().schedule) == (1, "alternating")
    assert (rap.Config().num_adversaries, rap.Config().schedule) == (2, "joint")
    assert rarl_config.adversary_hidden == (8,) and isinstance(rarl_config.adversary_hidden[0], int)


def test_assign_adversaries_redraws_only_where_an_episode_ended():
    index = jnp.array([0, 1, 2, 0, 1], jnp.int32)
    done = jnp.array([False, True, False, True, False])
    assign = jax.jit(jax.vmap(adversarial.assign_adversaries, in_axes=(0, None, None, None)), static_argnums=3)
    draws = np.asarray(assign(jax.random.split(jax.random.key(0), 60), index, done, 3))
    np.testing.assert_array_equal(draws[:, ~np.asarray(done)], np.broadcast_to([0, 2, 1], (60, 3)))
    assert set(draws[:, 1]) == {0, 1, 2} and set(draws[:, 3]) == {0, 1, 2}


# --------------------------------------------------------------------------------------------- per-copy assignment
def test_each_copy_is_driven_by_its_own_adversary_for_a_whole_episode():
    """Three adversaries that push the cart with known constant forces (+0.3, -0.6, +0.9 of the 2 N scale); the
    protagonist's action is fixed at 0. The applied force of each copy at each step then names the adversary that
    drives it: it must be constant within an episode and may change only at an episode start."""
    scale = 2.0
    env = scg_jax.make("cartpole", **ENV_OPTIONS, adversary={"channel": "action", "scale": scale})
    params = env.default_params
    config = rap.Config(total_env_steps=32 * 50, num_adversaries=3, **{**TINY, "rollout_length": 50})
    game = adversarial.make_game(config, env, "rap")
    runner = jax.jit(lambda key: adversarial.init(game, key, params))(jax.random.key(0))
    pushes = jnp.array([0.3, -0.6, 0.9])
    adversaries = runner.adversaries.params
    # Zero last-layer weights and these biases: each adversary's mean is its constant; a tiny std makes it exact.
    last = sorted(adversaries["actor"]["params"])[-1]
    layer = adversaries["actor"]["params"][last]
    layer = {"kernel": jnp.zeros_like(layer["kernel"]), "bias": pushes[:, None]}
    adversaries = {
        **adversaries,
        "actor": {"params": {**adversaries["actor"]["params"], last: layer}},
        "log_std": jnp.full_like(adversaries["log_std"], -30.0),
    }
    protagonist = {**runner.protagonist.params, "log_std": jnp.full_like(runner.protagonist.params["log_std"], -30.0)}
    last_p = sorted(protagonist["actor"]["params"])[-1]
    zero_p = jax.tree.map(jnp.zeros_like, protagonist["actor"]["params"][last_p])
    protagonist["actor"] = {"params": {**protagonist["actor"]["params"], last_p: zero_p}}
    runner = runner._replace(
        protagonist=runner.protagonist._replace(params=protagonist),
        adversaries=runner.adversaries._replace(params=adversaries),
    )
    _, traj, _, final_index = jax.jit(lambda r, k: adversarial.rollout(game, r, params, k, info_keys=("u",)))(
        runner, jax.random.key(1)
    )
    # 50 steps of 20-step episodes: every copy hands over to a fresh draw at least twice.
    acting = np.asarray(traj.extras["label"])  # (T, N)
    u = np.asarray(traj.info["u"])[..., 0]  # (T, N) applied force, N
    np.testing.assert_allclose(u, scale * np.asarray(pushes)[acting], atol=1e-5)
    np.testing.assert_array_equal(acting[0], np.asarray(runner.adversary_index))
    done = np.asarray(traj.terminated | traj.truncated)
    changed = acting[1:] != acting[:-1]
    assert not np.any(changed & ~done[:-1])  # a copy's adversary changes only after its episode ended
    assert np.any(changed)  # and does change at some episode starts (a third of the draws keep it)
    # The hand-over: where the last step ended an episode a fresh draw, elsewhere the same adversary.
    np.testing.assert_array_equal(np.asarray(final_index)[~done[-1]], acting[-1][~done[-1]])
    assert set(np.unique(acting)) == {0, 1, 2}


# --------------------------------------------------------------------------------------------- bad input
def test_adversary_on_an_unsupported_env_or_channel_is_refused():
    with pytest.raises(ValueError, match=r"env\.adversary: rarl .* made without one"):
        rarl.make_learner({}, scg_jax.make("cartpole"))
    obs_env = scg_jax.make("quadrotor_2d", adversary={"channel": "observation", "scale": 0.1})
    with pytest.raises(ValueError, match=r"env\.adversary\.channel: .* allowed values are action, dynamics"):
        rap.make_learner({}, obs_env)
    env = scg_jax.make("cartpole", adversary={"channel": "action"})
    with pytest.raises(ValueError, match=r"training\.rarl\.schedule"):
        rarl.make_learner({"schedule": "sometimes"}, env)
    with pytest.raises(ValueError, match=r"training\.rap\.num_adversaries: must be positive"):
        rap.make_learner({"num_adversaries": 0}, env)
    with pytest.raises(ValueError, match=r"training\.rarl\.protagonist_iterations"):
        rarl.make_learner({"protagonist_iterations": 0, "adversary_iterations": 0}, env)


# --------------------------------------------------------------------------------------------- learning
def _returns(path):
    with open(path, newline="") as file:
        rows = list(csv.DictReader(file))
    return rows, np.array([float(r["episode_return"]) for r in rows])


def test_rarl_adversary_alone_learns_to_lower_the_return_and_the_protagonist_loads_as_a_controller(tmp_path):
    """adversary_iterations only (the protagonist frozen): the adversary ascends -r, so the protagonist's return
    falls; the frozen protagonist is saved and evaluated by the harness on an env without an adversary input."""
    env = scg_jax.make("cartpole", **ENV_OPTIONS, adversary={"channel": "action", "scale": 5.0})
    params = env.default_params
    config = dict(TINY, total_env_steps=32 * 10 * 40, protagonist_iterations=0, adversary_iterations=1,
                  adversary_learning_rate=0.01)  # fmt: skip
    learner = rarl.make_learner(config, env)
    key = jax.random.key(0)
    start = jax.jit(learner.init)(key, params)
    run_training(learner, env, params, key, tmp_path, progress=False, chunk=40)
    rows, returns = _returns(tmp_path / "progress.csv")
    assert {"episode_cost", "violation_fraction", "adversary_policy_loss"} <= set(rows[0])
    assert all(float(r["protagonist_updated"]) == 0 for r in rows)
    assert returns[-5:].mean() < returns[1:6].mean() - 0.5, returns  # a worse episode for the protagonist
    saved, _ = load_checkpoint(tmp_path, "policy", jax.eval_shape(lambda: learner.policy_params(start)))
    jax.tree.map(np.testing.assert_array_equal, saved["actor"], start.protagonist.params["actor"])  # frozen
    plain = scg_jax.make("cartpole", **ENV_OPTIONS)
    policy = load_policy(tmp_path, plain, plain.default_params)
    assert policy.name == "rarl"
    obs = jnp.array([0.1, 0.0, 0.05, 0.0])
    u, _ = policy.act((), obs, 0, None)
    np.testing.assert_allclose(u, 10.0 * learner.make_policy(saved)(obs), rtol=1e-6)  # F = force_max a
    assert evaluate(plain, plain.default_params, policy, jax.random.key(2), 4, measure_time=False).summary["length"] > 0


def test_rap_protagonist_learns_against_a_population(tmp_path):
    env = scg_jax.make("cartpole", **ENV_OPTIONS, adversary={"channel": "action", "scale": 0.5})
    params = env.default_params
    # A wide initial policy (std = the whole force range): the return is low from the input penalty until the
    # protagonist learns a narrower, stabilising policy.
    config = dict(TINY, total_env_steps=32 * 10 * 150, num_adversaries=2, learning_rate=0.01, lr_decay=False,
                  init_log_std=0.0)  # fmt: skip
    learner = rap.make_learner(config, env)
    run_training(learner, env, params, jax.random.key(1), tmp_path, progress=False, chunk=150)
    rows, returns = _returns(tmp_path / "progress.csv")
    assert all(float(r["protagonist_updated"]) == 1 and float(r["adversaries_updated"]) == 1 for r in rows)
    assert returns[-10:].mean() > returns[1:11].mean() + 1.0, returns
    assert float(rows[-1]["policy_std"]) < 0.7 < float(rows[0]["policy_std"])
