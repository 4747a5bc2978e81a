"""Linear MPC: the condensed QP against a direct simulation, the batched qpax solve against qpOASES, the JAX
controller against the CasADi one, LQR without active constraints, and constraint satisfaction in closed loop."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import scg_jax
from scg_algorithms.base import Reference
from scg_algorithms.evaluation import evaluate
from scg_algorithms.lqr import make_lqr
from scg_algorithms.mpc import cases, structured
from scg_algorithms.mpc import qp as qp_lib
from scg_algorithms.mpc.linear import make_linear_mpc, make_linear_mpc_casadi

# Position box inside the default state bounds, so some stages of a perturbed tracking QP press against it.
QUAD_CONSTRAINTS = cases.case_constraints("quadrotor_2d")
# Cart within 0.3 m, force within 2 N (LQR asks for more from the states below), plus the default input rows,
# which repeat the 10 N actuator limits (the controllers merge them).
CARTPOLE_CONSTRAINTS = cases.case_constraints("cartpole", extra=[{"type": "abs_bound", "on": "input", "bound": 2.0}])
CARTPOLE_SPREAD = np.array(cases.CASES["cartpole"].spread)  # half-widths of the random states (m, m/s, rad, rad/s)


@pytest.fixture(scope="module")
def quadrotor():
    env = scg_jax.make("quadrotor_2d", task="tracking", constraints=QUAD_CONSTRAINTS)
    params = env.default_params
    return env, params, Reference(*(np.asarray(a, np.float64) for a in env.reference(params)))


@pytest.fixture(scope="module")
def cartpole():
    env = scg_jax.make("cartpole", constraints=CARTPOLE_CONSTRAINTS)
    params = env.default_params
    return env, params, Reference(*(np.asarray(a, np.float64) for a in env.reference(params)))


def _random_states(reference, spread, count, seed):
    """``count`` (step, state) pairs: a random step of the reference and a state around its point."""
    rng = np.random.default_rng(seed)
    steps = rng.integers(0, reference.x_ref.shape[0] - 1, count)
    states = reference.x_ref[steps] + rng.uniform(-1.0, 1.0, (count, reference.x_ref.shape[1])) * spread
    return steps, states


# --------------------------------------------------------------------------------------------- the condensed QP
def _random_model(rng, nx, nu, num_points):
    spd = lambda n: (lambda a: a @ a.T + n * np.eye(n))(rng.normal(size=(n, n)))  # noqa: E731
    return qp_lib.AffineModel(
        Ad=np.eye(nx) + 0.3 * rng.normal(size=(num_points, nx, nx)),
        Bd=rng.normal(size=(num_points, nx, nu)),
        c=rng.normal(size=(num_points, nx)),
        x_bar=rng.normal(size=(num_points, nx)),
        u_bar=rng.normal(size=nu),
        K=0.3 * rng.normal(size=(num_points, nu, nx)),
        P=np.stack([spd(nx) for _ in range(num_points)]),
    )


def _simulated(model, Q, R, rows, x0, x_ref, step, v, e, horizon, slack_l1, slack_l2):
    """J/2, the row values ``(Ax x + Au u - b) / |row|`` per stage and u_0 of the plan ``v``, by forward
    simulation of the affine model with the stage points clamped at its last point."""
    last, T = model.num_points - 1, x_ref.shape[0] - 1
    norms = np.linalg.norm(np.concatenate([rows.Ax, rows.Au], axis=1), axis=1)
    x, cost, values, u0 = x0, 0.0, [], None
    for j in range(horizon):
        i = min(step + j, last)
        u = model.u_bar - model.K[i] @ (x - model.x_bar[i]) + v[j]
        x = model.Ad[i] @ x + model.Bd[i] @ u + model.c[i]
        weight = model.P[min(step + horizon, last)] if j == horizon - 1 else Q
        dx, du = x - x_ref[min(step + 1 + j, T)], u - model.u_bar
        cost += 0.5 * dx @ weight @ dx + 0.5 * du @ R @ du
        values.append((rows.Ax @ x + rows.Au @ u - rows.b) / norms)
        u0 = u if j == 0 else u0
    cost += slack_l1 * e.sum() + 0.5 * slack_l2 * e @ e
    return cost, np.stack(values), u0


@pytest.mark.parametrize("softening", ["hard", "shared", "per_stage"])
def test_condensed_qp_matches_a_forward_simulation_of_a_time_varying_model(softening):
    # A random model with a different linearisation at each of 7 points and pre-stabilising gains, so every
    # part of the condensing is exercised (the envs' own linearisations are all time-invariant).
    rng = np.random.default_rng(0)
    nx, nu, H, slack_l1, slack_l2 = 3, 2, 4, 7.0, 3.0
    model = _random_model(rng, nx, nu, 7)
    Q, R = np.diag([1.0, 2.0, 0.5]), np.diag([0.3, 0.7])
    rows = qp_lib.ConstraintRows(
        Ax=np.array([[1.0, 0.0, -2.0], [0.0, 0.0, 0.0], [0.5, 1.0, 0.0]]),
        Au=np.array([[0.0, 1.0], [3.0, -1.0], [0.0, 0.0]]),
        b=np.array([1.0, 2.0, -0.5]),
        soft=np.array([True, False, True]),
    )
    soft = softening != "hard"
    per_stage = softening == "per_stage"
    qp = qp_lib.build_qp(
        model, H, Q, R, rows, soft_constraints=soft, slack_per_stage=per_stage, slack_l1=slack_l1, slack_l2=slack_l2
    )
    assert qp.hess.shape[0] == model.num_points  # one QP per step: the model is time-varying
    num_slacks = (2 * H if per_stage else 2) if soft else 0
    assert qp.num_slacks == num_slacks and qp.num_decisions == H * nu + num_slacks
    x_ref = rng.normal(size=(9, nx))
    with jax.enable_x64(True):
        arrays = qp_lib.qp_arrays(qp, jnp.float64)
        for step in (0, 2, 5):  # 5 + H runs past the last linearisation point: the stages clamp
            x0 = rng.normal(size=nx)
            hess, q, G, h, theta, index = (np.asarray(a) for a in qp_lib.qp_vectors(qp, arrays, step, x0, x_ref))
            objective = []
            for _ in range(2):
                z = rng.normal(size=qp.num_decisions)
                v, e = z[: H * nu].reshape(H, nu), z[H * nu :]
                cost, values, u0 = _simulated(model, Q, R, rows, x0, x_ref, step, v, e, H, slack_l1, slack_l2)
                objective.append((qp.objective_scale * (0.5 * z @ hess @ z + q @ z), cost))
                # Row (stage j, row r) of G z - h is the scaled row value minus its slack.
                slack = np.zeros((H, 3))
                if soft:
                    slack[:, [0, 2]] = e.reshape(H, 2) if per_stage else e
                np.testing.assert_allclose((G @ z - h)[: 3 * H], (values - slack).ravel(), atol=1e-9)
                np.testing.assert_allclose((G @ z - h)[3 * H :], -e, atol=1e-12)
                np.testing.assert_allclose(qp_lib.first_input(arrays, z, theta, index), u0, atol=1e-9)
            # The QP objective is J/2 up to a constant that does not depend on z.
            (f1, j1), (f2, j2) = objective
            np.testing.assert_allclose(f1 - f2, j1 - j2, rtol=1e-9, atol=1e-9)


# --------------------------------------------------------------------------------------------- the QP solve
def test_batched_qpax_solve_matches_qpoases_on_the_quadrotor_tracking_qp(quadrotor):
    env, params, reference = quadrotor
    steps, states = _random_states(reference, np.array([0.1, 0.3, 0.1, 0.3, 0.3, 0.5]), 12, seed=0)
    with jax.enable_x64(True):
        qp = make_linear_mpc(env, params, {"horizon": 10}).info["qp"]
        arrays = qp_lib.qp_arrays(qp, jnp.float64)
        vectors = jax.vmap(qp_lib.qp_vectors, in_axes=(None, None, 0, 0, None))
        hess, q, G, h, theta, index = vectors(qp, arrays, jnp.asarray(steps), jnp.asarray(states), reference.x_ref)
        solution = jax.jit(qp_lib.solve_qp_batch)(hess[0], q, G[0], h)
        u_qpax = jax.vmap(qp_lib.first_input, in_axes=(None, 0, 0, None))(arrays, solution.z, theta, 0)
    compared = active = 0
    for i in range(len(steps)):
        z_ref, success = qp_lib.solve_qp_casadi(hess[i], q[i], G[i], h[i], "qpoases")
        if not success:  # the hard position box cannot be met from this state: qpax must not claim a solution
            assert solution.status[i] == qp_lib.STATUS_FAILED
            continue
        compared += 1
        active += int(np.any(np.asarray(G[i]) @ z_ref - np.asarray(h[i]) > -1e-7))
        assert solution.status[i] != qp_lib.STATUS_FAILED
        np.testing.assert_allclose(solution.z[i], z_ref, atol=1e-4)
        u_ref = qp.u0_map[0] @ np.concatenate([z_ref, np.asarray(theta[i])])
        np.testing.assert_allclose(u_qpax[i], u_ref, atol=1e-4)
    # The comparison covers feasible QPs, most of them with rows at their bounds.
    assert compared >= 8 and active >= 5


def test_float32_qpax_solve_matches_qpoases_on_the_cartpole_qp(cartpole):
    # Float32 (the default): the interior point's float32 limit is far below the 1e-4 N checked here on the
    # cart-pole (measured within 1e-6 N), though on larger, stiffer QPs (the 2D quadrotor's) it is up to about 1e-2 N.
    env, params, reference = cartpole
    steps, states = _random_states(reference, CARTPOLE_SPREAD, 10, seed=0)
    controller = make_linear_mpc(env, params, {"horizon": 20})
    qp = controller.info["qp"]
    arrays = qp_lib.qp_arrays(qp)
    vectors = jax.vmap(qp_lib.qp_vectors, in_axes=(None, None, 0, 0, None))
    hess, q, G, h, theta, _ = vectors(qp, arrays, jnp.asarray(steps), jnp.asarray(states, jnp.float32), reference.x_ref)
    solution = jax.jit(qp_lib.solve_qp_batch)(hess[0], q, G[0], h)
    with jax.enable_x64(True):
        # The reference solves the same QP, formed in float64.
        arrays64 = qp_lib.qp_arrays(qp, jnp.float64)
        data64 = jax.vmap(qp_lib.qp_vectors, in_axes=(None, None, 0, 0, None))(
            qp, arrays64, jnp.asarray(steps), jnp.asarray(states), reference.x_ref
        )
    active = 0
    for i in range(len(steps)):
        z_ref, success = qp_lib.solve_qp_casadi(data64[0][i], data64[1][i], data64[2][i], data64[3][i], "qpoases")
        assert success and solution.status[i] != qp_lib.STATUS_FAILED
        active += int(np.any(np.asarray(data64[2][i]) @ z_ref - np.asarray(data64[3][i]) > -1e-7))
        u_ref = np.asarray(arrays64.u0_map[0]) @ np.concatenate([z_ref, np.asarray(data64[4][i])])
        np.testing.assert_allclose(qp_lib.first_input(arrays, solution.z[i], theta[i], 0), u_ref, atol=1e-4)
    assert active >= 5


# --------------------------------------------------------------------------------------------- the controllers
def test_jax_and_casadi_linear_mpc_give_the_same_first_input_on_the_cartpole(cartpole):
    # Float32 JAX controller against qpOASES in float64 on the sparse problem built from the symbolic model's own
    # constraint functions: agreement to 1e-4 N (the float32 interior point reaches about 1e-6 N here).
    env, params, reference = cartpole
    steps, states = _random_states(reference, CARTPOLE_SPREAD, 8, seed=1)
    options = {"horizon": 20}
    jax_mpc = make_linear_mpc(env, params, options)
    casadi_mpc = make_linear_mpc_casadi(env, params, options)
    act = jax.jit(jax_mpc.act)
    saturated = 0
    for step, x in zip(steps, states, strict=True):
        u_jax, status = act(jax_mpc.reset(None, reference), jnp.asarray(x, jnp.float32), step, reference)
        u_casadi, info = casadi_mpc.act(casadi_mpc.reset(None, reference), x, step, reference)
        assert info["success"] and int(status.status) == structured.CONVERGED
        np.testing.assert_allclose(u_jax, u_casadi, atol=1e-4)
        saturated += int(abs(u_casadi[0]) > 2.0 - 1e-6)
    assert 0 < saturated < len(steps)  # some first inputs sit at the 2 N bound, some do not


@pytest.mark.parametrize("per_stage", [False, True])
def test_jax_and_casadi_soft_constrained_mpc_agree_on_the_quadrotor(quadrotor, per_stage):
    # Float64: the 2D quadrotor's QP is beyond float32's reach at 1e-4 N (see the float32 test above).
    env, params, reference = quadrotor
    steps, states = _random_states(reference, 0.2, 5, seed=0)
    options = {"horizon": 10, "soft_constraints": True, "slack_per_stage": per_stage}
    casadi_mpc = make_linear_mpc_casadi(env, params, options)
    violated = 0
    with jax.enable_x64(True):
        jax_mpc = make_linear_mpc(env, params, options)
        qp = jax_mpc.info["qp"]
        arrays = qp_lib.qp_arrays(qp, jnp.float64)
        act = jax.jit(jax_mpc.act)
        reference64 = Reference(*(jnp.asarray(a, jnp.float64) for a in reference))
        plan = jax.jit(lambda step, x: qp_lib.solve_qp(*qp_lib.qp_vectors(qp, arrays, step, x, reference64.x_ref)[:4]))
        for step, x in zip(steps, states, strict=True):
            u_jax, status = act(jax_mpc.reset(None, reference64), jnp.asarray(x), step, reference64)
            u_casadi, info = casadi_mpc.act({}, x, step, reference)
            assert info["success"] and int(status.status) == structured.CONVERGED
            np.testing.assert_allclose(u_jax, u_casadi, atol=1e-4)
            z = plan(step, jnp.asarray(x)).z
            violated += int(np.max(z[qp.num_decisions - qp.num_slacks :]) > 1e-6)
    assert violated >= 3  # most plans leave the position box: the slacks are priced the same way in both


@pytest.mark.parametrize("solver", ["admm", "ipm", "active_set"])
@pytest.mark.parametrize("system", list(cases.CASES))
def test_linear_mpc_matches_qpoases_to_a_millinewton_with_active_input_and_state_rows(system, solver):
    # Float32, 100 random states per system through one vmapped call (the benchmark runs 1,000); CasADi qpOASES
    # one by one in float64. The states where qpOASES fails (hard state rows the plant cannot meet; on the 3D
    # quadrotor also some where the ADMM converges to a plan that meets them) are left out of the comparison.
    # The cart-pole's force is also held within 2 N (LQR asks for more from these states).
    extra = [{"type": "abs_bound", "on": "input", "bound": 2.0}] if system == "cartpole" else []
    count = 100
    env, params = cases.make_case_env(system, extra=extra)
    reference = Reference(*(np.asarray(a, np.float64) for a in env.reference(params)))
    case = cases.CASES[system]
    steps, states = cases.random_states(env, reference, case.offset, case.spread, count)
    options = {"horizon": 20}
    jax_mpc = make_linear_mpc(env, params, {**options, "solver": solver})
    casadi_mpc = make_linear_mpc_casadi(env, params, options)
    reference32 = Reference(*(jnp.asarray(a, jnp.float32) for a in reference))
    act = jax.jit(jax.vmap(lambda x, k: jax_mpc.act(jax_mpc.reset(None, reference32), x, k, reference32)))
    u_jax, ctrl_state = act(jnp.asarray(states, jnp.float32), jnp.asarray(steps))
    u_jax, status = np.asarray(u_jax), np.asarray(ctrl_state.status)
    u_casadi, feasible = [], []
    for step, x in zip(steps, states, strict=True):
        u, info = casadi_mpc.act({}, x, step, reference)
        u_casadi.append(u)
        feasible.append(info["success"])
    u_casadi, feasible = np.array(u_casadi), np.array(feasible)
    assert feasible.sum() >= 40
    lo, hi = jax_mpc.info["u_low"], jax_mpc.info["u_high"]
    assert np.all((u_jax >= lo) & (u_jax <= hi))
    if solver in ("admm", "active_set"):
        assert np.all(status[feasible] != structured.INFEASIBLE)
        np.testing.assert_allclose(u_jax[feasible], u_casadi[feasible], atol=1e-3)
    else:
        # The interior point in float32 can miss a state by a few millinewtons where its iterate lost the active set
        # before the polish could hold it (docs/controllers.md: of the benchmark's 1,000 states per system, the one
        # on the 2D quadrotor whose feasible set is a sliver, 4.3e-3 N): at most one of these 100 per system beyond
        # 1e-3 N, none beyond 1e-2 N.
        error = np.abs(u_jax - u_casadi).max(axis=1)[feasible]
        assert np.sum(error > 1e-3) <= 1 and error.max() <= 1e-2
        assert np.median(error) <= 1e-5
    # Active rows among the compared states: a first input at its bound, and a state row with a multiplier.
    at_bound = np.any((np.abs(u_casadi - lo) < 1e-6) | (np.abs(u_casadi - hi) < 1e-6), axis=1)
    assert np.sum(at_bound & feasible) >= 10
    if solver in ("admm", "active_set"):  # both keep their multipliers (the ADMM's warm start)
        multipliers = np.asarray(ctrl_state.warm.multipliers).reshape(count, 20, -1)
        state_active = np.any(np.abs(multipliers[:, :, env.nu :]) > 1e-6, axis=(1, 2))
        assert np.sum(state_active & feasible) >= 5


FIXED_STEP = {"admm_tol": 0.0, "admm_polish_rounds": 0, "admm_adaptive_rho": False}


@pytest.mark.parametrize(
    "system, with_state, iterations, rho_scale, alpha",
    [("cartpole", False, 25, 1.0, 1.6), ("quadrotor_2d", False, 100, 10.0, 1.6), ("cartpole", True, 160, 25.0, 1.9)],
    ids=["cartpole_25", "quadrotor_2d_100_x10", "cartpole_box_160_x25_alpha_1.9"],
)
def test_the_fixed_step_throughput_settings_run_their_iterations_and_match_qpoases(
    system, with_state, iterations, rho_scale, alpha
):
    # benchmarks/control.py's throughput settings: every copy runs exactly `iterations` iterations at the prepared
    # step size times `rho_scale`, whose products prepare folds once (structured.Prepared.fixed), with no polish.
    # Over the benchmark's 1,000 states they hold qpOASES's first input to 1.5e-6 N (cart-pole, input bounds),
    # 7e-4 N (2D quadrotor, input bounds; the unscaled step size leaves 25 states beyond 1e-3 N) and 7.7e-4 N
    # (cart-pole with its 0.3 m cart box, over-relaxation 1.9; at 1.6 it needs 200 iterations, and at 1.9 with 150
    # one state is 1.0e-3 N off); here 60 of those states, float32.
    env, params = cases.make_case_env(system, with_state=with_state)
    reference = Reference(*(np.asarray(a, np.float64) for a in env.reference(params)))
    case = cases.CASES[system]
    steps, states = cases.random_states(env, reference, case.offset, case.spread, 60)
    fast = {**FIXED_STEP, "admm_max_iter": iterations, "admm_check_every": iterations}
    jax_mpc = make_linear_mpc(env, params, {"horizon": 20, **fast, "admm_rho_scale": rho_scale, "admm_alpha": alpha})
    assert jax_mpc.info["structured"].settings.alpha == alpha
    prepared = jax_mpc.info["structured"].prepared
    unscaled = make_linear_mpc(env, params, {"horizon": 20, **fast}).info["structured"].prepared
    np.testing.assert_allclose(float(prepared.rho), rho_scale * float(np.min(prepared.lam)), rtol=1e-5)
    np.testing.assert_allclose(float(unscaled.rho), float(np.min(unscaled.lam)), rtol=1e-5)
    GT, lam = (np.asarray(a, np.float64) for a in (prepared.GT, prepared.lam))
    folded = (GT / (lam + float(prepared.rho))) @ GT.T  # the one (rows x rows) product per iteration
    np.testing.assert_allclose(np.asarray(prepared.fixed), folded, rtol=1e-4, atol=1e-6 * np.abs(folded).max())
    casadi_mpc = make_linear_mpc_casadi(env, params, {"horizon": 20})
    reference32 = Reference(*(jnp.asarray(a, jnp.float32) for a in reference))
    act = jax.jit(jax.vmap(lambda x, k: jax_mpc.act(jax_mpc.reset(None, reference32), x, k, reference32)))
    u_jax, ctrl_state = act(jnp.asarray(states, jnp.float32), jnp.asarray(steps))
    solved = [casadi_mpc.act({}, x, k, reference) for k, x in zip(steps, states, strict=True)]
    u_casadi = np.array([u for u, _ in solved])
    assert all(info["success"] for _, info in solved)
    np.testing.assert_array_equal(np.asarray(ctrl_state.iterations), iterations)
    np.testing.assert_allclose(np.asarray(u_jax), u_casadi, atol=1e-3)
    lo, hi = jax_mpc.info["u_low"], jax_mpc.info["u_high"]
    assert np.sum(np.any((np.abs(u_casadi - lo) < 1e-6) | (np.abs(u_casadi - hi) < 1e-6), axis=1)) >= 5


def test_the_admm_step_size_settles_where_moving_it_every_five_iterations_did_not():
    """The ADMM checks its residuals and moves its step size every ``admm_check_every`` iterations (20). Moved every
    5, it kept some copies from settling: of the benchmark's first 100 cart-pole states with the cart box
    (``cases``, seed 0), 2 ran to the 1,000-iteration cap, and a batch waits for its slowest copy (the polish then
    found their plans). Every 20, the slowest converges by 180 iterations, to the same first inputs."""
    env, params = cases.make_case_env("cartpole")
    reference = Reference(*(jnp.asarray(a, jnp.float32) for a in env.reference(params)))
    case = cases.CASES["cartpole"]
    steps, states = cases.random_states(env, reference, case.offset, case.spread, 100)
    runs = {}
    for name, options in (("default", {}), ("every 5", {"admm_check_every": 5})):
        mpc = make_linear_mpc(env, params, {"horizon": 20, **options})
        act = jax.jit(jax.vmap(lambda x, k, mpc=mpc: mpc.act(mpc.reset(None, reference), x, k, reference)))
        u, ctrl_state = act(jnp.asarray(states, jnp.float32), jnp.asarray(steps))
        runs[name] = np.asarray(u), np.asarray(ctrl_state.iterations), np.asarray(ctrl_state.status)
        if name == "default":
            assert mpc.info["options"].admm_check_every == 20
    u, iterations, status = runs["default"]
    assert np.all(status == structured.CONVERGED) and iterations.max() < 300
    u_old, iterations_old, _ = runs["every 5"]
    assert np.sum(iterations_old >= 1000) >= 1
    np.testing.assert_allclose(u, u_old, atol=1e-4)


@pytest.mark.parametrize(
    "system, with_state, picked",
    [("quadrotor_2d", False, [155, 212, 964]), ("quadrotor_1d", True, [150])],
    ids=["quadrotor_2d_input", "quadrotor_1d_ceiling"],
)
def test_the_polish_refuses_a_wrong_sign_multiplier_and_a_crossed_free_row_in_float32(system, with_state, picked):
    # States of the benchmark's 1,000 (cases.random_states) where the float32 polish, accepting at the square root of
    # the resolution (3.5e-4), took a plan that held a row with a multiplier of the wrong sign (2D quadrotor: first
    # inputs 2.4e-3, 3.0e-3 and 1.3e-3 N from qpOASES's) or let a free row cross the 1D quadrotor's ceiling by
    # 1.35e-4 half-widths (1.1e-3 N). With POLISH_TOL and POLISH_DUAL_TOL the next round finds qpOASES's set.
    _converged_with_qpoases_first_inputs(system, with_state, picked)


def test_where_the_polish_rounds_cycle_the_dual_active_set_method_finds_qpoases_plan():
    # States 794 and 798 of the benchmark's 1,000 on the 2D quadrotor with its position box: the ADMM stops at its
    # 1,000-iteration cap, and the polish's rounds go round (on 794: a set of 23 rows that depend on each other, whose
    # solve gives no set, then 17 rows, then none again), so the first inputs were 0.17 N and 1.3e-3 N from
    # qpOASES's. The dual active-set method (admm_dual_active_set_steps, 30) takes 20 and 1 steps from the ADMM's set.
    _converged_with_qpoases_first_inputs("quadrotor_2d", True, [794, 798])


def _converged_with_qpoases_first_inputs(system, with_state, picked, atol=1e-4):
    """The default linear MPC on the benchmark's states ``picked`` (of cases.random_states' 1,000) converges to
    qpOASES's first inputs within ``atol`` (N)."""
    env, params = cases.make_case_env(system, with_state=with_state)
    reference = Reference(*(np.asarray(a, np.float64) for a in env.reference(params)))
    case = cases.CASES[system]
    steps, states = cases.random_states(env, reference, case.offset, case.spread, 1000)
    steps, states = steps[picked], states[picked]
    jax_mpc = make_linear_mpc(env, params, {"horizon": 20})
    casadi_mpc = make_linear_mpc_casadi(env, params, {"horizon": 20})
    reference32 = Reference(*(jnp.asarray(a, jnp.float32) for a in reference))
    act = jax.jit(jax.vmap(lambda x, k: jax_mpc.act(jax_mpc.reset(None, reference32), x, k, reference32)))
    u_jax, ctrl_state = act(jnp.asarray(states, jnp.float32), jnp.asarray(steps))
    solved = [casadi_mpc.act({}, x, k, reference) for k, x in zip(steps, states, strict=True)]
    assert all(info["success"] for _, info in solved)
    np.testing.assert_array_equal(np.asarray(ctrl_state.status), structured.CONVERGED)
    np.testing.assert_allclose(np.asarray(u_jax), np.array([u for u, _ in solved]), atol=atol)


