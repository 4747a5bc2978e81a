"""The structured horizon-QP solver (``scg_algorithms.mpc.structured``) against closed forms and qpOASES: the LQR
solution of an unconstrained LQ problem, a hand-solved KKT system with one active input bound, random time-varying
QPs with state and general rows, soft rows, an infeasible problem's status, warm starts, determinism and no
retracing."""

import itertools

import casadi as cs
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg

from scg_algorithms.mpc import structured as S


def _qp(layout, A, B, Q, R, P=None, K=None, u_box=np.inf, x_box=None, C=None, D=None, rows=None, c=None):
    """A ``HorizonQP`` with the same matrices at every stage (``P`` the terminal weight, default ``Q``)."""
    N, nx, nu, m = layout.horizon, layout.nx, layout.nu, layout.num_rows
    rep = lambda a: np.repeat(np.asarray(a, float)[None], N, axis=0)  # noqa: E731
    Qs = rep(Q)
    Qs[-1] = Q if P is None else P
    x_low, x_high = (np.zeros((N, 0)), np.zeros((N, 0))) if x_box is None else (rep(-x_box), rep(x_box))
    return S.HorizonQP(
        A=rep(A),
        B=rep(B),
        c=np.zeros((N, nx)) if c is None else c,
        K=rep(np.zeros((nu, nx)) if K is None else K),
        Q=Qs,
        q=np.zeros((N, nx)),
        R=rep(R),
        r=np.zeros((N, nu)),
        u_low=np.full((N, nu), -u_box),
        u_high=np.full((N, nu), u_box),
        x_low=x_low,
        x_high=x_high,
        C=rep(np.zeros((m, nx)) if C is None else C),
        D=rep(np.zeros((m, nu)) if D is None else D),
        row_low=np.full((N, m), -np.inf),
        row_high=np.zeros((N, m)) if rows is None else rows,
    )


DOUBLE_INTEGRATOR = (np.array([[1.0, 0.1], [0.0, 1.0]]), np.array([[0.005], [0.1]]))
# Jitted once for the module, the layout and settings static: a problem of the same layout and shapes (another
# prestabilisation, other numbers) reuses the compiled solver.
_solve = jax.jit(S.solve, static_argnums=(0, 4))
_solve_prepared = jax.jit(S.solve_prepared, static_argnums=(0, 8))


@pytest.mark.parametrize("prestabilize", [False, True])
def test_an_unconstrained_lq_problem_gives_the_lqr_plan(prestabilize):
    # With the DARE solution as terminal weight the finite-horizon optimum is the LQR law at every stage.
    A, B = DOUBLE_INTEGRATOR
    Q, R = np.diag([1.0, 0.1]), np.array([[0.01]])
    P = scipy.linalg.solve_discrete_are(A, B, Q, R)
    K = np.linalg.solve(R + B.T @ P @ B, B.T @ P @ A)
    layout = S.Layout(horizon=12, nx=2, nu=1)
    qp = _qp(layout, A, B, Q, R, P=P, K=K if prestabilize else None, u_box=1e3)
    x0 = np.array([1.0, -0.5])
    with jax.enable_x64(True):
        for sol in (
            _solve(layout, qp, jnp.asarray(x0)),
            _solve_prepared(layout, S.prepare(layout, qp), x0, qp.c, qp.q, qp.r, tuple(qp[8:12]) + tuple(qp[14:])),
        ):
            assert_lqr_plan(sol, x0, K, layout.horizon)


def assert_lqr_plan(sol, x0, K, horizon):
    """``sol`` converged to the LQR law ``u = -K x`` on the double integrator from ``x0`` at every stage."""
    A, B = DOUBLE_INTEGRATOR
    assert int(sol.status) == S.CONVERGED
    x = x0
    for k in range(horizon):
        np.testing.assert_allclose(sol.u[k], -K @ x, atol=1e-7)
        x = A @ x + B @ np.asarray(sol.u[k])
        np.testing.assert_allclose(sol.x[k + 1], x, atol=1e-9)


def test_one_active_input_bound_matches_the_hand_solved_kkt_system():
    # Horizon 2 on the double integrator from x0 = (1, 0): unconstrained, u = (-1.607, -0.297); with |u| <= 1
    # only u_0 hits its bound. Then v = (u_0, u_1) solves [[H, e_0], [e_0^T, 0]] [v; lam] = [-g; -1] with H, g
    # of the objective written out below: v = (-1, -0.3560), lam = -0.007367 (H v + g + lam e_0 = 0; negative:
    # the lower bound pushes, the solver's sign convention for its multipliers).
    A, B = DOUBLE_INTEGRATOR
    Q, R = np.diag([1.0, 0.1]), np.array([[0.01]])
    x0 = np.array([1.0, 0.0])
    # x_1 = A x0 + B u0, x_2 = A^2 x0 + A B u0 + B u1; J = 1/2 (x1' Q x1 + x2' Q x2 + r u0^2 + r u1^2).
    M1 = np.hstack([B, np.zeros((2, 1))])
    M2 = np.hstack([A @ B, B])
    H = M1.T @ Q @ M1 + M2.T @ Q @ M2 + 0.01 * np.eye(2)
    g = M1.T @ Q @ (A @ x0) + M2.T @ Q @ (A @ A @ x0)
    unconstrained = np.linalg.solve(H, -g)
    assert unconstrained[0] < -1.0 < unconstrained[1]
    kkt = np.block([[H, np.array([[1.0], [0.0]])], [np.array([[1.0, 0.0, 0.0]])]])
    v_lam = np.linalg.solve(kkt, np.concatenate([-g, [-1.0]]))
    np.testing.assert_allclose(v_lam, [-1.0, -0.35600907, -0.00736729], rtol=1e-6)
    layout = S.Layout(horizon=2, nx=2, nu=1)
    qp = _qp(layout, A, B, Q, R, u_box=1.0)
    with jax.enable_x64(True):
        sol = S.solve(layout, qp, jnp.asarray(x0))
    assert int(sol.status) == S.CONVERGED
    np.testing.assert_allclose(sol.u[:, 0], v_lam[:2], atol=1e-9)
    np.testing.assert_allclose(sol.multipliers[0, 0], v_lam[2], rtol=1e-6)
    np.testing.assert_allclose(sol.multipliers[1, 0], 0.0, atol=1e-9)


