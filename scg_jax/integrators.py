"""Fixed-step integrators written with arithmetic only, so they work on JAX arrays and CasADi symbols alike.

Each integrator advances ``x_next = step(f, x, dt)`` for an autonomous right-hand side ``f(x) -> x_dot``
(the input and external force are held constant over the step by the caller's closure).

- ``euler``: explicit Euler, first order.
- ``semi_implicit_euler``: symplectic Euler, first order. Velocity-like entries (``velocity_mask == 1``) are
  advanced first; the remaining (position-like) entries then use the derivative evaluated at the state with the
  updated velocities, the scheme physics engines use.
- ``rk4``: classical fourth-order Runge-Kutta.
"""

from __future__ import annotations

INTEGRATORS = ("euler", "semi_implicit_euler", "rk4")


def euler(f, x, dt, velocity_mask=None):
    return x + dt * f(x)


def semi_implicit_euler(f, x, dt, velocity_mask):
    x_vel = x + dt * f(x) * velocity_mask
    return x_vel + dt * f(x_vel) * (1.0 - velocity_mask)


def rk4(f, x, dt, velocity_mask=None):
    k1 = f(x)
    k2 = f(x + 0.5 * dt * k1)
    k3 = f(x + 0.5 * dt * k2)
    k4 = f(x + dt * k3)
    return x + dt / 6.0 * (k1 + 2.0 * k2 + 2.0 * k3 + k4)


def get_integrator(name: str):
    """Return the integrator called ``name``; raise a ValueError naming the allowed values otherwise."""
    table = {"euler": euler, "semi_implicit_euler": semi_implicit_euler, "rk4": rk4}
    if name not in table:
        raise ValueError(f"integrator: unknown value {name!r}; allowed values are {', '.join(INTEGRATORS)}")
    return table[name]


def make_discrete_dynamics(dynamics, integrator: str, dt: float, substeps: int, velocity_mask):
    """Discretise ``dynamics`` over one control period with ``substeps`` steps of ``integrator``.

    The input ``u`` and the external force ``f_ext`` are held constant over the period (zero-order hold).

    Args:
        dynamics: a system's ``dynamics(x, u, params, xp, f_ext=None)``.
        integrator: one of ``INTEGRATORS``.
        dt: control period (s); each substep is ``dt / substeps``.
        substeps: number of physics steps per control step (>= 1).
        velocity_mask: (nx,) numpy array, used by ``semi_implicit_euler``.

    Returns:
        ``step(x, u, params, xp, f_ext=None) -> x_next``, valid for both backends.
    """
    step_fn = get_integrator(integrator)
    h = dt / substeps

    def step(x, u, params, xp, f_ext=None):
        mask = xp.constant(velocity_mask)

        def f(state):
            return dynamics(state, u, params, xp, f_ext)

        return xp.repeat(substeps, lambda state: step_fn(f, state, h, mask), x)

    return step