def test_without_active_constraints_the_first_input_is_the_lqr_input(cartpole):
    # P is the Riccati solution, so the finite-horizon optimum starts with the infinite-horizon (LQR) input, for
    # either condensing (pre-stabilised or plain).
    env, params, reference = cartpole
    states = np.random.default_rng(4).uniform(-0.01, 0.01, (4, 4))
    K = make_lqr(env, params).info["K"][0]
    with jax.enable_x64(True):
        reference64 = Reference(*(jnp.asarray(a, jnp.float64) for a in reference))
        for prestabilize in (True, False):
            mpc = make_linear_mpc(env, params, {"horizon": 15, "prestabilize": prestabilize})
            act = jax.jit(mpc.act)
            for x in states:
                u, status = act(mpc.reset(None, reference64), jnp.asarray(x), 0, reference64)
                assert int(status.status) == structured.CONVERGED
                np.testing.assert_allclose(u, -K @ x, rtol=1e-6, atol=1e-9)


def test_the_ipm_polish_holds_a_loosely_held_active_set_harder(monkeypatch):
    # State 775 of the benchmark's 1,000 cart-pole states (input bounds, cart box): in float32 the interior point's
    # step broke off after 14 iterations, and its polish found the right 5 rows but held them only to 4e-5 (scaled;
    # its tolerance 1e-5) however many augmented-Lagrangian steps it took, so no round was accepted and the plan
    # was 6.6e-3 N from qpOASES's. A round that held the right rows loosely is now repeated at 100x the weight
    # (to 1e6), which holds them: 1.4e-5 N. Without the growth the miss is back.
    from scg_algorithms.mpc import interior_point

    env, params = cases.make_case_env("cartpole")
    reference = Reference(*(np.asarray(a, np.float64) for a in env.reference(params)))
    case = cases.CASES["cartpole"]
    steps, states = cases.random_states(env, reference, case.offset, case.spread, 1000)
    step, x = int(steps[775]), states[775]
    u_qpoases, info = make_linear_mpc_casadi(env, params, {"horizon": 20}).act({}, x, step, reference)
    assert info["success"]
    reference32 = Reference(*(jnp.asarray(a, jnp.float32) for a in reference))

    def first_input():
        mpc = make_linear_mpc(env, params, {"horizon": 20, "solver": "ipm"})
        u, ctrl_state = jax.jit(mpc.act)(mpc.reset(None, reference32), jnp.asarray(x, jnp.float32), step, reference32)
        return np.asarray(u), int(ctrl_state.status)

    u, status = first_input()
    assert status == structured.CONVERGED  # a polished plan
    np.testing.assert_allclose(u, u_qpoases, atol=1e-4)
    monkeypatch.setattr(interior_point, "POLISH_RHO_GROWTH", 1.0)
    u, status = first_input()
    assert status == structured.NUMERICAL and np.abs(u - u_qpoases).max() > 1e-3