def _qpoases(layout, qp, x0):
    """qpOASES on the sparse form of ``qp`` (states and inputs as variables): ``(u_0, success)``."""
    N, nx, nu = layout.horizon, layout.nx, layout.nu
    opti = cs.Opti("conic")
    X, U = opti.variable(nx, N + 1), opti.variable(nu, N)
    opti.subject_to(X[:, 0] == x0)
    cost = 0
    for k in range(N):
        opti.subject_to(X[:, k + 1] == qp.A[k] @ X[:, k] + qp.B[k] @ U[:, k] + qp.c[k])
        opti.subject_to(opti.bounded(qp.u_low[k], U[:, k], qp.u_high[k]))
        for j, i in enumerate(layout.x_rows):
            opti.subject_to(opti.bounded(qp.x_low[k, j], X[i, k + 1], qp.x_high[k, j]))
        if layout.num_rows and (np.any(qp.C[k]) or np.any(qp.D[k])):  # zero rows (infinite bounds) left out
            opti.subject_to(qp.C[k] @ X[:, k + 1] + qp.D[k] @ U[:, k] <= qp.row_high[k])
        cost += 0.5 * cs.bilin(qp.Q[k], X[:, k + 1]) + cs.dot(cs.DM(qp.q[k]), X[:, k + 1])
        cost += 0.5 * cs.bilin(qp.R[k], U[:, k]) + cs.dot(cs.DM(qp.r[k]), U[:, k])
    opti.minimize(cost)
    opti.solver("qpoases", {"printLevel": "none", "error_on_fail": False})
    try:
        sol = opti.solve()
    except RuntimeError:  # qpOASES reports infeasibility by failing
        return None, False
    return np.atleast_1d(sol.value(U[:, 0])), True


def _random_time_varying(rng, N, nx, nu, m):
    layout = S.Layout(horizon=N, nx=nx, nu=nu, x_rows=(0,), num_rows=m)
    spd = lambda n: (lambda a: a @ a.T / n + np.eye(n))(rng.normal(size=(n, n)))  # noqa: E731
    qp = S.HorizonQP(
        A=np.eye(nx) + 0.1 * rng.normal(size=(N, nx, nx)),
        B=0.3 * rng.normal(size=(N, nx, nu)),
        c=0.05 * rng.normal(size=(N, nx)),
        K=np.zeros((N, nu, nx)),
        Q=np.stack([spd(nx) for _ in range(N)]),
        q=rng.normal(size=(N, nx)),
        R=np.stack([0.1 * spd(nu) for _ in range(N)]),
        r=0.1 * rng.normal(size=(N, nu)),
        u_low=np.full((N, nu), -1.0),
        u_high=np.full((N, nu), 1.0),
        x_low=np.full((N, 1), -0.5),
        x_high=np.full((N, 1), 0.4),
        C=rng.normal(size=(N, m, nx)),
        D=rng.normal(size=(N, m, nu)),
        row_low=np.full((N, m), -np.inf),
        row_high=np.full((N, m), 2.0),
    )
    return layout, qp


def random_qps_match_qpoases(solve_one):
    """16 random time-varying problems with state and general rows (float64, batched through ``solve_one(layout,
    qp, x0)``) against qpOASES: every problem qpOASES solves converges to its first input within 1e-6, the others
    are not reported converged and violate a row, and the state rows bind in several."""
    rng = np.random.default_rng(0)
    problems = [_random_time_varying(rng, 8, 3, 2, 2) for _ in range(16)]
    layout = problems[0][0]
    x0s = rng.uniform(-0.5, 0.5, (16, 3))
    with jax.enable_x64(True):
        batch = jax.tree.map(lambda *a: jnp.stack(a), *[qp for _, qp in problems])
        sols = jax.jit(jax.vmap(lambda qp, x: solve_one(layout, qp, x)))(batch, jnp.asarray(x0s))
    active = solved = 0
    for i, (_, qp) in enumerate(problems):
        u_ref, success = _qpoases(layout, qp, x0s[i])
        if not success:  # a random problem may be infeasible: then the plan must not pass as a solution
            assert int(sols.status[i]) != S.CONVERGED and float(sols.violation[i]) > 1e-3
            continue
        solved += 1
        assert int(sols.status[i]) == S.CONVERGED
        np.testing.assert_allclose(sols.u[i, 0], u_ref, atol=1e-6)
        plan = np.asarray(sols.x[i, 1:, 0])
        active += int(np.any(np.isclose(plan, 0.4, atol=1e-6) | np.isclose(plan, -0.5, atol=1e-6)))
    assert solved >= 10 and active >= 4  # the state rows bind in several of them


def test_random_time_varying_qps_with_state_and_general_rows_match_qpoases():
    # Every matrix changes along the horizon (as SQP-RTI's linearisations do).
    settings = S.Settings(max_iterations=2000)
    random_qps_match_qpoases(lambda layout, qp, x: S.solve(layout, qp, x, None, settings))


