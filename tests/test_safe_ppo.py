"""Safety-layer PPO: the closed-form projection on hand examples, the env's constraint rows, bad input, and a
tiny run whose saved policy acts through the pretrained layer exactly as trained."""

import csv

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from scg_algorithms import ppo
from scg_algorithms.rl.policy import load_policy
from scg_algorithms.rl.training import run_training
from scg_algorithms.safe_ppo import layer as layer_lib
from scg_algorithms.safe_ppo import make_learner, project_mean, state_constraint_rows
from scg_jax.config import load_config, make_from_config
from tests.rl_helpers import tiny_ppo

CONFIG = "configs/paper_cartpole_constraint_rl.yaml"
CHEAP = ["env.physics_freq=50", "env.integrator=euler"]  # one Euler substep a control step: quick to compile
TINY = {
    **tiny_ppo(total_env_steps=256, num_epochs=1, num_minibatches=2),
    "constraint_slack": [0.05, 0.07, 0.05, 0.07],
    "constraint_epochs": 30,
    "constraint_lr": 0.01,
    "constraint_steps_per_epoch": 512,
    "constraint_eval_steps": 512,
    "constraint_batch_size": 64,
}


@pytest.fixture(scope="module")
def constraint_env():
    return make_from_config(load_config(CONFIG, CHEAP))


def test_projection_moves_the_mean_onto_the_most_violated_row():
    # Row 0: g = 2, c = -0.5, slack 0.1: lambda_0 = (2 * 0.5 - 0.5 + 0.1) / 4 = 0.15.
    # Row 1: g = -1, c = -1.0, slack 0.1: (-0.5 - 1.0 + 0.1) / 1 < 0 -> lambda_1 = 0.
    # mu_safe = 0.5 - 0.15 * 2 = 0.2, and row 0 then holds with equality: -0.5 + 2 * 0.2 + 0.1 = 0.
    mean, g, c, slack = jnp.array([0.5]), jnp.array([[2.0], [-1.0]]), jnp.array([-0.5, -1.0]), jnp.array([0.1, 0.1])
    np.testing.assert_allclose(project_mean(mean, g, c, slack), [0.2], rtol=1e-6)


def test_projection_corrects_only_the_row_with_the_largest_multiplier():
    # d = 2. Row 0: g = (1, 0), c = 0.1 -> lambda_0 = (0.3 + 0.1) / 1 = 0.4.
    # Row 1: g = (0, 2), c = 0.2 -> lambda_1 = (2 * 0.4 + 0.2) / 4 = 0.25 (active, but smaller: left alone).
    # mu_safe = (0.3, 0.4) - 0.4 * (1, 0) = (-0.1, 0.4).
    mean = jnp.array([0.3, 0.4])
    g = jnp.array([[1.0, 0.0], [0.0, 2.0]])
    np.testing.assert_allclose(project_mean(mean, g, jnp.array([0.1, 0.2]), 0.0), [-0.1, 0.4], rtol=1e-6)


def test_projection_leaves_a_safe_mean_alone_and_batches():
    g = jnp.array([[1.0], [-1.0]])
    means = jnp.array([[0.2], [-0.3], [0.9]])  # predicted rows c + g a + slack: (-0.3, -0.7), (-0.8, -0.2), (0.4, -1.4)
    projected = project_mean(means, jnp.broadcast_to(g, (3, 2, 1)), jnp.array([-0.5, -0.5]), 0.0)
    np.testing.assert_allclose(projected, [[0.2], [-0.3], [0.5]], rtol=1e-6)


def test_state_constraint_rows_of_the_constraint_task(constraint_env):
    env, params = constraint_env
    A, b = state_constraint_rows(env, params)
    # bounded on (theta, theta_dot) in [-0.2, 0.2]^2: rows theta - 0.2, theta_dot - 0.2, -0.2 - theta, -0.2 - theta_dot
    expected_A = [[0, 0, 1, 0], [0, 0, 0, 1], [0, 0, -1, 0], [0, 0, 0, -1]]
    np.testing.assert_array_equal(A, expected_A)
    np.testing.assert_allclose(b, [0.2, 0.2, 0.2, 0.2])
    x = jnp.array([0.0, 0.0, 0.25, -0.1])
    np.testing.assert_allclose(layer_lib.constraint_values({"A": A, "b": b}, x), [0.05, -0.3, -0.45, -0.1], atol=1e-7)


