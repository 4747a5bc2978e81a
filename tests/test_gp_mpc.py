"""GP-MPC on the paper's settings, all with a 150% prior at 10 Hz: cart-pole stabilization (Q = diag(10, 1, 10, 1),
R = 0.1), the cart-pole constraint task, and the 2D quadrotor circle."""

from __future__ import annotations

from pathlib import Path

import jax
import numpy as np
import pytest

import scg_jax
from scg_algorithms import gp, make_controller
from scg_algorithms.evaluation import evaluate
from scg_algorithms.gp_mpc.controller import LearningResult, learn, make_gp_mpc
from scg_algorithms.gp_mpc.run import is_run, load_run, save_run, write_learning_curve

# The data-efficiency setting of the paper (Fig. 6): 10 Hz, 5 s episodes, x0 in +-0.3 m and +-0.1 rad.
PAPER = dict(
    ctrl_freq=10,
    physics_freq=1000,
    episode_len_sec=5,
    Q=[10, 1, 10, 1],
    R=[0.1],
    init_state={"type": "uniform", "low": [-0.3, -0.1, -0.1, -0.1], "high": [0.3, 0.1, 0.1, 0.1]},
)
SMALL = {"horizon": 15, "rounds": 1, "train_episodes": 4, "eval_episodes": 4, "gp_iterations": 30,
         "max_fit_points": 100, "num_inducing": 20}  # fmt: skip


@pytest.fixture(scope="module")
def paper_cartpole():
    env = scg_jax.make("cartpole", "stabilization", **PAPER)
    params = env.default_params
    return env, params, scg_jax.prior_params(env, params, 1.5)


@pytest.mark.slow
def test_gp_mpc_learns_the_150_percent_prior_mismatch_in_one_round(paper_cartpole):
    """After one round (4 episodes, 20 s of data) GP-MPC is within 1.2x of the true-model MPC and at least 30%
    better than the 150%-prior MPC, on the same 4 seeded episodes (paper: 0.818 -> 0.129). Measured on these 4:
    prior MPC 0.819, GP-MPC 0.129, true-model MPC 0.133 (ratios 6.2 > 2, 0.16 <= 0.7, 0.98 <= 1.2)."""
    env, params, prior = paper_cartpole
    result = learn(env, params, prior, SMALL)
    before, after = result.history[0], result.history[-1]
    assert after["data_seconds"] == pytest.approx(20.0)
    eval_key = jax.random.fold_in(jax.random.key(0), 10_000)  # learn's evaluation episodes (seed 0)
    true_mpc = make_controller("nonlinear_mpc", env, params, {"horizon": 15})
    true_rmse = evaluate(env, params, true_mpc, eval_key, SMALL["eval_episodes"], measure_time=False).summary["rmse"]
    print(f"RMSE: prior MPC {before['rmse']:.3f}, GP-MPC {after['rmse']:.3f}, true-model MPC {true_rmse:.3f}")
    assert before["rmse"] > 2.0 * true_rmse  # the 150% prior costs accuracy
    assert after["rmse"] <= 0.7 * before["rmse"]
    assert after["rmse"] <= 1.2 * true_rmse


def test_gp_mpc_without_a_gp_is_the_nonlinear_mpc(paper_cartpole):
    """No GP and no initial uncertainty: zero margins, the same NLP as nonlinear_mpc, the same first inputs."""
    env, params, prior = paper_cartpole
    options = {"horizon": 10, "soft_constraints": False}
    gp_mpc = make_gp_mpc(env, prior, options)
    nmpc = make_controller("nonlinear_mpc", env, prior, options)
    a = evaluate(env, params, gp_mpc, jax.random.key(3), 2, measure_time=False)
    b = evaluate(env, params, nmpc, jax.random.key(3), 2, measure_time=False)
    np.testing.assert_allclose(a.trajectory["u_cmd"][:20], b.trajectory["u_cmd"][:20], atol=1e-6)


def test_bad_options_are_named(paper_cartpole):
    env, params, prior = paper_cartpole
    with pytest.raises(ValueError, match=r"controllers.gp_mpc.prob: must be in \(0, 1\)"):
        make_gp_mpc(env, prior, {"prob": 1.5})
    with pytest.raises(ValueError, match=r"controllers.gp_mpc.kernel: unknown value 'matern'"):
        make_gp_mpc(env, prior, {"kernel": "matern"})
    with pytest.raises(ValueError, match=r"controllers.gp_mpc.inducing_points: unknown"):
        make_gp_mpc(env, prior, {"inducing_points": 10})
    with pytest.raises(ValueError, match=r"controllers.gp_mpc.qp_max_iter: must be"):
        make_gp_mpc(env, prior, {"qp_max_iter": 0, "solver": "sqp_rti"})


