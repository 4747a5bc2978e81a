"""1D quadrotor: the Crazyflie restricted to vertical motion (a double integrator).

Description:
    The four motors act together and produce a total thrust ``T`` along world z.

State ``x`` (nx = 2): ``[z, z_dot]`` in m and m/s, z up.

Input ``u`` (nu = 1): total thrust ``T`` in N, in ``[4 motor_thrust_min, 4 motor_thrust_max]``
= [0.1126, 0.5934] N; hover ``m g`` = 0.2646 N. Normalised action ``a``: ``T = hover (1 + 0.1 a)``.

External force ``f_ext`` (1,): world-frame force along z on the centre of mass, N.

Episode end: ``z`` outside [-0.05, 2] m or ``|z_dot| > 30`` m/s, the optional goal, or the time limit.

Starting state: ``z ~ U(0.1, 1.5)`` m, ``z_dot ~ U(-0.01, 0.01)`` m/s. Stabilization goal ``z = 1`` m.

Equations::

    z_dd = (T + F_z) / m - g
"""

from __future__ import annotations

import numpy as np

from scg_jax.systems import crazyflie as cf
from scg_jax.systems.base import System, WrenchAllocation

Params = cf.Params
_thrust = cf.ThrustGroups(nu=1, motors_per_input=4)


def dynamics(x, u, params: Params, xp, f_ext=None):
    """Continuous-time 1D quadrotor dynamics.

    Args:
        x: (2,) ``[z, z_dot]``. u: (1,) ``[T]`` N. params: ``crazyflie.Params``. xp: backend namespace.
        f_ext: optional (1,) ``[F_z]`` N, world frame; ``None`` means zero.

    Returns:
        x_dot (2,).
    """
    fz = 0.0 if f_ext is None else f_ext[0]
    z_dd = (u[0] + fz) / params.mass - params.gravity
    return xp.stack([x[1], z_dd])


SYSTEM = System(
    name="quadrotor_1d",
    params_cls=Params,
    dynamics=dynamics,
    state_names=("z", "z_dot"),
    input_names=("T",),
    f_ext_dim=1,
    velocity_mask=np.array([0.0, 1.0]),
    state_low=np.array([cf.Z_LOW, -cf.VELOCITY_BOUND]),
    state_high=np.array([cf.Z_HIGH, cf.VELOCITY_BOUND]),
    init_low=np.array([0.1, -0.01]),
    init_high=np.array([1.5, 0.01]),
    goal=np.array([1.0, 0.0]),
    tracking_axes=((2, 0, 1),),
    default_plane="zx",
    default_offset=(1.0, 0.0),
    default_scale=0.5,
    q_diag=np.array([1.0, 0.1]),
    r_diag=np.array([0.1]),
    mse_weight=np.array([1.0, 0.0]),
    **_thrust.system_fields("quadrotor_1d"),
    inertial_fields=("mass",),
    wrench_allocation=WrenchAllocation(
        vertical_acceleration=1, angular_accelerations=(), inertia_fields=(), torque_axes=()
    ),
)