def test_a_safety_layer_needs_state_constraints():
    env, params = make_from_config(load_config(CONFIG, [*CHEAP, "env.constraints=[{type: default, on: input}]"]))
    with pytest.raises(ValueError, match=r"env.constraints: the safety layer .* needs at least one state constraint"):
        make_learner(TINY, env)


def test_bad_safety_layer_options_are_named(constraint_env):
    env, _ = constraint_env
    with pytest.raises(ValueError, match=r"training.safe_ppo.constraint_slack: expected 1 value or 4"):
        make_learner({**TINY, "constraint_slack": [0.1, 0.1]}, env)
    with pytest.raises(ValueError, match=r"training.safe_ppo.constraint_slack: every slack must be >= 0"):
        make_learner({**TINY, "constraint_slack": [-0.1]}, env)
    with pytest.raises(ValueError, match=r"training.safe_ppo.constraint_lr"):
        make_learner({**TINY, "constraint_lr": 0.0}, env)


@pytest.fixture(scope="module")
def trained(constraint_env, tmp_path_factory):
    env, params = constraint_env
    learner = make_learner(TINY, env)
    out_dir = tmp_path_factory.mktemp("safe_ppo")
    captured = []

    def policy_params(runner_state):
        captured.append(learner.policy_params(runner_state))
        return captured[-1]

    result = run_training(
        learner._replace(policy_params=policy_params), env, params, jax.random.key(0), out_dir, progress=False
    )
    return out_dir, learner, captured[-1], result


def test_pretrained_models_explain_the_action_effect_on_held_out_data(trained):
    out_dir, _, _, _ = trained
    rows = list(csv.DictReader((out_dir / "progress.csv").open()))
    mse, baseline = float(rows[-1]["constraint_model_mse"]), float(rows[-1]["constraint_model_baseline_mse"])
    # Random actions move theta_dot by up to ~0.3 rad/s a step; the linear-in-action models must explain part of it.
    assert np.isfinite(mse) and mse < 0.8 * baseline
    assert float(rows[-1]["pretrain_env_steps"]) == 30 * 512 + 512


def test_saved_policy_acts_through_the_layer(trained, constraint_env):
    env, params = constraint_env
    out_dir, learner, policy_params, _ = trained
    controller = load_policy(out_dir, env, params)
    assert controller.name == "safe_ppo"
    obs = jax.random.uniform(jax.random.key(3), (32, env.observation_size), minval=-0.3, maxval=0.3)
    obs = obs.at[:, 2].set(jnp.linspace(-0.25, 0.25, 32))  # theta across both bounds: some rows active
    layer = policy_params["layer"]
    # The same actor without the layer: plain PPO's policy on the same parameters (its mean is far inside [-1, 1]
    # after a tiny run, so its clip is inactive and it returns the unprojected mean).
    ppo_options = {k: v for k, v in TINY.items() if not k.startswith("constraint_")}
    plain = ppo.make_learner(ppo_options, env).make_policy(
        {k: policy_params[k] for k in ("actor", "log_std", "obs_stats")}
    )
    mean = jax.vmap(lambda o: plain(o, None))(obs)
    assert float(jnp.max(jnp.abs(mean))) < 0.5
    _, apply = layer_lib.make_constraint_model(learner.config.constraint_hidden_dim, env.action_size)
    g, c = apply(layer["model"], obs), layer_lib.constraint_values(layer, obs)
    expected = jnp.clip(project_mean(mean, g, c, jnp.array(TINY["constraint_slack"])), -1.0, 1.0)
    policy = learner.make_policy(policy_params)
    actions = jax.vmap(lambda o: policy(o, None))(obs)
    np.testing.assert_allclose(actions, expected, rtol=1e-5, atol=1e-6)
    assert float(jnp.max(jnp.abs(actions - mean))) > 1e-3  # the layer did correct some of them
    # The controller returns the same actions as forces (10 N per unit action).
    forces = jax.vmap(lambda o: controller.act((), o, 0, None)[0])(obs)
    np.testing.assert_allclose(forces, 10.0 * actions, rtol=1e-5, atol=1e-5)
