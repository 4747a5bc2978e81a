"""3D quadrotor: the full rigid-body Crazyflie in an X configuration.

Description:
    World frame x, y, z with z up; body frame x forward, y left, z along the thrust. Attitude is ZYX Euler
    angles (roll ``phi``, pitch ``theta``, yaw ``psi``), so ``R = Rz(psi) Ry(theta) Rx(phi)`` maps body to
    world; ``p, q, r`` are body angular rates. Motors, each at distance ``L`` from the centre of mass:
    1 front-left ``(+d, +d)``, 2 back-left ``(-d, +d)``, 3 back-right ``(-d, -d)``, 4 front-right ``(+d, -d)``
    with ``d = L / sqrt(2)``; motors 1 and 3 spin one way, 2 and 4 the other, so the yaw moment is
    ``(km / kf) (-f1 + f2 - f3 + f4)``. With ``phi = psi = 0`` the pitch dynamics reduce exactly to the 2D
    model with ``T1 = f1 + f4`` (front pair) and ``T2 = f2 + f3`` (back pair).

State ``x`` (nx = 12): ``[x, x_dot, y, y_dot, z, z_dot, phi, theta, psi, p, q, r]`` in m, m/s, rad, rad/s.

Input ``u`` (nu = 4): motor thrusts ``[f1, f2, f3, f4]`` in N, each in
``[motor_thrust_min, motor_thrust_max]`` = [0.02816, 0.14834] N; hover ``m g / 4`` = 0.06615 N.
Normalised action: ``f_i = hover (1 + 0.1 a_i)``.

External force ``f_ext`` (3,): world-frame ``[F_x, F_y, F_z]`` on the centre of mass, N.

Episode end: ``|x|, |y| > 2`` m, ``z`` outside [-0.05, 2] m, ``|velocity| > 30`` m/s, ``|phi|, |theta| > 85``
deg, ``|p|, |q|, |r| > 500`` deg/s (yaw is unbounded), the optional goal, or the time limit.

Starting state: ``x, y ~ U(-0.5, 0.5)``, ``z ~ U(0.1, 1.5)``, angles ``U(-0.3, 0.3)``, velocities and rates
``U(-0.01, 0.01)``. Stabilization goal ``z = 1``, everything else zero.

Equations (``T = f1 + f2 + f3 + f4``, ``J = diag(Ixx, Iyy, Izz)``, ``w = [p, q, r]``)::

    [x_dd, y_dd, z_dd] = (R [0, 0, T] + f_ext) / m - [0, 0, g]
    J w_dot = M - w x (J w),   M = [d (f1 + f2 - f3 - f4), d (-f1 + f2 + f3 - f4), (km/kf)(-f1 + f2 - f3 + f4)]
    [phi_d, theta_d, psi_d] = [p + (q sin(phi) + r cos(phi)) tan(theta),
                               q cos(phi) - r sin(phi),
                               (q sin(phi) + r cos(phi)) / cos(theta)]
"""

from __future__ import annotations

import numpy as np

from scg_jax.systems import crazyflie as cf
from scg_jax.systems.base import System, WrenchAllocation

Params = cf.Params
_thrust = cf.ThrustGroups(nu=4, motors_per_input=1)


