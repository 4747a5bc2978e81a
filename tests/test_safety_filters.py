"""Safety filters: the CBF-QP's closed form (worked numbers), parity with CasADi/qpOASES, minimal intervention,
the 1D quadrotor ceiling (true, 150 % and learned models), the harness's intervention metrics, bad input."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import scg_jax
from scg_algorithms.evaluation import evaluate, make_evaluator
from scg_algorithms.safety_filters import FILTERS, filtered, make_filter
from scg_algorithms.safety_filters.base import INTERVENTION_THRESHOLD
from scg_algorithms.safety_filters.cbf import cbf_filter, is_valid_cbf, solve_single
from scg_algorithms.safety_filters.contract import floor_and_ceiling_env
from scg_algorithms.safety_filters.uncertified import random_input
from scg_jax.env import prior_params

CEILING = 1.5
TRUE_BRAKING = 0.9 * (9.8 - 4 * 0.02816 / 0.027)  # a_b of the true plant, m/s^2


def _ceiling_env():
    return scg_jax.make(
        "quadrotor_1d",
        init_state={"type": "uniform", "low": [0.1, -0.01], "high": [1.4, 0.01]},
        done_on_out_of_bounds=False,
        constraints=[{"type": "bounded", "on": "state", "active_dims": [0], "low": [-10.0], "high": [CEILING]}],
    )


def _cartpole_env():
    box = [2.0, 2.0, 0.2, 2.0]
    return scg_jax.make(
        "cartpole",
        constraints=[{"type": "bounded", "on": "state", "low": [-b for b in box], "high": box}],
    )


# --------------------------------------------------------------------------------------------- closed form
# Compiled once per input size for all the worked cases (the multipliers, box and price are traced).
_solve_single = jax.jit(solve_single)


@pytest.mark.parametrize(
    "u_l, a, c, box, inv_two_k, u_expected, s_expected, solved",
    [
        # already safe: unchanged, no slack
        ([1.0], [1.0], 0.5, 10.0, 5e-5, [1.0], 0.0, True),
        # interior: -4 + 2 (2 lam) + 5e-5 lam = 0, u = 2 lam, s = 5e-5 lam
        ([0.0], [2.0], -4.0, 10.0, 5e-5, [8.0 / 4.00005], 4.0 / 4.00005 * 5e-5, True),
        # saturated at 10: the slack takes the rest, -20 + 10 + s = 0
        ([0.0], [1.0], -20.0, 10.0, 5e-5, [10.0], 10.0, True),
        # two inputs, hard constraint: u2 saturates at lam = 5/3, then -18 + 15 + lam = 0, u = (3, 5)
        ([0.0, 0.0], [1.0, 3.0], -18.0, 5.0, 0.0, [3.0, 5.0], 0.0, True),
        # hard and infeasible: every input saturated and still -40 + 5 + 15 < 0; best corner, shortfall 20
        ([0.0, 0.0], [1.0, 3.0], -40.0, 5.0, 0.0, [5.0, 5.0], 20.0, False),
        # no input authority (Lg h = 0): the slack alone, s = 1
        ([2.0], [0.0], -1.0, 10.0, 5e-5, [2.0], 1.0, True),
    ],
)
def test_closed_form_worked_numbers(u_l, a, c, box, inv_two_k, u_expected, s_expected, solved):
    with jax.enable_x64(True):
        n = len(u_l)
        u, s, ok = _solve_single(
            jnp.asarray(u_l), jnp.asarray(a), jnp.asarray(c), -box * jnp.ones(n), box * jnp.ones(n), inv_two_k
        )
        np.testing.assert_allclose(np.asarray(u), u_expected, rtol=0, atol=1e-12)
        np.testing.assert_allclose(float(s), s_expected, rtol=1e-12, atol=1e-12)
        assert bool(ok) is solved


# --------------------------------------------------------------------------------------------- parity


# The ellipsoid is the original's candidate, not a CBF: built only when its infeasible states are accepted.
ELLIPSOID = {"barrier": "ellipsoid", "max_infeasible_fraction": 1.0}


@pytest.mark.parametrize("case", ["ellipsoid", "braking"])
def test_jax_filter_equals_casadi_qpoases_and_leaves_safe_inputs_bit_exact(case):
    with jax.enable_x64(True):
        if case == "ellipsoid":  # one barrier: the closed form
            env, options = _cartpole_env(), ELLIPSOID
            low, high = [-2.0, -2.0, -0.2, -2.0], [2.0, 2.0, 0.2, 2.0]
        else:  # floor and ceiling: two braking barriers, qpax
            env, options = floor_and_ceiling_env(), {"barrier": "braking"}
            low, high = [0.1, -3.0], [1.5, 3.0]
        params = env.default_params
        jax_filter = make_filter("cbf", env, params, options)
        casadi_filter = make_filter("cbf", env, params, {**options, "solver": "casadi"})
        assert jax_filter.info["solver"] == ("closed_form" if case == "ellipsoid" else "qpax")
        u_low, u_high = (np.asarray(b) for b in (jax_filter.params["u_low"], jax_filter.params["u_high"]))
        rng = np.random.default_rng(0)
        n = 300
        xs = rng.uniform(low, high, size=(n, env.nx))
        span = u_high - u_low
        us = rng.uniform(u_low - 0.1 * span, u_high + 0.1 * span, size=(n, env.nu))
        certify = jax.jit(jax.vmap(lambda x, u: jax_filter.certify(x, u, jax_filter.params, ())))
        u, _, info = certify(jnp.asarray(xs), jnp.asarray(us))
        u = np.asarray(u)
        reference = np.array([casadi_filter.certify(xs[i], us[i], casadi_filter.params, ())[0] for i in range(n)])
        np.testing.assert_allclose(u, reference, rtol=0, atol=1e-6)
        # Where the clipped input already satisfies the barrier condition, it comes back bit for bit.
        terms = jax.vmap(lambda x: jax_filter.terms_fn(x, jax_filter.params))(jnp.asarray(xs))
        u_l = np.clip(us, u_low, u_high)
        slope = float(jax_filter.params["slope"])
        margin = np.asarray(terms.Lf + slope * terms.h) + np.einsum("nmu,nu->nm", np.asarray(terms.Lg), u_l)
        safe = np.all(margin >= 0, axis=1)
        assert 0.1 < safe.mean() < 0.95
        assert np.array_equal(u[safe], u_l[safe])
        # The correction is the change of what the actuators apply: none where the clipped input is kept.
        correction = np.asarray(info.correction)
        assert np.all(correction[safe] == 0.0)
        np.testing.assert_allclose(correction, u - u_l, rtol=0, atol=1e-12)
        # An unsafe input is changed, unless it is already at the actuator limit the QP pushes it towards (then
        # the slack takes the rest and the applied input is unchanged).
        moved = np.abs(correction).max(axis=1) > 0
        at_limit = np.any((u_l == u_low) | (u_l == u_high), axis=1)
        assert np.all(moved[~safe] | at_limit[~safe]) and moved[~safe].mean() > 0.5


# --------------------------------------------------------------------------------------------- validity check
def test_is_valid_cbf_refuses_the_ellipsoid_candidate_and_passes_the_braking_barrier():
    env = _cartpole_env()
    accepted = make_filter("cbf", env, env.default_params, ELLIPSOID)
    report = is_valid_cbf(accepted, env, 4000, jax.random.key(0))
    assert report.num_inside > 500
    assert 0.02 < report.infeasible_fraction < 0.3  # the original's ellipsoid is a candidate, not a CBF
    assert np.all(report.worst_margins < 0)
    assert np.all(np.abs(report.worst_states) <= report.high + 1e-9)
    # Built with the default tolerance (1 %), the same check refuses it and says with which fraction.
    validity = accepted.info["validity"]
    assert validity["infeasible_fraction"] == pytest.approx(validity["infeasible"] / validity["inside"])
    percent = f"{100 * validity['infeasible_fraction']:.1f} %"
    with pytest.raises(ValueError, match=rf"safety_filters\.cbf\.barrier: .*ellipsoid: .*\({percent} > "):
        make_filter("cbf", env, env.default_params, {"barrier": "ellipsoid"})

    quad = _ceiling_env()
    ceiling = make_filter("cbf", quad, quad.default_params, {"barrier": "braking"})
    assert ceiling.info["validity"]["infeasible"] == 0
    valid = is_valid_cbf(ceiling, quad, 4000, jax.random.key(0), low=[-1.0, -5.0], high=[1.5, 5.0])
    assert valid.num_inside > 1000 and valid.num_infeasible == 0


# --------------------------------------------------------------------------------------------- closed loop
@pytest.fixture(scope="module")
def ceiling_setup():
    env = _ceiling_env()
    params = env.default_params
    return env, params, random_input(env, params)


def test_ceiling_unfiltered_true_and_wrong_prior(ceiling_setup):
    env, params, uncertified = ceiling_setup
    episodes = 256
    unfiltered = evaluate(env, params, uncertified, jax.random.key(1), episodes, measure_time=False)
    assert unfiltered.summary["constraint_violation_steps"] / env.num_steps >= 0.8
    assert "intervention_fraction" not in unfiltered.summary

    options = {"barrier": "braking", "slope": 0.5, "braking_deceleration": TRUE_BRAKING}
    true_filter = make_filter("cbf", env, params, options)
    wrong_filter = make_filter("cbf", env, prior_params(env, params, 1.5), options)
    # One compiled loop for both models: the filter's params are traced.
    run = make_evaluator(env, lambda p: filtered(uncertified, true_filter.replace(params=p), env), episodes)
    true_run = run(true_filter.params, jax.random.key(1), params)
    wrong_run = run(wrong_filter.params, jax.random.key(1), params)
    steps = episodes * env.num_steps
    true_violations = true_run.summary["constraint_violation_steps"] * episodes / steps
    assert true_violations <= 1e-4
    assert true_run.trajectory["x"][:, :, 0].max() <= CEILING + 0.01
    assert 0.2 < true_run.summary["intervention_fraction"] < 1.0
    assert true_run.summary["mean_correction"] > 0 and true_run.summary["infeasible_fraction"] == 0.0
    # The harness's metrics are the filter's own reports, averaged over the steps.
    correction = np.abs(true_run.trajectory["filter_correction"][..., 0])
    assert true_run.summary["intervention_fraction"] == pytest.approx(
        float(np.mean(correction > INTERVENTION_THRESHOLD))
    )
    assert true_run.summary["mean_correction"] == pytest.approx(float(np.mean(correction)), rel=1e-6)
    wrong_violations = wrong_run.summary["constraint_violation_steps"] * episodes / steps
    assert wrong_violations > 0.05 > true_violations


def test_learned_cbf_recovers_safety_on_a_wrong_prior(ceiling_setup):
    from scg_algorithms.safety_filters.learned_cbf import load_learned_cbf, save_run, train_learned_cbf

    env, params, _ = ceiling_setup
    options = {
        "barrier": "braking", "slope": 0.5, "braking_deceleration": TRUE_BRAKING, "num_episodes": 2,
        "num_copies": 16, "eval_episodes": 64, "hidden_sizes": [32, 32], "train_iterations": 150,
    }  # fmt: skip
    result = train_learned_cbf(env, params, prior_params(env, params, 1.5), options)
    history = result.history
    assert [row["episode"] for row in history] == [0, 1, 2]
    assert history[0]["violation_fraction"] > 0.05  # untrained: the prior CBF
    assert history[-1]["violation_fraction"] <= 1e-3
    assert history[-1]["heldout_rmse"] < history[1]["heldout_rmse"] / 5  # the correction explains the residual
    assert history[-1]["data_seconds"] == pytest.approx(history[-1]["data_steps"] * env.dt)
    # Saved and loaded, the filter certifies identically.
    import tempfile

    with tempfile.TemporaryDirectory() as folder:
        save_run(folder, result, system=env.system.name, prior_scale=1.5)
        loaded = load_learned_cbf(folder, env, params)
    obs = jnp.array([1.45, 0.8])
    u = jnp.array([0.5])
    a = result.filter.certify(obs, u, result.filter.params, ())[0]
    b = loaded.certify(obs, u, loaded.params, ())[0]
    np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


def test_host_path_records_the_casadi_filter(ceiling_setup):
    env, params, uncertified = ceiling_setup
    host = filtered(uncertified, make_filter("cbf", env, params, {"barrier": "braking", "solver": "casadi"}), env)
    assert not host.is_jax
    run = evaluate(env, params, host, jax.random.key(3), 1)
    correction = np.abs(run.trajectory["filter_correction"][..., 0])
    assert correction.shape == (env.num_steps, 1)
    assert run.summary["intervention_fraction"] == pytest.approx(float(np.mean(correction > INTERVENTION_THRESHOLD)))
    assert 0.2 < run.summary["intervention_fraction"] < 1.0
    assert run.trajectory["x"][:, :, 0].max() <= CEILING


# --------------------------------------------------------------------------------------------- bad input
def test_bad_input_errors():
    quad = _ceiling_env()
    cart = _cartpole_env()
    params = quad.default_params
    low, high = np.array([0.1126]), np.array([0.5934])

    def vector_barrier(x, p, xp=None):
        return x

    with pytest.raises(ValueError, match=r"barrier\[0\]: a barrier h\(x, barrier_params\) must return a scalar"):
        cbf_filter(quad.system, params.physics, low, high, [vector_barrier], {})

    def quadratic_thrust(x, u, physics, xp, f_ext=None):
        return xp.stack([x[1], u[0] * u[0] / physics.mass - physics.gravity])

    squared = dataclasses.replace(quad.system, dynamics=quadratic_thrust)
    with pytest.raises(ValueError, match="not control-affine"):
        cbf_filter(squared, params.physics, low, high, [lambda x, p: 1.0 - x[0]], {})

    cart_filter = make_filter("cbf", cart, cart.default_params)
    with pytest.raises(ValueError, match="built for the cartpole system, not for quadrotor_1d"):
        filtered(random_input(quad, params), cart_filter, quad)
    with pytest.raises(ValueError, match="built for the cartpole system"):
        evaluate(quad, params, filtered(random_input(quad, params), cart_filter), jax.random.key(0), 1)
    with pytest.raises(ValueError, match=r"safety_filters\.cbf\.barrier: .*row 0 bounds x: a braking barrier needs"):
        make_filter("cbf", cart, cart.default_params, {"barrier": "braking"})
    with pytest.raises(ValueError, match=r"safety_filters\.cbf\.slop: unknown key"):
        make_filter("cbf", cart, cart.default_params, {"slop": 1.0})
    floor = floor_and_ceiling_env()
    with pytest.raises(ValueError, match=r"safety_filters\.cbf\.solver: closed_form solves one barrier"):
        make_filter("cbf", floor, floor.default_params, {"barrier": "braking", "solver": "closed_form"})
    with pytest.raises(ValueError, match=r"safety_filters\.cbf\.solver: the casadi filter has no backup controller"):
        make_filter("cbf", cart, cart.default_params, {"barrier": "backup", "solver": "casadi"})
    with pytest.raises(ValueError, match="unknown name 'mpc'; allowed values are cbf, learned_cbf"):
        make_filter("mpc", cart, cart.default_params)
    assert {"cbf", "learned_cbf"} <= set(FILTERS)


def test_cli_eval_with_a_filter_and_bad_filter(tmp_path):
    """The PID drives to a goal above the 1.5 m ceiling: the CBF keeps every episode below it by correcting nearly
    every step (without the filter most steps violate it), and its per-step intervention metric is what the saved
    trajectories show."""
    import json

    from scg_cli import main

    config = "configs/quadrotor_1d_ceiling.yaml"
    out = tmp_path / "eval.json"
    args = ["eval", "--config", config, "--controller", "pid", "--filter", "cbf", "--episodes", "4", "--out", str(out)]
    assert main(args) == 0
    record = json.loads(out.read_text())
    assert record["controller"] == "pid+cbf" and record["filter"] == "cbf"
    assert record["failure_rate"] == 0.0 and record["per_episode"]["violation_steps"] == [0, 0, 0, 0]
    assert record["infeasible_fraction"] == 0.0 and 0.9 < record["intervention_fraction"] <= 1.0
    with np.load(out.with_suffix(".npz")) as data:
        assert data["x"][..., 0].max() <= 1.5 + 1e-6  # altitude (m) under the ceiling at every step
        correction = np.linalg.norm(data["filter_correction"], axis=-1)  # (T, episodes), N
    assert record["intervention_fraction"] == pytest.approx(np.mean(correction > INTERVENTION_THRESHOLD))
    assert record["mean_correction"] == pytest.approx(np.mean(correction), rel=1e-5) and record["mean_correction"] > 0
    unfiltered = tmp_path / "pid.json"
    assert main([*args[:5], "--episodes", "4", "--out", str(unfiltered)]) == 0
    assert json.loads(unfiltered.read_text())["failure_rate"] == 1.0  # the same PID alone crosses the ceiling
    assert main(["eval", "--config", config, "--controller", "pid", "--filter", "nope", "--out", str(out)]) == 2
