"""iLQR: exact on linear-quadratic problems (finite-horizon Riccati, box-constrained QP), the receding-horizon
controller against LQR, batch consistency and determinism, and its option errors."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.optimize

import scg_jax
from scg_algorithms.evaluation import evaluate
from scg_algorithms.ilqr import ILQRSettings, ilqr_solve, make_ilqr, model_step_fn
from scg_algorithms.lqr import discrete_lqr_gain, make_lqr


def _riccati(A, B, Q, R, Q_terminal, horizon):
    """Finite-horizon discrete Riccati recursion (float64): gains K_k (u = -K_k x) and cost-to-go P_0."""
    P = Q_terminal
    gains = []
    for _ in range(horizon):
        K = np.linalg.solve(R + B.T @ P @ B, B.T @ P @ A)
        P = Q + A.T @ P @ (A - B @ K)
        gains.append(K)
    return np.array(gains[::-1]), P


def _lqr_plan(A, B, gains, dx0):
    xs, us = [dx0], []
    for K in gains:
        us.append(-K @ xs[-1])
        xs.append(A @ xs[-1] + B @ us[-1])
    return np.array(xs), np.array(us)


# ------------------------------------------------------------------------------------------------ exactness
def test_first_iteration_on_the_1d_quadrotor_is_the_finite_horizon_riccati_solution():
    with jax.enable_x64(True):
        env = scg_jax.make("quadrotor_1d")
        params = env.default_params
        step = model_step_fn(env, params)  # one RK4 step over dt
        m, g, dt = float(params.physics.mass), float(params.physics.gravity), env.dt
        # z_dd = T / m - g is a double integrator with a constant input over the step, whose solution is a
        # quadratic in time: RK4 integrates it exactly, so the model is affine with the exact discretisation.
        A = np.array([[1.0, dt], [0.0, 1.0]])
        B = np.array([[dt**2 / (2 * m)], [dt / m]])
        x, u = np.array([0.7, -0.4]), np.array([0.31])
        np.testing.assert_allclose(step(x, u), A @ x + B @ u - np.array([g * dt**2 / 2, g * dt]), rtol=1e-12)

        horizon = 30
        goal, u_eq = np.array([1.0, 0.0]), np.array([m * g])
        Q, R = np.asarray(params.Q), np.asarray(params.R)
        # A terminal weight far from the DARE solution, so the gains change along the horizon.
        Q_terminal = np.diag([20.0, 5.0])
        gains, P0 = _riccati(A, B, Q, R, Q_terminal, horizon)
        assert np.max(np.abs(gains[0] - gains[-1])) > 0.1 * np.max(np.abs(gains[-1]))
        x0 = np.array([0.6, 0.3])
        dx, du = _lqr_plan(A, B, gains, x0 - goal)

        sol = ilqr_solve(
            step,
            x0,
            np.tile(u_eq, (horizon, 1)),  # hovering: far from the optimum
            np.tile(goal, (horizon + 1, 1)),
            np.tile(u_eq, (horizon, 1)),
            Q,
            R,
            Q_terminal,
            -np.inf,
            np.inf,
        )
        # One Newton step (mu starts at 0) reaches the optimum; the second backward pass predicts no decrease.
        assert int(sol.iterations) == 1 and bool(sol.converged)
        assert float(sol.cost_history[0]) > 1.5 * float(sol.cost)
        np.testing.assert_allclose(sol.u, u_eq + du, atol=1e-10)
        np.testing.assert_allclose(sol.x, goal + dx, atol=1e-10)
        np.testing.assert_allclose(sol.K, gains, rtol=1e-9)
        np.testing.assert_allclose(sol.d, 0.0, atol=1e-10)
        np.testing.assert_allclose(sol.cost, 0.5 * (x0 - goal) @ P0 @ (x0 - goal), rtol=1e-10)


# A two-input linear system (two coupled double integrators, dt = 0.1) for the multi-input box-QP branch.
DT = 0.1
A2 = np.array([[1, DT, 0, 0], [0, 1, 0.02, 0], [0, 0, 1, DT], [0.02, 0, 0, 1.0]])
B2 = np.array([[0, 0], [DT, 0.3 * DT], [0, 0], [-0.2 * DT, DT]])
Q2, R2, QT2 = np.diag([1.0, 0.1, 1.0, 0.1]), 0.01 * np.eye(2), 5.0 * np.eye(4)
H2 = 20
X0_2 = np.array([1.0, 0.0, -0.5, 0.2])


@pytest.fixture(scope="module")
def linear_solve():
    """``ilqr_solve`` on the linear system, jitted once with the limits as arguments (call it under x64)."""
    settings = ILQRSettings(max_iterations=50, tolerance=1e-12)

    def solve(low, high):
        zeros_u = jnp.zeros((H2, 2))
        return ilqr_solve(
            lambda x, u: A2 @ x + B2 @ u,
            X0_2,
            zeros_u,
            jnp.zeros((H2 + 1, 4)),
            zeros_u,
            Q2,
            R2,
            QT2,
            low,
            high,
            settings,
        )

    return jax.jit(solve)


def test_two_inputs_without_limits_match_the_riccati_solution(linear_solve):
    with jax.enable_x64(True):
        sol = linear_solve(jnp.full(2, -jnp.inf), jnp.full(2, jnp.inf))
        gains, P0 = _riccati(A2, B2, Q2, R2, QT2, H2)
        dx, du = _lqr_plan(A2, B2, gains, X0_2)
        assert int(sol.iterations) == 1 and bool(sol.converged)
        np.testing.assert_allclose(sol.u, du, atol=1e-10)
        np.testing.assert_allclose(sol.x, dx, atol=1e-10)
        np.testing.assert_allclose(sol.K, gains, rtol=1e-8, atol=1e-10)
        np.testing.assert_allclose(sol.cost, 0.5 * X0_2 @ P0 @ X0_2, rtol=1e-10)


def test_box_constrained_solution_is_the_qp_optimum(linear_solve):
    low, high = np.array([-1.0, -0.5]), np.array([1.0, 0.5])
    with jax.enable_x64(True):
        sol = linear_solve(jnp.asarray(low), jnp.asarray(high))
    U = np.asarray(sol.u)
    assert bool(sol.converged) and np.all(U >= low) and np.all(U <= high)
    # Condensed QP in the stacked inputs: x_k = A^k x0 + S_k U, cost 1/2 U^T H U + h^T U + const.
    nu = 2
    powers = [np.linalg.matrix_power(A2, k) for k in range(H2 + 1)]
    S = np.zeros((H2 + 1, 4, H2 * nu))
    for k in range(1, H2 + 1):
        S[k] = A2 @ S[k - 1]
        S[k][:, (k - 1) * nu : k * nu] = B2
    weights = [Q2] * H2 + [QT2]
    Hess = sum(S[k].T @ weights[k] @ S[k] for k in range(H2 + 1)) + np.kron(np.eye(H2), R2)
    h = sum(S[k].T @ weights[k] @ powers[k] @ X0_2 for k in range(H2 + 1))
    const = 0.5 * sum(X0_2 @ powers[k].T @ weights[k] @ powers[k] @ X0_2 for k in range(H2 + 1))
    flat = U.reshape(-1)
    np.testing.assert_allclose(0.5 * flat @ Hess @ flat + h @ flat + const, sol.cost, rtol=1e-12)
    # KKT of the strictly convex QP, which certify the unique optimum: zero gradient on the free inputs, a
    # gradient pushing outward on those at a limit.
    gradient = Hess @ flat + h
    at_low = flat <= np.tile(low, H2) + 1e-9
    at_high = flat >= np.tile(high, H2) - 1e-9
    free = ~(at_low | at_high)
    assert np.sum(~free) >= 5  # the limits matter
    assert np.max(np.abs(gradient[free])) < 1e-7
    assert np.all(gradient[at_low] > -1e-7) and np.all(gradient[at_high] < 1e-7)
    # And a general-purpose bounded solver agrees on the optimal cost.
    bounds = list(zip(np.tile(low, H2), np.tile(high, H2), strict=True))
    reference = scipy.optimize.minimize(
        lambda v: (0.5 * v @ Hess @ v + h @ v, Hess @ v + h),
        np.zeros(H2 * nu),
        jac=True,
        method="L-BFGS-B",
        bounds=bounds,
        options={"ftol": 1e-15, "gtol": 1e-12, "maxiter": 10000},
    )
    np.testing.assert_allclose(float(sol.cost), reference.fun + const, rtol=1e-9)


# ------------------------------------------------------------------------------------------------ controller
def test_receding_horizon_ilqr_reproduces_lqr_on_a_linear_model():
    # 1D quadrotor near the goal: the model is linear and exact (see above) and no limit is reached. With the DARE
    # solution as terminal weight the finite-horizon Riccati gains all equal the infinite-horizon LQR gain, so each
    # solve's first input is LQR's. The open-loop warm start makes the first solve start from hovering.
    env = scg_jax.make(
        "quadrotor_1d", episode_len_sec=2.0, init_state={"type": "uniform", "low": [0.96, -0.05], "high": [1.04, 0.05]}
    )
    params = env.default_params
    key = jax.random.key(0)
    lqr = evaluate(env, params, make_lqr(env, params), key, 4, measure_time=False).trajectory
    ilqr = evaluate(env, params, make_ilqr(env, params, {"warm_start": "open_loop"}), key, 4, measure_time=False)
    low, high = (float(b[0]) for b in env.input_bounds(params.physics))
    assert low < lqr["u_cmd"].min() and lqr["u_cmd"].max() < high
    assert np.ptp(lqr["u_cmd"]) > 0.05  # N: the inputs do move
    # float32: the solver stops once a step promises less than sqrt(eps) of the cost (see ilqr_solve).
    np.testing.assert_allclose(ilqr.trajectory["u_cmd"], lqr["u_cmd"], atol=2e-5)
    np.testing.assert_allclose(ilqr.trajectory["x"], lqr["x"], atol=1e-5)


@pytest.fixture(scope="module")
def quadrotor_2d_far():
    # Starts up to 1 m, 0.5 m/s, 0.5 rad and 0.5 rad/s away from hover: sin(theta) and the thrust limits matter.
    env = scg_jax.make(
        "quadrotor_2d",
        episode_len_sec=2.0,
        init_state={"type": "uniform", "low": [-1, -0.5, 0.5, -0.5, -0.5, -0.5], "high": [1, 0.5, 1.5, 0.5, 0.5, 0.5]},
    )
    return env, env.default_params


def test_ilqr_lowers_the_closed_loop_cost_of_lqr(quadrotor_2d_far):
    env, params = quadrotor_2d_far
    key = jax.random.key(0)
    lqr = evaluate(env, params, make_lqr(env, params), key, 4, measure_time=False)
    ilqr = evaluate(env, params, make_ilqr(env, params), key, 4, measure_time=False)
    # The cost compared is the episode's closed-loop quadratic cost on the true plant, sum_k 1/2 e^T Q e +
    # 1/2 du^T R du with the applied (clipped) inputs: minus the return of the env's quadratic reward, with the
    # Q and R both controllers are built from. LQR minimises exactly this (infinite-horizon) cost for the
    # linearisation without input limits; iLQR minimises it over its horizon, with the DARE cost-to-go after, on
    # the nonlinear model with the limits. From the same initial states (same key), it must do better on each.
    lqr_cost, ilqr_cost = -lqr.per_episode["return"], -ilqr.per_episode["return"]
    assert lqr.summary["failure_rate"] == 0.0 and ilqr.summary["failure_rate"] == 0.0
    assert np.all(ilqr_cost < lqr_cost)
    assert ilqr_cost.mean() < 0.85 * lqr_cost.mean()  # measured: 12.8 against 17.5
    low, high = env.input_bounds(params.physics)
    assert np.all(ilqr.trajectory["u_cmd"] >= np.asarray(low)) and np.all(ilqr.trajectory["u_cmd"] <= np.asarray(high))


# ------------------------------------------------------------------------------------------------ batching
X0_BATCH = np.array(
    [[0.8, 0.0, 0.5, 0.0, 0.4, 0.0], [-0.6, 0.3, 1.4, -0.2, -0.3, 0.5], [0.1, 0.0, 1.0, 0.0, 0.05, 0.0]]
)
HORIZON = 30


@pytest.fixture(scope="module")
def solves_2d():
    """The 2D quadrotor's solve from three states, vmapped and one at a time (float64), and its problem data."""
    with jax.enable_x64(True):
        env = scg_jax.make("quadrotor_2d")
        params = env.default_params
        step = model_step_fn(env, params)
        goal = np.asarray(params.goal, dtype=np.float64)
        u_eq = np.asarray(env.system.equilibrium_input(params.physics), dtype=np.float64)
        Q, R = np.asarray(params.Q, np.float64), np.asarray(params.R, np.float64)
        lin = env.symbolic_model(params, "rk4").linearize(goal, u_eq)
        K, P = discrete_lqr_gain(lin.Ad, lin.Bd, Q, R)
        low, high = (np.asarray(b, np.float64) for b in env.input_bounds(params.physics))
        settings = ILQRSettings(max_iterations=30)

        def solve(x0):
            hover = jnp.tile(u_eq, (HORIZON, 1))
            return ilqr_solve(step, x0, hover, jnp.tile(goal, (HORIZON + 1, 1)), hover, Q, R, P, low, high, settings)

        batched = jax.jit(jax.vmap(solve))
        single = jax.jit(solve)
        x0 = jnp.asarray(X0_BATCH)
        data = {"step": jax.jit(step), "goal": goal, "u_eq": u_eq, "Q": Q, "R": R, "P": P, "K": K, "low": low}
        data["high"] = high
        return batched(x0), batched(x0), [single(x) for x in x0], data


