"""GP-MPC on the JAX SQP-RTI (``controllers.gp_mpc.solver: sqp_rti``): a zero GP gives the nonlinear SQP-RTI, the
margins are the CasADi GP-MPC's, batched equals one copy at a time, and a new GP of the same size compiles nothing."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import scg_jax
from scg_algorithms import gp
from scg_algorithms.base import Reference
from scg_algorithms.gp_mpc.controller import Options, gp_sqp_mpc_builder, make_gp_mpc
from scg_algorithms.mpc.nonlinear import make_nonlinear_mpc

H = 8
# Stabilization with the cart-position and angle rows of a state box and the +-10 N input row: state rows become
# general QP rows, the input row tightens the input box.
CONSTRAINTS = [
    {"type": "bounded", "on": "state", "active_dims": [0, 2], "low": [-1.0, -0.5], "high": [1.0, 0.5]},
    {"type": "default", "on": "input"},
]
OPTIONS = {"horizon": H, "soft_constraints": False}


@pytest.fixture(scope="module")
def setting():
    env = scg_jax.make("cartpole", ctrl_freq=10, physics_freq=500, episode_len_sec=2.0, constraints=CONSTRAINTS)
    params = env.default_params
    prior = scg_jax.prior_params(env, params, 1.5)
    reference = Reference(*env.reference(params))
    return env, params, prior, reference


def _posterior(scale: float, signal_var: float, seed: int = 0) -> gp.GPPosterior:
    """An exact GP on 12 random transitions of the cart-pole (targets ``scale`` times a smooth function)."""
    rng = np.random.default_rng(seed)
    z = rng.uniform([-0.5, -1, -0.3, -1, -5], [0.5, 1, 0.3, 1, 5], (12, 5))
    y = scale * np.stack([np.sin(z[:, 2]), z[:, 4] / 5, np.cos(z[:, 0]) - 1, z[:, 1] * z[:, 2]], axis=1)
    hyper = gp.hyperparams(np.ones((4, 5)), [signal_var] * 4, [1e-4] * 4)
    return gp.exact_posterior(z, y, hyper)


STATES = np.array([[0.2, 0.0, 0.1, 0.0], [-0.4, 0.3, -0.2, 0.5], [0.0, -0.5, 0.3, -0.2]])


@pytest.fixture(scope="module")
def gp_programs(setting):
    """``(first_input, batched)``: the GP-MPC's first step from one state, and vmapped over states, jitted with the
    (split) GP an argument, so every GP of the same size (the zero GP included) runs the same two executables."""
    env, _, prior, reference = setting
    build = gp_sqp_mpc_builder(env, prior, Options(**OPTIONS, solver="sqp_rti"))

    @jax.jit
    def first_input(posterior, x):
        """The first step's input from x, the GP an argument of the compiled function."""
        controller = build(posterior)
        u, state = controller.act(controller.reset(None, reference), x, 0, reference)
        return u, state.num_failures

    return first_input, jax.jit(jax.vmap(first_input.__wrapped__, in_axes=(None, 0)))


def test_a_zero_gp_gives_the_nonlinear_sqp_rti(setting, gp_programs):
    # Zero mean and a signal variance of 1e-16 (margins below 1e-5): the same first input as the nonlinear MPC's
    # SQP-RTI on the prior (with GP-MPC's ADMM cap), at three states (the SQP's first step iterates to convergence).
    # The GP-MPC runs through the module's compiled program (the GP an argument; ``make_gp_mpc`` builds the same
    # controller from it).
    env, _, prior, reference = setting
    zero = _posterior(0.0, 1e-16)
    gp_mpc = make_gp_mpc(env, prior, {**OPTIONS, "solver": "sqp_rti"}, zero)
    nmpc = make_nonlinear_mpc(
        env,
        prior,
        {
            **OPTIONS,
            "solver": "sqp_rti",
            "qp_max_iter": Options().qp_max_iter,
            "qp_polish_rounds": Options().qp_polish_rounds,
        },
    )
    margins = gp_mpc.info["plan_margins"](jnp.tile(jnp.asarray(STATES[0]), (H + 1, 1)), jnp.zeros((H, 1)))
    assert 0.0 < float(jnp.max(margins)) < 1e-5

    states = jnp.asarray(STATES, jnp.float32)
    u_gp = np.asarray(gp_programs[1](gp.split_posterior(zero), states)[0])
    act = jax.vmap(lambda x: nmpc.act(nmpc.reset(None, reference), x, 0, reference)[0])
    np.testing.assert_allclose(u_gp, np.asarray(jax.jit(act)(states)), atol=1e-4)


def test_margins_equal_the_casadi_gp_mpc_tightening(setting):
    # Float64 along a random plan: the JAX margins (Jacobians by jax.jacfwd, covariance by lax.scan) against the
    # CasADi GP-MPC's PlanUncertainty, every row at every stage (state rows and the input row).
    env, _, prior, _ = setting
    posterior = _posterior(0.05, 1e-3)
    casadi = make_gp_mpc(env, prior, OPTIONS, posterior)
    rng = np.random.default_rng(1)
    x_plan, u_plan = rng.uniform(-0.3, 0.3, (H + 1, 4)), rng.uniform(-3.0, 3.0, (H, 1))
    expected = casadi.uncertainty.plan_margins(x_plan, u_plan)
    with jax.enable_x64(True):
        jax_mpc = make_gp_mpc(env, prior, {**OPTIONS, "solver": "sqp_rti"}, posterior)
        margins = np.asarray(jax_mpc.info["plan_margins"](jnp.asarray(x_plan), jnp.asarray(u_plan)))
    assert expected.shape == (H, 6) and expected[-1].min() > 1e-3  # every row tightened by the end
    np.testing.assert_allclose(margins, expected, rtol=1e-7, atol=1e-10)


def test_batched_equals_one_at_a_time_and_a_new_gp_compiles_nothing(gp_programs):
    first_input, batched = gp_programs
    first, second = gp.split_posterior(_posterior(0.05, 1e-3)), gp.split_posterior(_posterior(0.08, 2e-3, seed=3))
    states = jnp.asarray(STATES, jnp.float32)
    u_batch, failures = batched(first, states)
    u_single = np.stack([np.asarray(first_input(first, x)[0]) for x in states])
    # Float32: batched and single-copy programs round differently, within the QP's tolerance (qp_tol 1e-5, scaled).
    np.testing.assert_allclose(np.asarray(u_batch), u_single, atol=5e-4)
    assert np.all(np.asarray(failures) == 0)
    u_other = np.asarray(batched(second, states)[0])  # another GP of the same size: the same executable
    assert batched._cache_size() == 1 and first_input._cache_size() == 1  # the zero GP's run too, if it came first
    assert np.max(np.abs(u_other - np.asarray(u_batch))) > 1e-2  # and it does change the inputs