def test_the_condensed_hessian_is_the_sum_of_the_stage_costs_over_the_maps():
    # The cost-to-go recursion against its definition, H = sum_k Ex_k^T Q_k Ex_k + Eu_k^T R_k Eu_k, on a
    # time-varying problem with a pre-stabilising gain (float64).
    rng = np.random.default_rng(3)
    layout, qp = _random_time_varying(rng, 7, 4, 2, 0)
    K = 0.5 * rng.normal(size=(7, 2, 4))
    with jax.enable_x64(True):
        Ex, Eu = S._maps(layout, jnp.asarray(qp.A), jnp.asarray(qp.B), jnp.asarray(K))
        H = np.asarray(S._hessian(qp.A, qp.B, K, qp.Q, qp.R, Ex))
    expected = np.einsum("kxn,kxy,kym->nm", Ex, qp.Q, Ex) + np.einsum("kun,kuv,kvm->nm", Eu, qp.R, Eu)
    np.testing.assert_allclose(H, expected, rtol=1e-12, atol=1e-12 * np.abs(expected).max())


def test_a_fixed_step_size_folds_the_products_and_keeps_the_plans():
    # Fixed step size, p <= 2n rows: one (p, p) product per iteration. Against the same step size unfolded (adaptive,
    # but held by rho_min = rho_max), iteration for iteration (float64, tolerance 0: both run to the cap), and
    # against qpOASES where that solves the problem.
    rng = np.random.default_rng(4)
    problems = [_random_time_varying(rng, 8, 3, 2, 0) for _ in range(8)]
    layout = problems[0][0]
    assert layout.num_dense <= 2 * layout.num_decisions
    x0s = rng.uniform(-0.5, 0.5, (8, 3))
    fixed = S.Settings(max_iterations=600, eps_abs=0.0, eps_rel=0.0, rho=0.3, adaptive_rho=False)
    held = S.Settings(max_iterations=600, eps_abs=0.0, eps_rel=0.0, rho=0.3, rho_min=0.3, rho_max=0.3)
    with jax.enable_x64(True):
        batch = jax.tree.map(lambda *a: jnp.stack(a), *[qp for _, qp in problems])
        run = lambda st: jax.jit(jax.vmap(lambda qp, x: S.solve(layout, qp, x, None, st)))(batch, jnp.asarray(x0s))  # noqa: E731
        folded, unfolded = run(fixed), run(held)
    np.testing.assert_allclose(folded.u, unfolded.u, atol=1e-9)
    np.testing.assert_array_equal(folded.status, unfolded.status)
    solved = 0
    for i, (_, qp) in enumerate(problems):
        u_ref, success = _qpoases(layout, qp, x0s[i])
        if success and int(folded.status[i]) == S.CONVERGED:
            solved += 1
            np.testing.assert_allclose(folded.u[i, 0], u_ref, atol=1e-6)
    assert solved >= 6


def test_an_infeasible_problem_reports_its_status_and_a_finite_plan():
    # x_1 = x_0 + u with |u| <= 1 cannot reach x_1 <= 0 from x_0 = 5.
    layout = S.Layout(horizon=3, nx=1, nu=1, x_rows=(0,))
    qp = _qp(layout, np.eye(1), np.eye(1), np.eye(1), np.eye(1), u_box=1.0)
    qp = qp._replace(x_low=np.full((3, 1), -np.inf), x_high=np.zeros((3, 1)))
    sol = jax.jit(lambda x: S.solve(layout, qp, x))(jnp.array([5.0]))
    assert int(sol.status) == S.INFEASIBLE
    assert S.STATUS_NAMES[int(sol.status)] == "infeasible"
    for leaf in jax.tree.leaves(sol._replace(violation=0.0)):
        assert np.all(np.isfinite(np.asarray(leaf)))
    assert np.all(np.abs(sol.u) <= 1.0)
    assert float(sol.violation) >= 2.0 - 1e-3  # x_1 >= 4 at best, x_3 >= 2: the plan misses the row by >= 2


@pytest.mark.parametrize("slack", ["stage", "shared"])
def test_a_soft_state_row_prices_its_violation(slack):
    # The same problem with the row soft: u = -1 at every stage (each unit of x costs more than it saves),
    # x = (4, 3, 2), and the slacks are the violations (stage) or their worst, 4 (shared).
    layout = S.Layout(horizon=3, nx=1, nu=1, x_rows=(0,), soft_x=(True,), slack=slack, l1=10.0, l2=1.0)
    qp = _qp(layout, np.eye(1), np.eye(1), np.eye(1), np.eye(1), u_box=1.0)
    qp = qp._replace(x_low=np.full((3, 1), -np.inf), x_high=np.zeros((3, 1)))
    with jax.enable_x64(True):
        sol = S.solve(layout, qp, jnp.array([5.0]), None, S.Settings(max_iterations=2000))
    assert int(sol.status) == S.CONVERGED
    np.testing.assert_allclose(sol.u[:, 0], [-1.0, -1.0, -1.0], atol=1e-7)
    np.testing.assert_allclose(sol.x[1:, 0], [4.0, 3.0, 2.0], atol=1e-7)
    expected = [4.0, 3.0, 2.0] if slack == "stage" else [4.0, 4.0, 4.0]
    np.testing.assert_allclose(sol.slack[:, 1], expected, atol=1e-5)  # soft rows keep the ADMM's accuracy


@pytest.fixture(scope="module")
def boxed_lq():
    A, B = DOUBLE_INTEGRATOR
    Q, R = np.diag([1.0, 0.1]), np.array([[0.01]])
    P = scipy.linalg.solve_discrete_are(A, B, Q, R)
    K = np.linalg.solve(R + B.T @ P @ B, B.T @ P @ A)
    layout = S.Layout(horizon=20, nx=2, nu=1, x_rows=(1,))
    qp = _qp(layout, A, B, Q, R, P=P, K=K, u_box=3.0, x_box=np.array([0.6]))
    prepared = S.prepare(layout, qp)
    bounds = tuple(qp[8:12]) + tuple(qp[14:])
    traces = []

    def solve(x, warm):
        traces.append(1)
        return S.solve_prepared(layout, prepared, x, qp.c, qp.q, qp.r, bounds, warm)

    return layout, qp, jax.jit(solve), traces


