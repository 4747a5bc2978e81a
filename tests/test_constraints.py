"""Constraints: each form against a hand computation and its CasADi form; sign convention; env signals."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import scg_jax
from scg_jax import constraints as C
from scg_jax.backends import jax_backend

X = np.array([0.3, -1.0, 1.2, 0.5, 0.1, -2.0])  # quadrotor_2d: x, x_dot, z, z_dot, theta, theta_dot
U = np.array([0.1, 0.25])

FORMS = [
    # (option, hand-computed rows)
    (
        {"type": "bounded", "on": "state", "active_dims": [0, 2], "low": [-1, 0.5], "high": [1, 1.0]},
        [0.3 - 1, 1.2 - 1.0, -1 - 0.3, 0.5 - 1.2],
    ),
    ({"type": "abs_bound", "on": "input", "bound": 0.2}, [0.1 - 0.2, 0.25 - 0.2, -0.2 - 0.1, -0.2 - 0.25]),
    (
        {
            "type": "linear",
            "on": "input_and_state",
            "active_dims": [0, 6, 7],
            "A": [[1, 2, 0], [0, 1, -1]],
            "b": [0.4, 0.0],
        },
        [0.3 + 0.2 - 0.4, 0.1 - 0.25],
    ),
    (
        {"type": "quadratic", "on": "state", "active_dims": [0, 2], "P": [[2, 0], [0, 1]], "b": 1.5},
        [2 * 0.09 + 1.44 - 1.5],
    ),
    ({"type": "default", "on": "input"}, [0.1 - 0.29668, 0.25 - 0.29668, 0.05632 - 0.1, 0.05632 - 0.25]),
]


@pytest.mark.parametrize(("option", "expected"), FORMS, ids=[f[0]["type"] for f in FORMS])
def test_each_form_against_hand_computation_and_casadi(option, expected):
    env = scg_jax.make("quadrotor_2d", constraints=[option])
    params = env.default_params
    with jax.enable_x64(True):
        params64 = env.default_params
        values = C.evaluate_all(env.constraint_specs, params64.constraints, jnp.asarray(X), jnp.asarray(U), jax_backend)
    np.testing.assert_allclose(np.asarray(values), expected, rtol=1e-9, atol=1e-12)
    model = env.symbolic_model(params)
    np.testing.assert_allclose(np.asarray(model.g(X, U)).ravel(), expected, rtol=1e-6, atol=1e-7)
    np.testing.assert_allclose(np.asarray(model.constraints[0](X, U)).ravel(), expected, rtol=1e-6, atol=1e-7)


def test_default_state_constraint_drops_infinite_bounds():
    env = scg_jax.make("cartpole", constraints=[{"type": "default", "on": "state"}])
    spec = env.constraint_specs[0]
    assert spec.num_rows == 4  # x and theta only: the velocities are unbounded
    values = C.evaluate_all(
        env.constraint_specs, env.default_params.constraints, jnp.zeros(4), jnp.zeros(1), jax_backend
    )
    np.testing.assert_allclose(np.asarray(values), [-2.4, -np.pi / 2, -2.4, -np.pi / 2], rtol=1e-6)


def test_a_state_violating_exactly_one_row_shows_exactly_that_row_positive():
    option = {"type": "bounded", "on": "state", "low": [-1, -5, 0, -5, -0.5, -5], "high": [1, 5, 2, 5, 0.5, 5]}
    env = scg_jax.make("quadrotor_2d", constraints=[option])
    x = np.array([0.0, 0.0, 1.0, 0.0, 0.7, 0.0])  # theta above its high bound of 0.5, nothing else
    values = np.asarray(
        C.evaluate_all(
            env.constraint_specs, env.default_params.constraints, jnp.asarray(x), jnp.asarray(U), jax_backend
        )
    )
    positive = np.flatnonzero(values > 0)
    np.testing.assert_array_equal(positive, [4])  # row 4 is theta - high
    np.testing.assert_allclose(values[4], 0.2, rtol=1e-6)


def test_strict_and_tolerance_decide_what_counts_as_violated():
    base = {"type": "abs_bound", "on": "input", "bound": 0.2}
    values = jnp.array([0.0, 0.05, -0.4, -0.45])  # first row exactly on the boundary
    for strict, tolerance, expected in [
        (False, 0.0, [0, 1, 0, 0]),
        (True, 0.0, [1, 1, 0, 0]),
        (False, 0.1, [0, 0, 0, 0]),
    ]:
        env = scg_jax.make("quadrotor_2d", constraints=[{**base, "strict": strict, "tolerance": tolerance}])
        mask = C.violated(env.constraint_specs, env.default_params.constraints, values)
        np.testing.assert_array_equal(np.asarray(mask), expected)


def test_env_reports_values_cost_penalty_and_termination():
    option = {"type": "abs_bound", "on": "input", "bound": 3.0}
    env = scg_jax.make("cartpole", constraints=[option], violation_penalty=2.0, done_on_violation=True)
    free = scg_jax.make("cartpole")
    params, free_params = env.default_params, free.default_params
    _, state = env.reset(jax.random.key(0), params)
    ok = env.step(state, jnp.array([1.0]), params)
    assert float(ok.cost) == 0.0 and not bool(ok.terminated)
    np.testing.assert_allclose(np.asarray(ok.info["constraint_values"]), [1.0 - 3.0, -3.0 - 1.0])
    bad = env.step(state, jnp.array([4.0]), params)
    reference = free.step(free.reset(jax.random.key(0), free_params)[1], jnp.array([4.0]), free_params)
    assert float(bad.cost) == 1.0 and bool(bad.info["constraint_violation"]) and bool(bad.terminated)
    np.testing.assert_allclose(float(bad.reward), float(reference.reward) - 2.0, rtol=1e-6)
    np.testing.assert_allclose(np.asarray(bad.info["constraint_values"]), [1.0, -7.0])


def test_a_sweep_over_constraint_tightness_is_a_vmap():
    env = scg_jax.make("cartpole", constraints=[{"type": "abs_bound", "on": "input", "bound": 3.0}])
    params = env.default_params
    _, state = env.reset(jax.random.key(0), params)
    bounds = jnp.array([1.0, 2.0, 3.0, 4.0, 5.0])
    sweep = jax.vmap(lambda b: params.replace(constraints=(params.constraints[0].replace(b=jnp.array([b, b])),)))(
        bounds
    )
    out = jax.vmap(env.step, in_axes=(None, None, 0))(state, jnp.array([2.5]), sweep)
    np.testing.assert_array_equal(np.asarray(out.cost), [1, 1, 0, 0, 0])


@pytest.mark.parametrize(
    ("option", "message"),
    [
        ({"type": "box"}, r"constraints\[0\].type: unknown value 'box'; allowed values are bounded, abs_bound"),
        ({"type": "bounded", "on": "output"}, r"constraints\[0\].on: unknown value 'output'; allowed values are"),
        (
            {"type": "bounded", "low": [0, 0], "high": [1, 1]},
            r"constraints\[0\].low: expected 6 values, got 2: \[0.0, 0.0\]$",
        ),
        (
            {"type": "linear", "on": "input", "A": [[1, 0, 0]], "b": [1]},
            r"constraints\[0\].A: expected a matrix of shape \(rows, 2\), got shape \(1, 3\)$",
        ),
        ({"type": "abs_bound", "bound": 1, "active_dims": [7]}, r"constraints\[0\].active_dims: expected"),
        (
            {"type": "quadratic", "on": "input", "P": [[1, 0], [0, 1]], "b": 1, "rows": 2},
            r"constraints\[0\].rows: unknown key for a quadratic constraint; allowed keys are type, on, active_dims, "
            r"strict, tolerance, P, b$",
        ),
    ],
)
def test_bad_constraints_name_the_field(option, message):
    with pytest.raises(ValueError, match=message):
        scg_jax.make("quadrotor_2d", constraints=[option])


@pytest.mark.parametrize(
    ("option", "message"),
    [
        ({"type": "quadratic", "P": np.eye(6).tolist()}, r"constraints\[0\].b: required for a quadratic constraint"),
        ({"type": "abs_bound"}, r"constraints\[0\].bound: required for a abs_bound constraint"),
        (
            {"type": "abs_bound", "bound": [1.0, 2.0]},
            r"constraints\[0\].bound: expected a number or 6 values, got 2: \[1.0, 2.0\]$",
        ),
        ({"type": "linear", "A": "wide", "b": [1]}, r"constraints\[0\].A"),
    ],
)
def test_missing_or_malformed_constraint_values_name_the_field(option, message):
    with pytest.raises(ValueError, match=message):
        scg_jax.make("quadrotor_2d", constraints=[option])


def _random_constraints(rng, system) -> list[dict]:
    """One constraint of every type on every variable, with random active dims and random finite parameters (a
    default constraint on dims that have a finite bound, as one with none has no row)."""
    nx, nu = system.nx, system.nu
    bounded = np.concatenate([np.isfinite(system.state_high), np.ones(nu, bool)])
    options = []
    for on, size in (("state", nx), ("input", nu), ("input_and_state", nx + nu)):
        for kind in C.CONSTRAINT_TYPES:
            offset = nx if on == "input" else 0
            candidates = [i for i in range(size) if kind != "default" or bounded[offset + i]]
            d = int(rng.integers(1, len(candidates) + 1))
            dims = sorted(rng.choice(candidates, d, replace=False).tolist())
            option = {"type": kind, "on": on, "active_dims": dims, "tolerance": float(rng.uniform(0, 0.1))}
            if kind == "bounded":
                low = rng.uniform(-2, 0, d)
                option.update(low=low.tolist(), high=(low + rng.uniform(0.1, 3, d)).tolist())
            elif kind == "abs_bound":
                option["bound"] = rng.uniform(0.1, 3, d).tolist()
            elif kind == "linear":
                rows = int(rng.integers(1, 4))
                option.update(A=rng.normal(size=(rows, d)).tolist(), b=rng.normal(size=rows).tolist())
            elif kind == "quadratic":
                M = rng.normal(size=(d, d))
                option.update(P=(M @ M.T).tolist(), b=float(rng.uniform(0.1, 2)))
            options.append(option)
    return options


@pytest.mark.parametrize("system", tuple(scg_jax.SYSTEMS))
@pytest.mark.parametrize("seed", [0, 1])
def test_jax_and_casadi_constraints_agree_at_random_points_and_random_parameters(system, seed):
    """Every type on every variable, random active dims and parameters (set at make, then redrawn in EnvParams so
    the CasADi model is shown to read the params it is given), at 25 random (x, u): equal to 1e-9 in float64."""
    rng = np.random.default_rng(seed)
    probe = scg_jax.make(system)
    nx, nu = probe.nx, probe.nu
    env = scg_jax.make(system, constraints=_random_constraints(rng, probe.system))
    with jax.enable_x64(True):
        params = env.default_params
        redrawn = []
        for spec, values in zip(env.constraint_specs, params.constraints, strict=True):
            leaves = {name: getattr(values, name) for name in ("b", "tolerance")}
            if spec.form == "quadratic":
                M = rng.normal(size=values.P.shape)
                leaves["P"] = jnp.asarray(M @ M.T)
                leaves["b"] = jnp.asarray(rng.uniform(0.1, 2))
            else:
                leaves["A"] = jnp.asarray(rng.normal(size=values.A.shape))
                leaves["b"] = jnp.asarray(rng.normal(size=values.b.shape))
            redrawn.append(values.replace(**leaves))
        params = params.replace(constraints=tuple(redrawn))
        assert all(leaf.dtype == jnp.float64 for leaf in jax.tree.leaves(params.constraints))
        model = env.symbolic_model(params)
        evaluate = jax.jit(lambda x, u: C.evaluate_all(env.constraint_specs, params.constraints, x, u, jax_backend))
        rows = [spec.num_rows for spec in env.constraint_specs]
        assert sum(rows) > len(C.CONSTRAINT_TYPES) * 3  # every constraint contributed rows
        for _ in range(25):
            x = rng.normal(scale=2.0, size=nx)
            u = rng.normal(scale=2.0, size=nu)
            values = np.asarray(evaluate(jnp.asarray(x), jnp.asarray(u)))
            symbolic = np.asarray(model.g(x, u), dtype=np.float64).ravel()
            np.testing.assert_allclose(symbolic, values, rtol=1e-9, atol=1e-12)
            per_constraint = np.concatenate([np.asarray(g(x, u)).ravel() for g in model.constraints])
            np.testing.assert_allclose(per_constraint, values, rtol=1e-9, atol=1e-12)
