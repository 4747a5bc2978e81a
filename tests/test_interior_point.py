"""The interior-point horizon-QP solver (``scg_algorithms.mpc.interior_point``) against closed forms and qpOASES:
the LQR plan of an unconstrained LQ problem, the hand-solved KKT system with one active input bound, random
time-varying QPs with state and general rows, the Riccati step against a dense KKT solve, an infeasible problem's
status, determinism, batching and no retracing."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg

from scg_algorithms.mpc import interior_point as ipm
from scg_algorithms.mpc import structured as S
from tests.test_structured_qp import (
    DOUBLE_INTEGRATOR,
    _qp,
    _random_time_varying,
    assert_lqr_plan,
    random_qps_match_qpoases,
)

_solve = jax.jit(ipm.solve, static_argnums=(0, 3))


def test_an_unconstrained_lq_problem_gives_the_lqr_plan():
    # With the DARE solution as terminal weight the finite-horizon optimum is the LQR law at every stage; the input
    # box (1e3) is far away, so its multipliers vanish and the plan is the barrier-free one.
    A, B = DOUBLE_INTEGRATOR
    Q, R = np.diag([1.0, 0.1]), np.array([[0.01]])
    P = scipy.linalg.solve_discrete_are(A, B, Q, R)
    K = np.linalg.solve(R + B.T @ P @ B, B.T @ P @ A)
    layout = S.Layout(horizon=12, nx=2, nu=1)
    qp = _qp(layout, A, B, Q, R, P=P, u_box=1e3)
    x0 = np.array([1.0, -0.5])
    with jax.enable_x64(True):
        sol = jax.tree.map(np.asarray, _solve(layout, qp, jnp.asarray(x0), ipm.IPMSettings()))
    assert_lqr_plan(sol, x0, K, layout.horizon)
    np.testing.assert_allclose(sol.multipliers, 0.0, atol=1e-7)


def test_one_active_input_bound_matches_the_hand_solved_kkt_system():
    # The structured solver's worked example (tests/test_structured_qp.py): horizon 2 on the double integrator from
    # x0 = (1, 0) with |u| <= 1: v = (-1, -0.35600907), the lower bound's multiplier -0.00736729.
    A, B = DOUBLE_INTEGRATOR
    Q, R = np.diag([1.0, 0.1]), np.array([[0.01]])
    layout = S.Layout(horizon=2, nx=2, nu=1)
    qp = _qp(layout, A, B, Q, R, u_box=1.0)
    with jax.enable_x64(True):
        # Without refinement too (a float64 Riccati step is exact to round-off).
        for settings in (
            ipm.IPMSettings(polish_rounds=0, refinement_steps=0),
            ipm.IPMSettings(polish_rounds=0),
            ipm.IPMSettings(),
        ):
            sol = jax.tree.map(np.asarray, _solve(layout, qp, jnp.array([1.0, 0.0]), settings))
            assert int(sol.status) == S.CONVERGED
            np.testing.assert_allclose(sol.u[:, 0], [-1.0, -0.35600907], atol=1e-6)
            np.testing.assert_allclose(sol.multipliers[:, 0], [-0.00736729, 0.0], atol=1e-6)
    assert bool(sol.polished)  # with the polish: u_0 held at its bound exactly
    np.testing.assert_allclose(sol.u[:, 0], [-1.0, -0.35600907], atol=1e-12)


def test_the_riccati_step_solves_the_dense_kkt_system():
    # One Newton step's LQ problem (row weights W, linear terms g) against the dense KKT system of the same
    # problem in (x_1..x_N, u_0..u_N-1) with the dynamics as equations (float64, a general row: the cross term).
    rng = np.random.default_rng(5)
    layout, qp = _random_time_varying(rng, 5, 3, 2, 2)
    N, nx, nu = 5, 3, 2
    with jax.enable_x64(True):
        qp64 = S.HorizonQP(*(jnp.asarray(a) for a in qp))
        rows = ipm._make_rows(layout, qp64)
        w = jnp.asarray(rng.uniform(0.0, 3.0, rows.lo.shape))
        gx, gu = jnp.asarray(rng.normal(size=(N, nx))), jnp.asarray(rng.normal(size=(N, nu)))
        factor, _ = ipm._factorize(qp64, rows, w, 1.0)
        dx, du = (np.asarray(a) for a in ipm._step(qp64, factor, gx, gu))
        # Dense: z = (x_1..x_N, u_0..u_N-1); cost 1/2 z' H z + g' z with H from Q, R and the rows G' W G.
        G = np.zeros((N, rows.lo.shape[1], N * (nx + nu)))
        for k in range(N):
            xs, us = slice(k * nx, (k + 1) * nx), slice(N * nx + k * nu, N * nx + (k + 1) * nu)
            G[k, :nu, us] = np.diag(1.0 / np.asarray(rows.su[k]))
            G[k, nu, xs.start + 0] = 1.0 / float(rows.sx[k, 0])
            G[k, nu + 1 :, xs] = np.asarray(rows.C[k])
            G[k, nu + 1 :, us] = np.asarray(rows.D[k])
        H = scipy.linalg.block_diag(*qp.Q, *qp.R) + np.einsum("kri,kr,krj->ij", G, np.asarray(w), G)
        g = np.concatenate([np.asarray(gx).ravel(), np.asarray(gu).ravel()])
        E = np.zeros((N * nx, N * (nx + nu)))  # dx_{k+1} - A_k dx_k - B_k du_k = 0, dx_0 = 0
        for k in range(N):
            E[k * nx : (k + 1) * nx, k * nx : (k + 1) * nx] = np.eye(nx)
            if k:
                E[k * nx : (k + 1) * nx, (k - 1) * nx : k * nx] = -qp.A[k]
            E[k * nx : (k + 1) * nx, N * nx + k * nu : N * nx + (k + 1) * nu] = -qp.B[k]
        kkt = np.block([[H, E.T], [E, np.zeros((N * nx, N * nx))]])
        z = np.linalg.solve(kkt, np.concatenate([-g, np.zeros(N * nx)]))[: N * (nx + nu)]
    np.testing.assert_allclose(dx.ravel(), z[: N * nx], rtol=1e-9, atol=1e-10)
    np.testing.assert_allclose(du.ravel(), z[N * nx :], rtol=1e-9, atol=1e-10)


def test_random_time_varying_qps_with_state_and_general_rows_match_qpoases():
    # The structured solver's 16 random problems (every matrix changes along the horizon), float64, batched.
    random_qps_match_qpoases(ipm.solve)


def test_an_infeasible_problem_reports_its_status_and_a_finite_plan():
    # x_1 = x_0 + u with |u| <= 1 cannot reach x_1 <= 0 from x_0 = 5: the multiplier of the state row grows
    # without bound.
    layout = S.Layout(horizon=3, nx=1, nu=1, x_rows=(0,))
    qp = _qp(layout, np.eye(1), np.eye(1), np.eye(1), np.eye(1), u_box=1.0)
    qp = qp._replace(x_low=np.full((3, 1), -np.inf), x_high=np.zeros((3, 1)))
    sol = _solve(layout, qp, jnp.array([5.0], jnp.float32), ipm.IPMSettings())
    assert int(sol.status) == S.INFEASIBLE and not bool(sol.polished)
    for leaf in jax.tree.leaves(sol):
        assert np.all(np.isfinite(np.asarray(leaf)))
    assert float(sol.violation) >= 2.0 - 1e-3  # x_3 >= 2 at best


@pytest.fixture(scope="module")
def boxed():
    """A 2-state problem whose input bound binds from the starts below, jitted once (float32)."""
    A, B = DOUBLE_INTEGRATOR
    layout = S.Layout(horizon=15, nx=2, nu=1, x_rows=(1,))
    qp = _qp(layout, A, B, np.diag([1.0, 0.1]), np.array([[0.01]]), u_box=1.0)
    qp = qp._replace(x_low=np.full((15, 1), -0.6), x_high=np.full((15, 1), 0.6))
    traces = []

    def solve(x):
        traces.append(1)
        return ipm.solve(layout, qp, x)

    return layout, qp, jax.jit(jax.vmap(solve)), traces


def test_same_inputs_same_result_batched_equals_one_at_a_time_and_no_retracing(boxed):
    layout, qp, solve, traces = boxed
    x0s = jnp.asarray(np.random.default_rng(1).uniform([-1.0, -0.5], [1.0, 0.5], (6, 2)), jnp.float32)
    first, second = solve(x0s), solve(x0s + 0.0)
    for a, b in zip(jax.tree.leaves(first), jax.tree.leaves(second), strict=True):
        np.testing.assert_array_equal(a, b)
    assert len(traces) == 1
    for i in range(3):
        one = jax.jit(lambda x: ipm.solve(layout, qp, x))(x0s[i])
        # Not bit for bit: rounding differs between the batched and the single program, and where it puts a held
        # row's gap near the polish's tolerance the two accept different rounds (one repeated at a larger weight):
        # measured 1.8e-6 apart, each within 1.8e-6 of the float64 plan.
        np.testing.assert_allclose(one.u, first.u[i], atol=1e-5)
    assert np.all(np.abs(first.u) <= 1.0 + 1e-6) and np.any(np.isclose(np.abs(first.u), 1.0, atol=1e-5))
    assert np.all(np.asarray(first.status) == S.CONVERGED)


def test_bad_settings_and_soft_rows_name_the_field():
    with pytest.raises(ValueError, match=r"IPMSettings\.max_iterations: must be >= 1"):
        ipm.IPMSettings(max_iterations=0)
    with pytest.raises(ValueError, match=r"IPMSettings\.tol: must be positive"):
        ipm.IPMSettings(tol=0.0)
    with pytest.raises(ValueError, match=r"IPMSettings\.polish_rounds: must be >= 0"):
        ipm.IPMSettings(polish_rounds=-1)
    with pytest.raises(ValueError, match=r"IPMSettings\.refinement_steps: must be >= 0"):
        ipm.IPMSettings(refinement_steps=-1)
    layout = S.Layout(horizon=2, nx=1, nu=1, x_rows=(0,), soft_x=(True,), l1=1.0)
    with pytest.raises(ValueError, match=r"soft rows are not supported.*Layout\.soft_x"):
        ipm.check_layout(layout)
