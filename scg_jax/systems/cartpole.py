"""Cart-pole: a pole hinged on a cart that moves along a frictionless track.

Description:
    A cart of mass ``m_c`` moves along a horizontal track; a uniform thin pole of mass ``m_p`` and length
    ``2 l`` is hinged at its lower end on the cart. A horizontal force ``F`` pushes the cart. The equations are
    the frictionless ones of Florian (2007) with the thin-rod inertia factor 4/3, as in the safe-control-gym
    paper, extended with an external force ``(F_x, F_z)`` acting on the pole's centre of mass.

State ``x`` (nx = 4):
    ====  ==========  ==========================================  =========
    idx   name        meaning                                     unit
    ====  ==========  ==========================================  =========
    0     x           cart position (positive to the right)       m
    1     x_dot       cart velocity                               m/s
    2     theta       pole angle from upright, positive leaning    rad
                      towards +x (clockwise in the x-z plane)
    3     theta_dot   pole angular velocity                       rad/s
    ====  ==========  ==========================================  =========

Input ``u`` (nu = 1): force ``F`` on the cart along +x, in ``[-force_max, force_max]`` N (10 N by default).
Normalised action ``a`` in [-1, 1]: ``F = force_max * a``.

External force ``f_ext`` (2,): ``(F_x, F_z)`` in N on the pole's centre of mass, world frame (z up).

Episode end: ``|x| > 2.4`` m or ``|theta| > pi/2`` (out of bounds), the optional goal, or the time limit.

Starting state: each entry ``U(-0.05, 0.05)`` unless randomised otherwise.

Equations (M = m_c + m_p, F' = F + F_x)::

    theta_dd = (g sin(th) - cos(th) (F' + m_p l th_d^2 sin(th)) / M + (F_x cos(th) - F_z sin(th)) / m_p)
               / (l (4/3 - m_p cos^2(th) / M))
    x_dd     = (F' + m_p l (th_d^2 sin(th) - theta_dd cos(th))) / M

With ``f_ext = 0`` these are exactly Florian's equations; the external-force terms follow from the Lagrangian
with the generalised forces ``Q_x = F_x`` and ``Q_theta = l (F_x cos(th) - F_z sin(th))``.
"""

from __future__ import annotations

import numpy as np

from scg_jax._pytree import pytree_dataclass
from scg_jax.systems.base import System, require_positive


@pytree_dataclass
class Params:
    """Physical parameters of the cart-pole (primitive quantities only).

    Attributes:
        cart_mass: m_c, kg.
        pole_mass: m_p, kg.
        pole_half_length: l, m; the distance from the hinge to the pole's centre of mass (the pole is 2 l long).
        gravity: g, m/s^2.
        force_max: actuator limit on |F|, N.
    """

    cart_mass: float = 1.0
    pole_mass: float = 0.1
    pole_half_length: float = 0.5
    gravity: float = 9.8
    force_max: float = 10.0


def dynamics(x, u, params: Params, xp, f_ext=None):
    """Continuous-time cart-pole dynamics ``x_dot = f(x, u)``.

    Args:
        x: state (4,) ``[x, x_dot, theta, theta_dot]`` (m, m/s, rad, rad/s).
        u: input (1,) ``[F]`` in N.
        params: ``Params``.
        xp: backend namespace (``scg_jax.backends.jax_backend`` or ``casadi_backend``).
        f_ext: optional (2,) ``[F_x, F_z]`` in N on the pole's centre of mass; ``None`` means zero.

    Returns:
        x_dot (4,) in the backend's array type.
    """
    x_dot, theta, theta_dot = x[1], x[2], x[3]
    fx, fz = (0.0, 0.0) if f_ext is None else (f_ext[0], f_ext[1])
    m_c, m_p, l, g = params.cart_mass, params.pole_mass, params.pole_half_length, params.gravity
    total_mass = m_c + m_p
    sin_t, cos_t = xp.sin(theta), xp.cos(theta)
    force = u[0] + fx
    theta_dd = (
        g * sin_t - cos_t * (force + m_p * l * theta_dot**2 * sin_t) / total_mass + (fx * cos_t - fz * sin_t) / m_p
    ) / (l * (4.0 / 3.0 - m_p * cos_t**2 / total_mass))
    x_dd = (force + m_p * l * (theta_dot**2 * sin_t - theta_dd * cos_t)) / total_mass
    return xp.stack([x_dot, x_dd, theta_dot, theta_dd])


def input_bounds(params: Params):
    return -params.force_max * np.ones(1), params.force_max * np.ones(1)


def equilibrium_input(params: Params):
    return np.zeros(1)


def action_to_input(action, params: Params):
    return params.force_max * action


def input_to_action(u, params: Params):
    return u / params.force_max


def validate_params(params: Params) -> None:
    require_positive(params, ("cart_mass", "pole_mass", "pole_half_length", "gravity", "force_max"), "cartpole")


SYSTEM = System(
    name="cartpole",
    params_cls=Params,
    dynamics=dynamics,
    state_names=("x", "x_dot", "theta", "theta_dot"),
    input_names=("F",),
    f_ext_dim=2,
    velocity_mask=np.array([0.0, 1.0, 0.0, 1.0]),
    state_low=np.array([-2.4, -np.inf, -np.pi / 2, -np.inf]),
    state_high=np.array([2.4, np.inf, np.pi / 2, np.inf]),
    init_low=np.full(4, -0.05),
    init_high=np.full(4, 0.05),
    goal=np.zeros(4),
    tracking_axes=((0, 0, 1),),
    default_plane="xz",
    default_offset=(0.0, 0.0),
    default_scale=1.0,
    q_diag=np.ones(4),
    r_diag=np.full(1, 0.1),
    mse_weight=np.ones(4),
    input_bounds=input_bounds,
    equilibrium_input=equilibrium_input,
    action_to_input=action_to_input,
    input_to_action=input_to_action,
    gymnasium_id="scg_jax/CartPole-v0",
    view="cartpole",
    validate_params=validate_params,
    inertial_fields=("cart_mass", "pole_mass", "pole_half_length"),
    wrench_allocation=None,
)