def test_a_shifted_warm_start_reaches_the_cold_plan_and_the_loop_never_retraces(boxed_lq):
    # A closed loop on the plan's own model from a state that presses both the input and the velocity bound.
    # (Warm starts do not save iterations on this problem: 30-50 either way at the default tolerances.)
    layout, qp, solve, traces = boxed_lq
    x = jnp.array([2.0, 0.0])
    cold = solve(x, None)
    np.testing.assert_allclose(cold.u[:2, 0], [-3.0, -3.0], atol=1e-5)
    np.testing.assert_allclose(cold.x[2:5, 1], [-0.6, -0.6, -0.6], atol=1e-5)
    warm = cold.warm
    for _ in range(5):
        x = jnp.asarray(qp.A[0]) @ x + jnp.asarray(qp.B[0]) @ cold.u[0]
        cold_next = solve(x, S.Warm(*(jnp.zeros_like(a) for a in warm)))
        warm_next = solve(x, S.shift(layout, warm))
        assert int(cold_next.status) == int(warm_next.status) == S.CONVERGED
        np.testing.assert_allclose(warm_next.u, cold_next.u, atol=5e-4)
        cold, warm = warm_next, warm_next.warm
    assert len(traces) == 2  # once without a warm start, once with one; never again


def test_preparing_a_second_family_of_the_same_layout_compiles_nothing(boxed_lq):
    """``prepare``'s float64 maps are one compiled program per layout: another template of the same sizes (a new
    controller or filter) reuses it and gives its own numbers."""
    layout, qp, _, _ = boxed_lq
    S.prepare(layout, qp)
    compiled = S._linear_maps._cache_size()
    other = qp._replace(Q=2.0 * np.asarray(qp.Q), R=2.0 * np.asarray(qp.R))  # the Hessian H doubles
    first, second = S.prepare(layout, qp), S.prepare(layout, other)
    assert S._linear_maps._cache_size() == compiled
    assert float(second.scale) == pytest.approx(2.0 * float(first.scale), rel=1e-12)  # max diag(H)