def test_vmap_over_copies_equals_one_at_a_time_and_repeats_exactly(solves_2d):
    first, second, singles, _ = solves_2d
    # The copies stop after different numbers of iterations, so the vmapped while loop must freeze finished ones.
    iterations = np.asarray(first.iterations)
    assert len(set(iterations.tolist())) > 1 and np.all(np.asarray(first.converged))
    for name in first._fields:
        batched = np.asarray(getattr(first, name))
        assert np.array_equal(batched, np.asarray(getattr(second, name))), name
        one_by_one = np.stack([np.asarray(getattr(s, name)) for s in singles])
        np.testing.assert_allclose(batched, one_by_one, rtol=1e-10, atol=1e-12, err_msg=name)


def test_solutions_descend_stay_within_limits_and_beat_the_lqr_plan(solves_2d):
    sol, _, _, data = solves_2d
    history = np.asarray(sol.cost_history)
    assert np.all(np.diff(history, axis=1) <= 0.0)
    u = np.asarray(sol.u)
    assert np.all(u >= data["low"]) and np.all(u <= data["high"])
    # The horizon cost (the solver's objective: stage costs 1/2 dx^T Q dx + 1/2 du^T R du and the DARE terminal
    # weight, on the RK4 model) of the LQR policy, clipped to the limits, from the same states. iLQR starts from
    # hovering open loop, not from LQR, so doing better is not built in.
    with jax.enable_x64(True):
        for copy, x0 in enumerate(X0_BATCH):
            x, cost = x0, 0.0
            for _ in range(HORIZON):
                dx = x - data["goal"]
                u_lqr = np.clip(data["u_eq"] - data["K"] @ dx, data["low"], data["high"])
                du = u_lqr - data["u_eq"]
                cost += 0.5 * dx @ data["Q"] @ dx + 0.5 * du @ data["R"] @ du
                x = np.asarray(data["step"](x, u_lqr))
            dx = x - data["goal"]
            cost += 0.5 * dx @ data["P"] @ dx
            assert float(sol.cost[copy]) < cost, copy