@pytest.mark.parametrize("solver", ["admm", "ipm", "active_set"])
def test_an_infeasible_qp_falls_back_to_the_clipped_lqr_input(cartpole, solver):
    # The cart 1 m beyond its 0.3 m bound: no plan meets the hard row at the next state, so the input is LQR's,
    # clipped to the 2 N box. (The first-input test's controller and argument types: the same program, which the
    # run's compilation cache then holds.)
    env, params, reference = cartpole
    mpc = make_linear_mpc(env, params, {"horizon": 20, "solver": solver})
    x = np.array([1.3, 0.0, 0.0, 0.0])
    u, status = jax.jit(mpc.act)(mpc.reset(None, reference), jnp.asarray(x, jnp.float32), np.int64(0), reference)
    assert int(status.status) == structured.INFEASIBLE
    K = make_lqr(env, params).info["K"][0]
    np.testing.assert_allclose(u, np.clip(-K @ x, -2.0, 2.0), rtol=1e-6)
    assert np.all(mpc.info["u_high"] == 2.0) and np.all(mpc.info["u_low"] == -2.0)


def test_mpc_holds_an_input_bound_that_lqr_violates():
    env = scg_jax.make(
        "cartpole",
        episode_len_sec=3.0,
        init_state={"type": "uniform", "low": [-0.1] * 4, "high": [0.1] * 4},
        constraints=[{"type": "abs_bound", "on": "input", "bound": 1.5}],
    )
    params = env.default_params
    key = jax.random.key(0)
    lqr = evaluate(env, params, make_lqr(env, params), key, 8, measure_time=False)
    mpc_controller = make_linear_mpc(env, params, {"horizon": 20})
    mpc = evaluate(env, params, mpc_controller, key, 8, measure_time=False)
    # LQR asks for up to 5 N from these starts (the same episodes: same key).
    assert np.abs(lqr.trajectory["u_cmd"]).max() > 3.0
    assert lqr.summary["constraint_violation_steps"] > 0
    assert mpc.summary["constraint_violation_steps"] == 0 and mpc.summary["crash_rate"] == 0.0
    assert mpc.summary["length"] == env.num_steps
    # The bound is held by the QP itself, not only by the final clip: no solve failed over the episodes.
    reference = Reference(*env.reference(params))

    def replay(obs_seq):
        def body(state, inputs):
            obs, step = inputs
            _, state = mpc_controller.act(state, obs, step, reference)
            return state, state.status

        steps = jnp.arange(obs_seq.shape[0])
        return jax.lax.scan(body, mpc_controller.reset(None, reference), (obs_seq, steps))[1]

    statuses = jax.jit(jax.vmap(replay, in_axes=1))(jnp.asarray(mpc.trajectory["obs"]))
    assert np.all(np.asarray(statuses) == structured.CONVERGED)


