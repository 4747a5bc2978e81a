"""Integrators: convergence order against a fine reference solution, and backend agreement."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from scg_jax.backends import jax_backend
from scg_jax.integrators import INTEGRATORS, get_integrator, make_discrete_dynamics
from scg_jax.systems import cartpole

X0 = np.array([0.1, 0.5, 0.3, -0.2])
U = np.array([1.5])
HORIZON = 0.5  # s


def _integrate(name: str, steps: int):
    step = make_discrete_dynamics(cartpole.dynamics, name, HORIZON, steps, cartpole.SYSTEM.velocity_mask)
    return np.asarray(step(jnp.asarray(X0), jnp.asarray(U), cartpole.Params(), jax_backend))


@pytest.mark.parametrize(("name", "order"), [("euler", 1), ("semi_implicit_euler", 1), ("rk4", 4)])
def test_convergence_order(name, order):
    with jax.enable_x64(True):
        reference = _integrate("rk4", 8192)
        steps = [16, 32, 64, 128]
        errors = [np.linalg.norm(_integrate(name, n) - reference) for n in steps]
    slopes = np.log2(np.array(errors[:-1]) / np.array(errors[1:]))
    assert np.all(np.abs(slopes - order) < 0.15), (name, errors, slopes)


def test_semi_implicit_euler_updates_velocities_first():
    """On the harmonic oscillator x_dd = -x, symplectic Euler is q' = q + h (v - h q), v' = v - h q."""
    mask = jnp.array([0.0, 1.0])
    f = lambda x: jnp.stack([x[1], -x[0]])  # noqa: E731
    h, x = 0.1, jnp.array([1.0, 0.5])
    x_new = get_integrator("semi_implicit_euler")(f, x, h, mask)
    v_new = 0.5 - h * 1.0
    np.testing.assert_allclose(np.asarray(x_new), [1.0 + h * v_new, v_new], rtol=1e-6)


def test_unknown_integrator_names_allowed_values():
    with pytest.raises(
        ValueError, match="integrator: unknown value 'midpoint'; allowed values are " + ", ".join(INTEGRATORS)
    ):
        get_integrator("midpoint")