def dynamics(x, u, params: Params, xp, f_ext=None):
    """Continuous-time 3D quadrotor dynamics.

    Args:
        x: (12,) ``[x, x_dot, y, y_dot, z, z_dot, phi, theta, psi, p, q, r]``.
        u: (4,) motor thrusts ``[f1, f2, f3, f4]`` N.
        params: ``crazyflie.Params``. xp: backend namespace.
        f_ext: optional (3,) world-frame force ``[F_x, F_y, F_z]`` N; ``None`` means zero.

    Returns:
        x_dot (12,).
    """
    fx, fy, fz = (0.0, 0.0, 0.0) if f_ext is None else (f_ext[0], f_ext[1], f_ext[2])
    phi, theta, psi = x[6], x[7], x[8]
    p, q, r = x[9], x[10], x[11]
    f1, f2, f3, f4 = u[0], u[1], u[2], u[3]
    m, g = params.mass, params.gravity
    ixx, iyy, izz = params.ixx, params.iyy, params.izz
    arm = params.arm_length / xp.sqrt(2.0)
    yaw_per_thrust = params.km / params.kf

    s_phi, c_phi = xp.sin(phi), xp.cos(phi)
    s_theta, c_theta = xp.sin(theta), xp.cos(theta)
    s_psi, c_psi = xp.sin(psi), xp.cos(psi)
    thrust = f1 + f2 + f3 + f4
    # Third column of R = Rz(psi) Ry(theta) Rx(phi): the body z axis in the world frame.
    x_dd = (thrust * (c_psi * s_theta * c_phi + s_psi * s_phi) + fx) / m
    y_dd = (thrust * (s_psi * s_theta * c_phi - c_psi * s_phi) + fy) / m
    z_dd = (thrust * c_theta * c_phi + fz) / m - g

    moment_x = arm * (f1 + f2 - f3 - f4)
    moment_y = arm * (-f1 + f2 + f3 - f4)
    moment_z = yaw_per_thrust * (-f1 + f2 - f3 + f4)
    p_dot = (moment_x - (izz - iyy) * q * r) / ixx
    q_dot = (moment_y - (ixx - izz) * r * p) / iyy
    r_dot = (moment_z - (iyy - ixx) * p * q) / izz

    rate_term = q * s_phi + r * c_phi
    phi_dot = p + rate_term * xp.tan(theta)
    theta_dot = q * c_phi - r * s_phi
    psi_dot = rate_term / c_theta
    return xp.stack([x[1], x_dd, x[3], y_dd, x[5], z_dd, phi_dot, theta_dot, psi_dot, p_dot, q_dot, r_dot])


_STATE_HIGH = np.array(
    [
        cf.POSITION_BOUND,
        cf.VELOCITY_BOUND,
        cf.POSITION_BOUND,
        cf.VELOCITY_BOUND,
        cf.Z_HIGH,
        cf.VELOCITY_BOUND,
        cf.ANGLE_BOUND,
        cf.ANGLE_BOUND,
        np.inf,
        cf.RATE_BOUND,
        cf.RATE_BOUND,
        cf.RATE_BOUND,
    ]
)
_STATE_LOW = -_STATE_HIGH
_STATE_LOW[4] = cf.Z_LOW

SYSTEM = System(
    name="quadrotor_3d",
    params_cls=Params,
    dynamics=dynamics,
    state_names=("x", "x_dot", "y", "y_dot", "z", "z_dot", "phi", "theta", "psi", "p", "q", "r"),
    input_names=("f1", "f2", "f3", "f4"),
    f_ext_dim=3,
    velocity_mask=np.array([0.0, 1.0, 0.0, 1.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 1.0, 1.0]),
    state_low=_STATE_LOW,
    state_high=_STATE_HIGH,
    init_low=np.array([-0.5, -0.01, -0.5, -0.01, 0.1, -0.01, -0.3, -0.3, -0.3, -0.01, -0.01, -0.01]),
    init_high=np.array([0.5, 0.01, 0.5, 0.01, 1.5, 0.01, 0.3, 0.3, 0.3, 0.01, 0.01, 0.01]),
    goal=np.array([0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0]),
    tracking_axes=((0, 0, 1), (1, 2, 3), (2, 4, 5)),
    default_plane="xz",
    default_offset=(0.0, 1.0),
    default_scale=0.5,
    q_diag=np.array([1.0, 0.1, 1.0, 0.1, 1.0, 0.1, 0.1, 0.1, 0.1, 0.1, 0.1, 0.1]),
    r_diag=np.full(4, 0.1),
    mse_weight=np.array([1.0, 0.0, 1.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0]),
    **_thrust.system_fields("quadrotor_3d"),
    inertial_fields=("mass", "ixx", "iyy", "izz"),
    # z_dd is x_dot[5]; the body angular accelerations p_dot, q_dot, r_dot are x_dot[9:12].
    wrench_allocation=WrenchAllocation(
        vertical_acceleration=5,
        angular_accelerations=(9, 10, 11),
        inertia_fields=("ixx", "iyy", "izz"),
        torque_axes=(0, 1, 2),
    ),
)