# --------------------------------------------------------------------------------------------- options
def test_the_default_solver_is_the_active_set_where_it_holds_the_problem_else_the_admm(cartpole):
    # auto: hard rows and one model (every env's linearisation) take the active set; soft rows, or an ADMM option
    # given, the ADMM.
    env, params, _ = cartpole
    for options, solver in [
        ({}, "active_set"),
        ({"soft_constraints": True}, "admm"),
        ({"admm_max_iter": 50}, "admm"),
        ({"warm_start": False}, "admm"),
        ({"solver": "ipm"}, "ipm"),
    ]:
        mpc = make_linear_mpc(env, params, {"horizon": 10, **options})
        assert mpc.info["solver"] == solver, options
        assert mpc.info["structured"].settings.method == ("dual_active_set" if solver == "active_set" else "admm")


@pytest.mark.parametrize(
    "options, message",
    [
        ({"horizn": 10}, r"controllers\.linear_mpc\.horizn: unknown key.*did you mean 'horizon'"),
        ({"horizon": 0}, r"controllers\.linear_mpc\.horizon: must be a positive integer"),
        ({"horizon": 2.5}, r"controllers\.linear_mpc\.horizon: expected an integer"),
        ({"linearize_about": "start"}, r"controllers\.linear_mpc\.linearize_about: unknown value 'start'"),
        ({"casadi_solver": "gurobi"}, r"controllers\.linear_mpc\.casadi_solver: unknown value.*qpoases, osqp"),
        ({"r_diag": [0.1, 0.1]}, r"controllers\.linear_mpc\.r_diag: expected 1 values, got 2"),
        ({"r_diag": [0.0]}, r"controllers\.linear_mpc\.r_diag: .*positive definite"),
        ({"solver_tol": 0.0}, r"controllers\.linear_mpc\.solver_tol: must be positive"),
        ({"admm_rho_scale": 0.0}, r"controllers\.linear_mpc\.admm_rho_scale: must be positive"),
        ({"admm_alpha": 2.0}, r"controllers\.linear_mpc\.admm_alpha: must be in the open interval \(0, 2\), got 2\.0"),
        ({"soft_constraints": True, "slack_l1": 0, "slack_l2": 0}, r"controllers\.linear_mpc\.slack_l1: "),
        ({"solver": "ipm", "soft_constraints": True}, r"controllers\.linear_mpc\.soft_constraints: .*allowed.*admm"),
        ({"ipm_max_iter": 0}, r"controllers\.linear_mpc\.ipm_max_iter: must be a positive integer"),
        ({"ipm_tol": 0.0}, r"controllers\.linear_mpc\.ipm_tol: must be positive"),
        ({"solver": "osqp"}, r"controllers\.linear_mpc\.solver: unknown value 'osqp'.*admm, ipm, qpax, active_set"),
        (
            {"solver": "active_set", "soft_constraints": True},
            r"controllers\.linear_mpc\.soft_constraints: the active_set solver holds hard constraints only",
        ),
        ({"active_set_slots": 0}, r"controllers\.linear_mpc\.active_set_slots: must be a positive integer"),
        ({"active_set_max_steps": 0}, r"controllers\.linear_mpc\.active_set_max_steps: must be a positive integer"),
    ],
)
def test_bad_options_name_the_field(cartpole, options, message):
    env, params, _ = cartpole
    with pytest.raises(ValueError, match=message):
        make_linear_mpc(env, params, options)


def test_the_casadi_variant_names_its_own_config_section(cartpole):
    env, params, _ = cartpole
    with pytest.raises(ValueError, match=r"controllers\.linear_mpc_casadi\.horizon: must be a positive integer"):
        make_linear_mpc_casadi(env, params, {"horizon": 0})
    with pytest.raises(ValueError, match=r"controllers\.linear_mpc_casadi\.r_diag: expected 1 values, got 3"):
        make_linear_mpc_casadi(env, params, {"r_diag": [1.0, 1.0, 1.0]})