def test_a_saved_run_loads_to_the_same_controller(paper_cartpole, tmp_path):
    env, params, prior = paper_cartpole
    rng = np.random.default_rng(0)
    z = rng.uniform(-0.3, 0.3, (40, 5))
    e = 0.01 * np.tanh(z[:, :4] + z[:, 4:])
    posterior = gp.fitc_posterior(z, e, gp.hyperparams(np.ones((4, 5)), 1e-4 * np.ones(4), 1e-6 * np.ones(4)), z[:10])
    options = {"horizon": 8}
    controller = make_gp_mpc(env, prior, options, posterior)
    result = LearningResult(posterior, controller, [{"round": 0, "rmse": 1.0}], (z, e))
    save_run(tmp_path, result, options, system="cartpole", prior_scale=1.5)
    assert is_run(tmp_path) and not is_run(tmp_path / "missing")
    history = [{"round": 0, "transitions": 0, "data_seconds": 0.0, "rmse": 0.8, "rmse_std": 0.1},
               {"round": 1, "transitions": 200, "data_seconds": 20.0, "rmse": 0.2, "rmse_std": 0.05}]  # fmt: skip
    write_learning_curve(tmp_path, history)
    rows = (tmp_path / "learning_curve.csv").read_text().splitlines()
    assert rows[0].startswith("round,transitions,data_seconds,rmse") and rows[2].startswith("1,200,20.0,0.2,0.05")
    assert (tmp_path / "learning_curve.png").read_bytes()[:4] == b"\x89PNG"
    loaded = load_run(tmp_path, env, prior)
    a = evaluate(env, params, controller, jax.random.key(5), 1, measure_time=False)
    b = evaluate(env, params, loaded, jax.random.key(5), 1, measure_time=False)
    np.testing.assert_array_equal(a.trajectory["u_cmd"], b.trajectory["u_cmd"])
    quad = scg_jax.make("quadrotor_2d")
    with pytest.raises(ValueError, match=r"the GP was learned on the cartpole and cannot control the quadrotor_2d"):
        load_run(tmp_path, quad, quad.default_params)
    with pytest.raises(ValueError, match=r"controllers.gp_mpc.rounds: nothing was learned"):
        save_run(tmp_path, result._replace(posterior=None), options, system="cartpole", prior_scale=1.5)


# The paper's constraint task (Fig. 7 top): (theta, theta_dot) in [-0.2, 0.2]^2, GP-MPC at 10 Hz with prob 0.99,
# Q = diag(3, 1, 3, 1), R = 1, an initial-state std of 0.005; episodes run on past a violation.
CONSTRAINED = dict(
    PAPER,
    Q=[3, 1, 3, 1],
    R=[1.0],
    done_on_out_of_bounds=False,
    constraints=[
        {"type": "default", "on": "input"},
        {"type": "bounded", "on": "state", "active_dims": [2, 3], "low": [-0.2, -0.2], "high": [0.2, 0.2]},
    ],
)


@pytest.mark.slow
def test_gp_mpc_tightening_removes_the_prior_mpcs_constraint_violations():
    """On the same 6 seeded episodes, the 150%-prior MPC lets theta_dot leave +-0.2 rad/s; GP-MPC after one round
    (3 episodes of data, a 15-point GP) plans with positive margins and violates in fewer steps (here: none).
    ``benchmarks/gp_mpc.py`` runs the full-size comparison."""
    env = scg_jax.make("cartpole", "stabilization", **CONSTRAINED)
    params = env.default_params
    prior = scg_jax.prior_params(env, params, 1.5)
    options = {"horizon": 10, "prob": 0.99, "initial_std": 0.005, "rounds": 1, "train_episodes": 3,
               "eval_episodes": 6, "gp_iterations": 20, "max_fit_points": 100, "num_inducing": 15}  # fmt: skip
    result = learn(env, params, prior, options)
    prior_steps, gp_steps = (6 * entry["constraint_violation_steps"] for entry in result.history)
    print(f"violating steps in 6 episodes: prior MPC {prior_steps:.0f}, GP-MPC {gp_steps:.0f}")
    assert prior_steps >= 3  # the prior's MPC does violate (about 1.8 steps per 50-step episode)
    assert gp_steps < prior_steps
    # The tightening is what acts: along a plan from a tilted state the margins of the theta rows are positive.
    controller = result.controller
    x_plan = np.zeros((11, 4)) + np.array([0.1, 0.0, 0.1, 0.0])
    margins = controller.uncertainty.plan_margins(x_plan, np.zeros((10, 1)))
    assert margins.shape == (10, controller.ng_env) and np.all(margins >= 0) and margins[-1].max() > 1e-3


QUAD_CONFIG = "paper_quadrotor_2d_gp_mpc.yaml"


@pytest.mark.slow
def test_gp_mpc_on_the_paper_quadrotor_circle_improves_on_the_prior():
    """Smoke test of the 2D quadrotor path (configs/paper_quadrotor_2d_gp_mpc.yaml: the paper's 1 m circle at 10 Hz,
    8 GP inputs, 6 outputs): one round on a small GP lowers the x-z RMSE of the 150%-prior MPC on the same episodes.
    ``benchmarks/gp_mpc.py`` runs the full comparison with the true-model MPC."""
    from scg_jax.config import load_config, make_from_config

    env, params = make_from_config(load_config(Path(__file__).resolve().parents[1] / "configs" / QUAD_CONFIG))
    prior = scg_jax.prior_params(env, params, 1.5)
    # The prior's LQR at 10 Hz loses the quadrotor within a second: 2 exploring episodes give ~13 transitions, on
    # which a converged hyperparameter fit (50 iterations; 20 are too few for the 8 inputs) already helps.
    options = {"horizon": 15, "prob": 0.99, "rounds": 1, "train_episodes": 2, "eval_episodes": 2,
               "gp_iterations": 50, "num_inducing": 30}  # fmt: skip
    result = learn(env, params, prior, options)
    before, after = result.history
    print(f"x-z RMSE: prior MPC {before['rmse']:.3f}, GP-MPC after {after['data_seconds']:.1f} s {after['rmse']:.3f}")
    assert before["failure_rate"] == after["failure_rate"] == 0.0
    # One round on ~13 transitions of a crashing LQR gains little here (0.241 against 0.252); the benchmark's later
    # rounds reach the true model's RMSE.
    assert after["transitions"] > 0 and after["rmse"] < before["rmse"]
