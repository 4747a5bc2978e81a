"""2D quadrotor: the Crazyflie restricted to the x-z plane.

Description:
    Two inputs, each the thrust of one motor pair: ``T1`` the front pair and ``T2`` the back pair. Pitch
    ``theta`` is positive when the thrust vector tilts towards +x.

State ``x`` (nx = 6): ``[x, x_dot, z, z_dot, theta, theta_dot]`` in m, m/s, m, m/s, rad, rad/s.

Input ``u`` (nu = 2): ``[T1, T2]`` in N, each in ``[2 motor_thrust_min, 2 motor_thrust_max]``
= [0.0563, 0.2967] N; hover ``m g / 2`` = 0.1323 N each. Normalised action: ``T_i = hover (1 + 0.1 a_i)``.

External force ``f_ext`` (2,): world-frame ``[F_x, F_z]`` on the centre of mass, N.

Episode end: ``|x| > 2`` m, ``z`` outside [-0.05, 2] m, ``|velocity| > 30`` m/s, ``|theta| > 85`` deg,
``|theta_dot| > 500`` deg/s, the optional goal, or the time limit.

Starting state: ``x ~ U(-0.5, 0.5)``, ``z ~ U(0.1, 1.5)``, ``theta ~ U(-0.3, 0.3)``, velocities and rate
``U(-0.01, 0.01)``. Stabilization goal ``x = 0, z = 1``.

Equations (``d = L / sqrt(2)``)::

    x_dd     = (sin(theta) (T1 + T2) + F_x) / m
    z_dd     = (cos(theta) (T1 + T2) + F_z) / m - g
    theta_dd = (T2 - T1) d / Iyy
"""

from __future__ import annotations

import numpy as np

from scg_jax.systems import crazyflie as cf
from scg_jax.systems.base import System, WrenchAllocation

Params = cf.Params
_thrust = cf.ThrustGroups(nu=2, motors_per_input=2)


def dynamics(x, u, params: Params, xp, f_ext=None):
    """Continuous-time 2D quadrotor dynamics.

    Args:
        x: (6,) ``[x, x_dot, z, z_dot, theta, theta_dot]``. u: (2,) ``[T1, T2]`` N.
        params: ``crazyflie.Params``. xp: backend namespace.
        f_ext: optional (2,) ``[F_x, F_z]`` N, world frame; ``None`` means zero.

    Returns:
        x_dot (6,).
    """
    fx, fz = (0.0, 0.0) if f_ext is None else (f_ext[0], f_ext[1])
    theta, theta_dot = x[4], x[5]
    thrust = u[0] + u[1]
    arm = params.arm_length / xp.sqrt(2.0)
    x_dd = (xp.sin(theta) * thrust + fx) / params.mass
    z_dd = (xp.cos(theta) * thrust + fz) / params.mass - params.gravity
    theta_dd = (u[1] - u[0]) * arm / params.iyy
    return xp.stack([x[1], x_dd, x[3], z_dd, theta_dot, theta_dd])


SYSTEM = System(
    name="quadrotor_2d",
    params_cls=Params,
    dynamics=dynamics,
    state_names=("x", "x_dot", "z", "z_dot", "theta", "theta_dot"),
    input_names=("T1", "T2"),
    f_ext_dim=2,
    velocity_mask=np.array([0.0, 1.0, 0.0, 1.0, 0.0, 1.0]),
    state_low=np.array(
        [-cf.POSITION_BOUND, -cf.VELOCITY_BOUND, cf.Z_LOW, -cf.VELOCITY_BOUND, -cf.ANGLE_BOUND, -cf.RATE_BOUND]
    ),
    state_high=np.array(
        [cf.POSITION_BOUND, cf.VELOCITY_BOUND, cf.Z_HIGH, cf.VELOCITY_BOUND, cf.ANGLE_BOUND, cf.RATE_BOUND]
    ),
    init_low=np.array([-0.5, -0.01, 0.1, -0.01, -0.3, -0.01]),
    init_high=np.array([0.5, 0.01, 1.5, 0.01, 0.3, 0.01]),
    goal=np.array([0.0, 0.0, 1.0, 0.0, 0.0, 0.0]),
    tracking_axes=((0, 0, 1), (2, 2, 3)),
    default_plane="xz",
    default_offset=(0.0, 1.0),
    default_scale=0.5,
    q_diag=np.array([1.0, 0.1, 1.0, 0.1, 0.1, 0.1]),
    r_diag=np.array([0.1, 0.1]),
    mse_weight=np.array([1.0, 0.0, 1.0, 0.0, 0.0, 0.0]),
    **_thrust.system_fields("quadrotor_2d"),
    inertial_fields=("mass", "iyy"),
    # z_dd is x_dot[3], theta_dd (pitch) x_dot[5].
    wrench_allocation=WrenchAllocation(
        vertical_acceleration=3, angular_accelerations=(5,), inertia_fields=("iyy",), torque_axes=(1,)
    ),
)