def test_same_inputs_same_result_and_batched_equals_one_at_a_time(boxed_lq):
    layout, qp, solve, _ = boxed_lq
    xs = jnp.asarray(np.random.default_rng(1).uniform(-2.0, 2.0, (6, 2)), jnp.float32)
    batched = jax.jit(jax.vmap(lambda x: solve(x, None)))
    first, second = batched(xs), batched(xs)
    for a, b in zip(jax.tree.leaves(first), jax.tree.leaves(second), strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    # vmap changes no arithmetic, only the order XLA's vector instructions round in: the plans agree to the solver's
    # float32 resolution (its polish accepts 3e-4 of a row's half-width, here 3 N; measured up to 1.6e-4 N).
    for i in range(xs.shape[0]):
        np.testing.assert_allclose(first.u[i], solve(xs[i], None).u, atol=1e-3)


def test_bad_layouts_and_settings_name_the_field():
    with pytest.raises(ValueError, match=r"Layout\.x_rows"):
        S.Layout(horizon=2, nx=2, nu=1, x_rows=(2,))
    with pytest.raises(ValueError, match=r"Layout\.slack: unknown value 'per_row'; allowed values are stage, shared"):
        S.Layout(horizon=2, nx=2, nu=1, slack="per_row")
    with pytest.raises(ValueError, match=r"Settings\.alpha"):
        S.Settings(alpha=2.0)
    with pytest.raises(ValueError, match=r"Settings\.dual_active_set_steps: must be >= 0"):
        S.Settings(dual_active_set_steps=-1)
    with pytest.raises(ValueError, match=r"Settings\.dual_active_set_steps: must be 0 with polish_soft_rows"):
        S.Settings(dual_active_set_steps=30, polish_soft_rows=True)
    layout = S.Layout(horizon=2, nx=2, nu=1)
    qp = _qp(layout, *DOUBLE_INTEGRATOR, np.eye(2), np.zeros((1, 1)))
    with pytest.raises(ValueError, match=r"template\.R must be positive definite"):
        S.prepare(layout, qp)


def _terminal_row_problem(soft: bool):
    """The double integrator, horizon 20, pre-stabilised by its LQR gain, with |u| <= 3, a velocity box |v| <= 0.4
    (soft at an exact-penalty price of 1,000 per m/s when ``soft``) and one general row at the last stage only,
    position <= 0.2 m (zero rows with infinite bounds at the others, as the MPSC's terminal rows), and a weak cost
    that leaves the cart short of it: the terminal row binds."""
    A, B = DOUBLE_INTEGRATOR
    Q, R = np.diag([0.01, 0.01]), np.array([[1.0]])
    P = scipy.linalg.solve_discrete_are(A, B, Q, R)
    K = np.linalg.solve(R + B.T @ P @ B, B.T @ P @ A)
    layout = S.Layout(
        horizon=20, nx=2, nu=1, x_rows=(1,), num_rows=1, soft_x=(soft,), soft_rows=(False,), l1=1e3 if soft else 0.0
    )
    qp = _qp(layout, A, B, Q, R, P=P, K=K, u_box=3.0, x_box=np.array([0.4]))
    C = np.zeros((20, 1, 2))
    C[-1, 0, 0] = 1.0
    row_high = np.full((20, 1), np.inf)
    row_high[-1] = 0.2
    return layout, qp._replace(C=C, row_high=row_high)


TERMINAL_STARTS = np.array([[0.7, 0.3], [0.6, -0.2], [0.5, 0.4], [0.8, 0.0], [0.45, 0.1], [0.75, -0.35]])


def test_rows_zero_at_every_stage_but_one_are_left_out_of_the_prepared_admm_and_the_plan_is_qpoases():
    layout, qp = _terminal_row_problem(soft=False)
    bounds = tuple(qp[8:12]) + tuple(qp[14:])
    with jax.enable_x64(True):
        settings = S.Settings(max_iterations=4000, eps_abs=1e-10, eps_rel=1e-10)
        prepared = S.prepare(layout, qp, settings)
        # 20 input rows, 20 velocity rows and the terminal row: the 19 zero general rows are left out.
        assert layout.num_dense == 60 and prepared.keep.shape == (41,) and prepared.GT.shape == (41, 20)
        run = jax.vmap(_solve_prepared, in_axes=(None, None, 0, None, None, None, None, None, None))
        sols = run(layout, prepared, jnp.asarray(TERMINAL_STARTS), qp.c, qp.q, qp.r, bounds, None, settings)
        per_copy = jax.vmap(lambda x: _solve(layout, qp, x, None, settings))(jnp.asarray(TERMINAL_STARTS))
    np.testing.assert_array_equal(np.asarray(sols.status), S.CONVERGED)
    for i, x0 in enumerate(TERMINAL_STARTS):
        u_ref, success = _qpoases(layout, qp, x0)
        assert success
        np.testing.assert_allclose(sols.u[i, 0], u_ref, atol=1e-6)
    np.testing.assert_allclose(sols.u, per_copy.u, atol=1e-6)  # the per-copy path holds every row
    np.testing.assert_allclose(np.asarray(sols.x[:, -1, 0]), 0.2, atol=1e-6)  # the terminal row binds in every one
    assert np.all(np.asarray(sols.multipliers)[:, :-1, 2] == 0.0)  # the left-out rows: no force, value 0
    assert np.all(np.asarray(sols.warm.values).reshape(6, 20, 3)[:, :-1, 2] == 0.0)


def test_a_warm_start_read_steps_ahead_is_the_shifted_one_and_its_left_out_entries_are_not_read():
    # warm_steps gathers the held rows of the warm start moved ahead in one step: the same start as shift (each
    # stage's rows from the stage steps later, the last repeated, past the horizon too), so the same plan, bit for
    # bit. 30 iterations without a polish leave the plan where its start put it, so an unused warm start would show.
    layout, qp = _terminal_row_problem(soft=False)
    bounds = tuple(qp[8:12]) + tuple(qp[14:])
    settings = S.Settings(max_iterations=30, check_every=10, polish_rounds=0, dual_active_set_steps=0)
    prepared = S.prepare(layout, qp, settings)
    solve = jax.jit(
        lambda x, warm, steps: _solve_prepared(layout, prepared, x, qp.c, qp.q, qp.r, bounds, warm, settings, steps)
    )
    x0, x1 = jnp.asarray(TERMINAL_STARTS[0], jnp.float32), jnp.asarray(TERMINAL_STARTS[1], jnp.float32)
    previous = solve(x0, None, 0).warm
    cold = solve(x1, None, 0)
    for steps in (0, 1, 3, 25):
        shifted = S.shift(layout, previous, steps)
        stage = np.minimum(np.arange(layout.horizon) + steps, layout.horizon - 1)  # each stage's source, the last kept
        for a, b in zip(shifted[:2], previous[:2], strict=True):
            np.testing.assert_array_equal(np.asarray(a), np.asarray(b).reshape(layout.horizon, -1)[stage].reshape(-1))
        read_ahead, given = solve(x1, previous, steps), solve(x1, shifted, 0)
        for a, b in zip(jax.tree.leaves(read_ahead), jax.tree.leaves(given), strict=True):
            np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
        assert np.abs(np.asarray(read_ahead.u) - np.asarray(cold.u)).max() > 1e-6  # the warm start was used
    # A left-out row's entry (the terminal row's zero copies) is never read: a NaN there changes nothing.
    values = np.asarray(previous.values).copy()
    values[2] = np.nan  # stage 0's general row, zero at every plan
    poisoned = solve(x1, previous._replace(values=jnp.asarray(values)), 1)
    np.testing.assert_array_equal(np.asarray(poisoned.u), np.asarray(solve(x1, previous, 1).u))


def test_a_left_out_row_whose_bounds_exclude_zero_makes_the_problem_infeasible():
    # The terminal row's zero copy at stage 3 given the bound 0 <= -0.5: no plan meets it, though the ADMM never
    # sees the row. The status says so, and the violation is the row's distance from 0.
    layout, qp = _terminal_row_problem(soft=False)
    row_high = np.array(qp.row_high)
    row_high[3] = -0.5
    bounds = tuple(qp[8:12]) + (qp.row_low, row_high)
    with jax.enable_x64(True):
        prepared = S.prepare(layout, qp)
        assert prepared.keep.shape == (41,)
        x0 = jnp.asarray(TERMINAL_STARTS[0])
        sol = _solve_prepared(layout, prepared, x0, qp.c, qp.q, qp.r, bounds, None, S.Settings())
        ok = _solve_prepared(
            layout, prepared, x0, qp.c, qp.q, qp.r, tuple(qp[8:12]) + tuple(qp[14:]), None, S.Settings()
        )
    assert int(sol.status) == S.INFEASIBLE and float(sol.violation) == pytest.approx(0.5)
    assert int(ok.status) == S.CONVERGED and float(ok.violation) < 1e-6


def test_the_polish_of_soft_rows_gives_the_exact_solution_where_no_soft_row_is_violated():
    # The velocity box soft at an exact penalty (1,000 per m/s, far above its multipliers): where a plan holds it,
    # the soft QP's solution is the hard one (qpOASES). 30 ADMM iterations leave the plan 1e-4 N or more off; six
    # polish rounds that hold the soft rows as well reach qpOASES to 1e-8 N, the hard rows alone do not.
    layout, qp = _terminal_row_problem(soft=True)
    bounds = tuple(qp[8:12]) + tuple(qp[14:])
    errors = {}
    with jax.enable_x64(True):
        for polish_soft_rows in (False, True):
            settings = S.Settings(max_iterations=30, polish_rounds=6, polish_soft_rows=polish_soft_rows)
            prepared = S.prepare(layout, qp, settings)
            run = jax.vmap(_solve_prepared, in_axes=(None, None, 0, None, None, None, None, None, None))
            sols = run(layout, prepared, jnp.asarray(TERMINAL_STARTS), qp.c, qp.q, qp.r, bounds, None, settings)
            hard = _terminal_row_problem(soft=False)[1]
            u_ref = np.concatenate([_qpoases(layout, hard, x0)[0] for x0 in TERMINAL_STARTS])
            errors[polish_soft_rows] = np.abs(np.asarray(sols.u[:, 0, 0]) - u_ref).max()
            if polish_soft_rows:
                np.testing.assert_array_equal(np.asarray(sols.status), S.CONVERGED)
                assert np.all(np.asarray(sols.slack) == 0.0)
    assert errors[True] <= 1e-8 and errors[False] >= 1e-4, errors


def _brute_force_qp(H, g, G, lo, hi):
    """The minimiser of 1/2 v'Hv + g'v subject to lo <= Gv <= hi and its multipliers, by trying every active set
    (each row free, at its lower or at its upper bound) and keeping the one that meets the KKT conditions."""
    p = G.shape[0]
    for sides in itertools.product((0, -1, 1), repeat=p):
        sides = np.array(sides)
        held = np.flatnonzero(sides)
        A = G[held]
        K = np.block([[H, A.T], [A, np.zeros((len(held), len(held)))]])
        rhs = np.concatenate([-g, np.where(sides[held] > 0, hi[held], lo[held])])
        try:
            solution = np.linalg.solve(K, rhs)
        except np.linalg.LinAlgError:
            continue
        v, lam = solution[: len(g)], solution[len(g) :]
        rows = G @ v
        if np.all(rows >= lo - 1e-10) and np.all(rows <= hi + 1e-10) and np.all(lam * sides[held] >= -1e-10):
            y = np.zeros(p)
            y[held] = lam
            return v, y
    raise AssertionError("no active set meets the KKT conditions")


def _random_boxed_qp(seed: int, n: int = 4, p: int = 7):
    """``(H, g, G, lo, hi)``: a random strictly convex QP with a box on each of ``n`` variables and ``p - n`` general
    rows, all within [-1, 1], its unconstrained minimiser pushed outside (``g`` large)."""
    rng = np.random.default_rng(seed)
    M = rng.normal(size=(n, n))
    H = M @ M.T + 0.1 * np.eye(n)
    g = 3.0 * rng.normal(size=n)
    G = np.vstack([np.eye(n), rng.normal(size=(p - n, n))])
    return H, g, G, -np.ones(p), np.ones(p)


@pytest.mark.parametrize("seed", [0, 1, 2, 3, 23, 31])
def test_the_dual_active_set_method_finds_the_brute_force_minimiser_from_any_start(seed, monkeypatch):
    # Goldfarb and Idnani's method (the polish's fallback) on random strictly convex QPs with 4 variables and 7 rows
    # (a box on each variable and 3 general rows), pushed against their bounds; more rows than variables, so the set
    # is gathered. Its start is the empty set, a set with wrong-signed rows to drop, or more rows than it can hold.
    # From the empty set, seeds 23 and 31 drop held rows on the way (2 and 3 times: a held multiplier reaches zero
    # before the row taken up meets its bound); seeds 0-3 only add rows.
    H, g, G, lo, hi = _random_boxed_qp(seed)
    n, p = G.shape[1], G.shape[0]
    v_expected, y_expected = _brute_force_qp(H, g, G, lo, hi)
    with jax.enable_x64(True):
        inv_G, inv_g = (jnp.asarray(a) for a in (np.linalg.solve(H, G.T), np.linalg.solve(H, g)))
        ops_data = (jnp.asarray(G), inv_G, inv_g)
        free = S._solve_polish_ops(ops_data).free
        primal_free, s_free = free(jnp.zeros(p))
        starts = {"empty": np.zeros(p), "wrong signs": -np.sign(y_expected), "too many": np.ones(p)}
        for name, start_side in starts.items():
            solve = jax.jit(
                lambda start: S._dual_active_set(
                    S._solve_polish_ops,
                    ops_data,
                    jnp.ones(p, bool),
                    jnp.asarray(lo),
                    jnp.asarray(hi),
                    primal_free,
                    s_free,
                    start,
                    k=n,
                    max_steps=30,
                    tol=1e-12,
                    skip=jnp.asarray(False),
                )  # fmt: skip
            )
            v, rows, y = (np.asarray(a) for a in solve(jnp.asarray(start_side, jnp.int32)))
            np.testing.assert_allclose(v, v_expected, atol=1e-10, err_msg=name)
            np.testing.assert_allclose(y, y_expected, atol=1e-9, err_msg=name)
            np.testing.assert_allclose(rows, G @ v_expected, atol=1e-10, err_msg=name)
            np.testing.assert_allclose(H @ v + g + G.T @ y, 0.0, atol=1e-9, err_msg=name)
        # Vmapped over the starts and a copy that skips it (its result: the minimiser without rows, no forces), in
        # chunks of 2 copies: the three starts' copies run in two chunks and give the minimiser.
        monkeypatch.setattr(S, "DUAL_ACTIVE_SET_CHUNK", 2)
        sides = jnp.asarray([*starts.values(), np.ones(p)], jnp.int32)
        skips = jnp.asarray([False, False, False, True])
        method = lambda side, skip: S._dual_active_set(  # noqa: E731
            S._solve_polish_ops, ops_data, jnp.ones(p, bool), jnp.asarray(lo), jnp.asarray(hi), primal_free, s_free,
            side, k=n, max_steps=30, tol=1e-12, skip=skip,
        )  # fmt: skip
        v, rows, y = (np.asarray(a) for a in jax.jit(jax.vmap(method))(sides, skips))
        np.testing.assert_allclose(v[:3], np.tile(v_expected, (3, 1)), atol=1e-10)
        np.testing.assert_allclose(y[:3], np.tile(y_expected, (3, 1)), atol=1e-9)
        np.testing.assert_array_equal(v[3], np.asarray(primal_free))
        np.testing.assert_array_equal(rows[3], np.asarray(s_free))
        np.testing.assert_array_equal(y[3], 0.0)


DUAL = S.Settings(method="dual_active_set", max_iterations=30)


@pytest.mark.parametrize("seed", [0, 23, 31])
def test_the_dual_active_set_solver_finds_the_brute_force_minimiser(seed, monkeypatch):
    # Settings.method="dual_active_set" on three of the QPs of the test above, in the eigen-coordinates xi = U^T v
    # of H = U diag(lam) U^T that solve_prepared hands it (GT = G U, h = U^T g), from the minimiser without rows.
    # Seeds 23 and 31 drop held rows on the way (seed 0 only adds). With one slot a set of more rows (every seed's
    # minimiser but 23's holds 2-4) outgrows it and the copy is solved again with n = 4 (vmapped below: with 2,
    # then 4); vmapped in chunks of 2 copies after one step over the batch, every copy gives the minimiser, and
    # the same call twice gives the same bits; the plain loops of an accelerator give the same.
    H, g, G, lo, hi = _random_boxed_qp(seed)
    n, p = G.shape[1], G.shape[0]
    v_expected, y_expected = _brute_force_qp(H, g, G, lo, hi)
    assert np.count_nonzero(y_expected) >= (1 if seed == 23 else 2)
    lam, U = np.linalg.eigh(H)
    with jax.enable_x64(True):
        GT, h = jnp.asarray(G @ U), jnp.asarray(U.T @ g)
        data = S._Scaled(lo=jnp.asarray(lo), hi=jnp.asarray(hi), off=jnp.zeros(p), norms=jnp.ones(p), scale=1.0)

        def solve(h, slots):
            settings = S.Settings(method="dual_active_set", max_iterations=30, active_set_slots=slots, polish_tol=1e-12)
            return S._active_set_solve(GT, GT.T, jnp.asarray(lam), h, data, settings)

        for slots in (n, 1):
            result = jax.jit(solve, static_argnums=1)(h, slots)
            assert int(result.status) == S.CONVERGED
            np.testing.assert_allclose(U @ np.asarray(result.primal), v_expected, atol=1e-10)
            np.testing.assert_allclose(np.asarray(result.y), y_expected, atol=1e-9)
            np.testing.assert_allclose(np.asarray(result.s), G @ v_expected, atol=1e-10)
            assert 1 <= int(result.iterations) <= 30
        monkeypatch.setattr(S, "ACTIVE_SET_CHUNK", 2)
        monkeypatch.setattr(S, "ACTIVE_SET_WHOLE_STEPS", 1)
        monkeypatch.setattr(S, "ACTIVE_SET_GROWTH", 2)  # 1, then 2, then 4 slots: every retry
        # Copies: this QP, the same with g = 0 (the minimiser without rows, v = 0, is feasible: no step) and with 2 g.
        hs = jnp.stack([h, 0.0 * h, 2.0 * h, h, h])
        batched = jax.jit(jax.vmap(lambda h: solve(h, 1)))
        first, second = batched(hs), batched(hs)
        for a, b in zip(jax.tree.leaves(first), jax.tree.leaves(second), strict=True):
            np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
        np.testing.assert_array_equal(np.asarray(first.status), S.CONVERGED)
        for i, factor in enumerate([1.0, 0.0, 2.0, 1.0, 1.0]):
            v, y = _brute_force_qp(H, factor * g, G, lo, hi)
            np.testing.assert_allclose(U @ np.asarray(first.primal[i]), v, atol=1e-10)
            np.testing.assert_allclose(np.asarray(first.y[i]), y, atol=1e-9)
        assert int(first.iterations[1]) == 0
        # An accelerator's path (structured._chunk gives None there): plain loops over the batch, the same plans.
        monkeypatch.setattr(S, "_chunk", lambda size: None)
        plain = jax.jit(jax.vmap(lambda h: solve(h, 1)))(hs)
        np.testing.assert_array_equal(np.asarray(plain.status), S.CONVERGED)
        np.testing.assert_allclose(np.asarray(plain.primal), np.asarray(first.primal), atol=1e-12)
        np.testing.assert_array_equal(np.asarray(plain.iterations), np.asarray(first.iterations))


def test_the_dual_active_set_solver_gives_the_lqr_plan_the_hand_solved_kkt_system_and_reports_infeasibility():
    # The closed forms of the ADMM's tests above, prepared and solved by Settings.method="dual_active_set" (float64).
    A, B = DOUBLE_INTEGRATOR
    Q, R = np.diag([1.0, 0.1]), np.array([[0.01]])
    P = scipy.linalg.solve_discrete_are(A, B, Q, R)
    K = np.linalg.solve(R + B.T @ P @ B, B.T @ P @ A)
    bounds = lambda qp: tuple(qp[8:12]) + tuple(qp[14:])  # noqa: E731
    with jax.enable_x64(True):
        # Unconstrained: the LQR law at every stage, with no step (no row is violated at the start).
        layout = S.Layout(horizon=12, nx=2, nu=1)
        qp = _qp(layout, A, B, Q, R, P=P, K=K, u_box=1e3)
        x0 = np.array([1.0, -0.5])
        sol = _solve_prepared(layout, S.prepare(layout, qp, DUAL), x0, qp.c, qp.q, qp.r, bounds(qp), None, DUAL)
        assert_lqr_plan(sol, x0, K, layout.horizon)
        assert int(sol.iterations) == 0
        # One active input bound: u = (-1, -0.35600907), multiplier -0.00736729, in one step.
        layout = S.Layout(horizon=2, nx=2, nu=1)
        qp = _qp(layout, A, B, Q, R, u_box=1.0)
        x0 = np.array([1.0, 0.0])
        sol = _solve_prepared(layout, S.prepare(layout, qp, DUAL), x0, qp.c, qp.q, qp.r, bounds(qp), None, DUAL)
        assert int(sol.status) == S.CONVERGED and int(sol.iterations) == 1
        np.testing.assert_allclose(sol.u[:, 0], [-1.0, -0.35600907], atol=1e-8)
        np.testing.assert_allclose(sol.multipliers[:, 0], [-0.00736729, 0.0], atol=1e-8)
    # Infeasible (float32): x_1 = x_0 + u with |u| <= 1 cannot reach x_1 <= 0 from x_0 = 5.
    layout = S.Layout(horizon=3, nx=1, nu=1, x_rows=(0,))
    qp = _qp(layout, np.eye(1), np.eye(1), np.eye(1), np.eye(1), u_box=1.0)
    qp = qp._replace(x_low=np.full((3, 1), -np.inf), x_high=np.zeros((3, 1)))
    sol = _solve_prepared(layout, S.prepare(layout, qp, DUAL), jnp.array([5.0]), qp.c, qp.q, qp.r, bounds(qp), None,
                          DUAL)  # fmt: skip
    assert int(sol.status) == S.INFEASIBLE
    for leaf in jax.tree.leaves(sol._replace(violation=0.0)):
        assert np.all(np.isfinite(np.asarray(leaf)))
    assert float(sol.violation) >= 2.0 - 1e-3


def test_the_dual_active_set_method_names_what_it_cannot_do():
    with pytest.raises(ValueError, match=r"Settings\.method: unknown value 'osqp'; allowed: admm, dual_active_set"):
        S.Settings(method="osqp")
    with pytest.raises(ValueError, match=r"Settings\.active_set_slots: must be >= 1"):
        S.Settings(method="dual_active_set", active_set_slots=0)
    layout = S.Layout(horizon=3, nx=1, nu=1, x_rows=(0,), soft_x=(True,), l1=10.0)
    qp = _qp(layout, np.eye(1), np.eye(1), np.eye(1), np.eye(1), u_box=1.0, x_box=np.array([1.0]))
    with pytest.raises(ValueError, match=r"Settings\.method: 'dual_active_set' holds hard rows only.*'admm'"):
        S.prepare(layout, qp, DUAL)
    with pytest.raises(ValueError, match=r"Settings\.method: 'dual_active_set' solves prepared families only"):
        S.solve(layout, qp, jnp.array([0.5]), None, DUAL)


def test_a_held_solve_ignores_the_right_hand_side_of_free_rows_even_infinite_ones():
    # Worked by hand: rows 0 and 2 held, S_HH = diag(2, 4), rhs_H = (1, 2) -> x = (0.5, 0, 0.5); row 1 is free and
    # its right-hand side (a free row's infinite bound, as a one-sided general row has) must not reach the solve.
    S_k = jnp.array([[2.0, 1.0, 0.0], [1.0, 3.0, 1.0], [0.0, 1.0, 4.0]])
    held = jnp.array([1.0, 0.0, 1.0])
    rhs = jnp.array([1.0, jnp.inf, 2.0])
    for solve in (S._solve_held, jax.jit(S._solve_held)):  # eagerly (op by op) and compiled
        np.testing.assert_allclose(np.asarray(solve(S_k, held, rhs)), [0.5, 0.0, 0.5], rtol=1e-6)


def test_first_extreme_is_numpys_argmax_and_argmin_with_ties_infinities_and_booleans():
    # Worked by hand: the largest of (1, 3, -inf, 3) is 3, first at 1; the smallest -inf, at 2; of booleans
    # (True, True, False, False) the smallest is False, first at 2; all -inf: 0; all NaN: 0 (argmax would say 0).
    v = jnp.array([1.0, 3.0, -jnp.inf, 3.0])
    assert int(S._first_extreme(v, largest=True)) == 1 and int(S._first_extreme(v, largest=False)) == 2
    assert int(S._first_extreme(jnp.array([True, True, False, False]), largest=False)) == 2
    assert int(S._first_extreme(jnp.full(3, -jnp.inf), largest=True)) == 0
    assert int(S._first_extreme(jnp.full(3, jnp.nan), largest=True)) == 0
    # Against numpy on random rows with many ties and infinities, batched as the dual active-set steps run it.
    rng = np.random.default_rng(0)
    values = rng.integers(-3, 3, (256, 40)).astype(np.float32)
    values[rng.random(values.shape) < 0.2] = -np.inf
    values[rng.random(values.shape) < 0.05] = np.inf
    for largest, oracle in ((True, np.argmax), (False, np.argmin)):
        picked = jax.jit(jax.vmap(lambda v, largest=largest: S._first_extreme(v, largest)))(jnp.asarray(values))
        np.testing.assert_array_equal(np.asarray(picked), oracle(values, axis=1))


def test_rows_first_orders_by_priority_then_index_like_a_stable_sort():
    # Worked by hand: priorities (1, 0, 2, 0, 1) -> the 0s (rows 1, 3), the 1s (0, 4), the 2 (2); the first 4.
    priority = jnp.array([1, 0, 2, 0, 1])
    np.testing.assert_array_equal(np.asarray(S._rows_first(priority, 4, levels=3)), [1, 3, 0, 4])
    # Against a stable sort on random priorities of 83 rows (the cart-pole MPSC's kept rows), batched as the polish
    # runs it.
    rng = np.random.default_rng(0)
    for levels in (2, 3):
        priorities = rng.integers(0, levels, (64, 83))
        picked = jax.jit(jax.vmap(lambda p, levels=levels: S._rows_first(p, 25, levels)))(jnp.asarray(priorities))
        expected = np.argsort(priorities, axis=1, kind="stable")[:, :25]
        np.testing.assert_array_equal(np.asarray(picked), expected)
