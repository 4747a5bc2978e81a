"""The model-based controllers on the 3D quadrotor (the original suite's examples run LQR, iLQR and MPC there):
closed-loop stabilisation at hover from tilted, displaced starts, with numbers, and the CasADi linear MPC
against the JAX one."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import scg_jax
from scg_algorithms.base import Reference
from scg_algorithms.evaluation import evaluate
from scg_algorithms.ilqr import make_ilqr
from scg_algorithms.lqr import make_lqr
from scg_algorithms.mpc.linear import make_linear_mpc, make_linear_mpc_casadi
from scg_algorithms.mpc.nonlinear import make_nonlinear_mpc

EPISODES = 2
GOAL = np.array([0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0])
# 10 cm per position axis, 0.1 rad per angle, 2 cm/s and 0.02 rad/s on the rates.
SPREAD = np.array([0.1, 0.02, 0.1, 0.02, 0.1, 0.02, 0.1, 0.1, 0.1, 0.02, 0.02, 0.02])
POSITION = [0, 2, 4]


@pytest.fixture(scope="module")
def hover():
    """Hover at 1 m for 3 s (150 steps at 50 Hz) from starts within ``SPREAD`` of it, motor limits and state bounds
    imposed; and LQR's closed loop there, the baseline of the other controllers."""
    env = scg_jax.make(
        "quadrotor_3d",
        "stabilization",
        episode_len_sec=3.0,
        goal=GOAL.tolist(),
        Q=[1.0, 0.1, 1.0, 0.1, 1.0, 0.1, 0.1, 0.1, 0.1, 0.1, 0.1, 0.1],
        R=[0.1] * 4,
        init_state={"type": "uniform", "low": list(GOAL - SPREAD), "high": list(GOAL + SPREAD)},
        constraints=[{"type": "default", "on": "input"}, {"type": "default", "on": "state"}],
    )
    params = env.default_params
    lqr = evaluate(env, params, make_lqr(env, params), jax.random.key(0), EPISODES, measure_time=False)
    return env, params, lqr


def _final_position_error(evaluation) -> np.ndarray:
    x = np.asarray(evaluation.trajectory["x"], dtype=np.float64)
    return np.linalg.norm(x[-1][:, POSITION] - GOAL[POSITION], axis=-1)


def _initial_position_error(evaluation) -> np.ndarray:
    x = np.asarray(evaluation.trajectory["x"], dtype=np.float64)
    return np.linalg.norm(x[0][:, POSITION] - GOAL[POSITION], axis=-1)


def test_lqr_stabilises_the_3d_quadrotor_at_hover(hover):
    env, _, lqr = hover
    # From up to 17 cm away and 0.1 rad tilted, the LQR of the prior linearised about hover brings the vehicle
    # back: measured 0.5 mm from the goal after 3 s (tenths of a millimetre: the time constant of the slowest
    # mode, x and y through the tilt, is about 0.5 s), RMSE 0.057 (weighted error over the 150 steps).
    assert lqr.summary["failure_rate"] == 0.0 and lqr.summary["length"] == env.num_steps
    assert np.all(_initial_position_error(lqr) > 0.03)
    assert np.all(_final_position_error(lqr) < 5e-3)
    assert lqr.summary["rmse"] < 0.08


def test_linear_mpc_is_lqr_when_no_limit_is_active(hover):
    env, params, lqr = hover
    controller = make_linear_mpc(env, params, {"horizon": 20})
    mpc = evaluate(env, params, controller, jax.random.key(0), EPISODES, measure_time=False)
    # The Riccati terminal weight makes the unconstrained finite-horizon optimum the LQR law, and no motor reaches
    # its limit from these starts: the two closed loops coincide (measured: the same RMSE to 1e-4).
    assert mpc.summary["failure_rate"] == 0.0
    u = np.asarray(mpc.trajectory["u"])
    low, high = (np.asarray(b) for b in env.input_bounds(params.physics))
    assert np.all(u > low + 1e-4) and np.all(u < high - 1e-4)
    np.testing.assert_allclose(mpc.summary["rmse"], lqr.summary["rmse"], rtol=5e-3)
    assert np.all(_final_position_error(mpc) < 5e-3)


@pytest.mark.slow
def test_ilqr_stabilises_the_3d_quadrotor_at_a_lower_cost_than_lqr(hover):
    env, params, lqr = hover
    ilqr = evaluate(
        env, params, make_ilqr(env, params, {"horizon": 20}), jax.random.key(0), EPISODES, measure_time=False
    )
    # iLQR optimises the episode's own quadratic cost on the nonlinear prior (with LQR's cost-to-go at the end of
    # its horizon), so its return (minus the cost) is at least LQR's: measured -0.481 against -0.496 (4 episodes).
    assert ilqr.summary["failure_rate"] == 0.0
    assert ilqr.summary["return"] > lqr.summary["return"]
    assert np.all(_final_position_error(ilqr) < 5e-3)


def test_nonlinear_mpc_stabilises_the_3d_quadrotor_at_a_lower_cost_than_lqr(hover):
    env, params, lqr = hover
    mpc = evaluate(env, params, make_nonlinear_mpc(env, params, {"horizon": 10}), jax.random.key(0), EPISODES)
    # IPOPT on the nonlinear prior over 0.2 s with the Riccati terminal weight: every step solved, the vehicle
    # back within 5 mm, and a lower closed-loop cost than LQR (measured -0.33 against -0.50 on one episode).
    assert mpc.summary["failure_rate"] == 0.0 and mpc.summary["length"] == env.num_steps
    assert mpc.summary["return"] > lqr.summary["return"]
    assert np.all(_final_position_error(mpc) < 5e-3)


def test_casadi_linear_mpc_matches_the_jax_one_on_the_3d_quadrotor(hover):
    # The condensed CasADi problem (qpOASES, float64) against the JAX controller in float64, at tilted starts far
    # enough out that motors saturate in some plans (so the constraints matter).
    env, params, _ = hover
    reference = Reference(*(np.asarray(a, np.float64) for a in env.reference(params)))
    options = {"horizon": 10}
    casadi_mpc = make_linear_mpc_casadi(env, params, options)
    rng = np.random.default_rng(0)
    states = GOAL + rng.uniform(-3.0, 3.0, (4, env.nx)) * SPREAD
    saturated = 0
    with jax.enable_x64(True):
        jax_mpc = make_linear_mpc(env, params, options)
        act = jax.jit(jax_mpc.act)
        reference64 = Reference(*(jnp.asarray(a, jnp.float64) for a in reference))
        for x in states:
            u_jax, _ = act(jax_mpc.reset(None, reference64), jnp.asarray(x), 0, reference64)
            u_casadi, info = casadi_mpc.act({}, x, 0, reference)
            assert info["success"]
            np.testing.assert_allclose(np.asarray(u_jax), u_casadi, atol=1e-4)
            low, high = jax_mpc.info["u_low"], jax_mpc.info["u_high"]
            saturated += int(np.any(u_casadi <= low + 1e-7) or np.any(u_casadi >= high - 1e-7))
    assert saturated >= 1