# ------------------------------------------------------------------------------------------------ errors
@pytest.mark.parametrize(
    "options, message",
    [
        ({"horizon": 0}, r"controllers.ilqr.horizon: must be a positive integer, got 0"),
        ({"max_iterations": 0}, r"controllers.ilqr.max_iterations: must be a positive integer, got 0"),
        ({"line_search_factor": 1.5}, r"controllers.ilqr.line_search_factor: must be in \(0, 1\)"),
        ({"regularization_factor": 1.0}, r"controllers.ilqr.regularization_factor: must be > 1"),
        ({"regularization_max": 1e-7}, r"controllers.ilqr.regularization_max: must exceed regularization_min"),
        ({"terminal_scale": 0.0}, r"controllers.ilqr.terminal_scale: must be positive"),
        ({"input_constraints": "soft"}, r"controllers.ilqr.input_constraints: unknown value 'soft'; allowed values"),
        ({"discretization": "euler"}, r"controllers.ilqr.discretization: unknown value 'euler'; allowed values"),
        ({"q_diag": [1.0, 1.0]}, r"controllers.ilqr.q_diag: expected 6 values, got 2"),
        ({"r_diag": [0.0, 1.0]}, r"controllers.ilqr.r_diag: the input weight must be positive definite"),
        ({"horizn": 10}, r"controllers.ilqr.horizn: unknown key; allowed keys are horizon"),
    ],
)
def test_bad_options_name_the_field(options, message):
    env = scg_jax.make("quadrotor_2d")
    with pytest.raises(ValueError, match=message):
        make_ilqr(env, env.default_params, options)


@pytest.mark.parametrize(
    "settings, message",
    [
        ({"max_iterations": 0}, r"ILQRSettings.max_iterations: must be a positive integer"),
        ({"line_search_steps": 0}, r"ILQRSettings.line_search_steps: must be a positive integer"),
        ({"tolerance": -1.0}, r"ILQRSettings.tolerance: must be positive"),
        (
            {"input_constraints": "none"},
            r"ILQRSettings.input_constraints: unknown value 'none'; allowed values are box",
        ),
    ],
)
def test_bad_solver_settings_name_the_field(settings, message):
    with pytest.raises(ValueError, match=message):
        ILQRSettings(**settings)
