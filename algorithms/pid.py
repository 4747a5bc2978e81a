"""PID baseline: cascaded position / attitude control of the 1D, 2D and 3D quadrotor (registered as ``"pid"``).

Structure (one control step, per copy, all in SI units):

1. **Position loop** (world frame, axes x, y, z): with ``e = p_ref - p`` (m), ``e_v = v_ref - v`` (m/s) and the
   integral ``I = clip(I + e dt, -integral_limit, integral_limit)`` (m s, clamped per axis: anti-windup), the
   desired acceleration is ``a = kp e + ki I + kd e_v + a_ff`` (m/s^2). ``a_ff`` is the reference's own
   acceleration, the forward difference ``(v_ref[k+1] - v_ref[k]) / dt`` of its analytic velocities (zero for
   stabilization; ``feedforward=False`` drops it). The axes a system does not have (y in 2D, x and y in 1D)
   carry zero error.
2. **Thrust vector**: ``F = m_prior (a + g e_z)`` (N, world frame), tilted at most ``max_tilt`` from vertical
   (its vertical part kept >= 10% of the prior hover thrust so the direction is defined). Its direction is the
   desired body z axis; the collective thrust is its projection on the *current* body z axis, ``T = F . b3``.
3. **Attitude** from the direction of ``F``: 2D ``theta_des = atan2(F_x, F_z)`` (pitch positive tilts the thrust
   towards +x, as in ``quadrotor_2d.py``); 3D ZYX Euler angles with the desired yaw ``psi_ref`` taken from the
   reference state (0 in tracking tasks): with ``F' = Rz(-psi_ref) F``, ``theta_des = atan2(F'_x, F'_z)`` and
   ``phi_des = atan2(-F'_y, sqrt(F'_x^2 + F'_z^2))``, exact for ``b3 = Rz Ry Rx e_z``.
4. **Attitude loop**: PD (PID when ``attitude_ki > 0``) on the wrapped Euler-angle error gives the desired body
   angular acceleration ``alpha = kp e_att + ki I_att - kd w`` (rad/s^2); in 3D the Euler error is first mapped
   to body axes by the Euler-rate-to-body-rate matrix, and the torque ``M = J alpha + w x (J w)`` cancels the
   gyroscopic term with the prior inertia ``J`` (N m).
5. **Mixer**: the motor thrusts solve ``[T, M] = A u`` where ``A`` (``allocation_matrix``) is read off the
   system's own ``dynamics`` with the prior parameters at the rows its record names (``System.wrench_allocation``):
   how a unit of each input changes the vertical acceleration times the mass and the angular accelerations times
   the inertia, at a level hover state. So no geometry is retyped here. Each motor is then clipped to
   ``env.input_bounds(prior_params.physics)``.

Gains are in physical units and independent of the vehicle's mass (they are accelerations per error): position
``kp`` 1/s^2, ``ki`` 1/s^3, ``kd`` 1/s; attitude ``kp`` 1/s^2, ``ki`` 1/s^3, ``kd`` 1/s. The defaults put the
attitude loop (roll, pitch) at ``sqrt(kp) = 17`` rad/s, damping ``kd / (2 sqrt(kp)) = 0.8``: 2.8 Hz, a ninth of the
25 Hz Nyquist frequency of the 50 Hz control rate, where the input held over a control period costs about
``omega dt / 2 = 10`` degrees of phase; yaw at 10 rad/s, damping 0.8; the position loop at ``sqrt(8) = 2.8`` rad/s,
damping 0.9, six times slower than the attitude loop it commands. With the integral the position loop's
characteristic polynomial ``s^3 + kd s^2 + kp s + ki`` has roots -2.35 +- 1.03j and -0.30 rad/s: the integral
removes a constant force error (e.g. a wrong prior mass) with a time constant of about 3 s.

Controller memory (``PIDState``) holds the two integrators, zero at reset. The cart-pole is not supported.
"""

from __future__ import annotations

import dataclasses
from typing import Any, NamedTuple

import jax.numpy as jnp
import numpy as np

from scg_algorithms.base import JaxController, option, parse_options, state_from_obs
from scg_jax.backends import jax_backend

SUPPORTED_SYSTEMS = ("quadrotor_1d", "quadrotor_2d", "quadrotor_3d")

# Where the thrust and the torques show in each system's dynamics (the rows of the wrench allocation) lives in the
# system's record, ``System.wrench_allocation`` (scg_jax/systems/); this module only reads it.


@dataclasses.dataclass(frozen=True)
class Options:
    """Gains of the cascaded PID (``controllers.pid`` in a config file).

    Per-axis options take 3 numbers (world x, y, z for the position loop; roll, pitch, yaw for the attitude
    loop) or one number for all three. Axes a model lacks are ignored.
    """

    position_kp: tuple = option((8.0, 8.0, 8.0), "position P gain per world axis x, y, z, 1/s^2")
    position_ki: tuple = option((2.0, 2.0, 2.0), "position I gain per world axis, 1/s^3")
    position_kd: tuple = option((5.0, 5.0, 5.0), "position D gain on the velocity error per world axis, 1/s")
    integral_limit: tuple = option((0.5, 0.5, 0.5), "clamp of the position integral per axis (anti-windup), m s")
    attitude_kp: tuple = option((300.0, 300.0, 100.0), "attitude P gain roll, pitch, yaw, 1/s^2")
    attitude_kd: tuple = option((28.0, 28.0, 16.0), "attitude D gain on the body rates roll, pitch, yaw, 1/s")
    attitude_ki: tuple = option((0.0, 0.0, 0.0), "attitude I gain roll, pitch, yaw (0: PD), 1/s^3")
    attitude_integral_limit: tuple = option((0.2, 0.2, 0.2), "clamp of the attitude integral per axis, rad s")
    max_tilt: float = option(0.6, "largest angle between the commanded thrust and the vertical, rad")
    feedforward: bool = option(True, "add the reference's acceleration (finite difference of its velocity)")

    def _check(self, path: str) -> None:
        for field in dataclasses.fields(self):
            value = getattr(self, field.name)
            if isinstance(value, tuple):
                if len(value) not in (1, 3):
                    raise ValueError(f"{path}.{field.name}: expected 1 or 3 values, got {len(value)}")
                if min(value) < 0:
                    raise ValueError(f"{path}.{field.name}: gains and limits must be >= 0, got {list(value)}")
        if not 0.0 < self.max_tilt < np.pi / 2:
            raise ValueError(f"{path}.max_tilt: must be in (0, pi/2) rad, got {self.max_tilt!r}")

    def vector(self, name: str) -> np.ndarray:
        """The per-axis option ``name`` as a (3,) array (one value broadcast to all three axes)."""
        return np.broadcast_to(np.asarray(getattr(self, name), dtype=float), (3,)).copy()


class PIDState(NamedTuple):
    """Controller memory of one copy.

    Attributes:
        position_integral: (3,) integral of the world-frame position error, m s.
        attitude_integral: (3,) integral of the roll, pitch, yaw error, rad s.
    """

    position_integral: Any
    attitude_integral: Any


def _check_system(env) -> None:
    if env.system.name not in SUPPORTED_SYSTEMS or env.system.wrench_allocation is None:
        raise ValueError(
            f"controllers.pid: system {env.system.name!r} is not supported; supported systems are "
            f"{', '.join(SUPPORTED_SYSTEMS)}"
        )


def allocation_matrix(env, physics):
    """The map from motor thrusts to collective thrust and body torques, read off the system's ``dynamics``.

    The dynamics are affine in ``u``; at a level state with zero rates, ``x_dot(e_i) - x_dot(0)`` is the effect
    of one newton on input ``i``. The vertical acceleration times the mass is the collective thrust and each body
    angular acceleration times its moment of inertia the torque.

    Args:
        env: a quadrotor env. physics: the (prior) ``Params``.

    Returns:
        A (nu, nu): ``[T, M...] = A u``, rows thrust (N) then torques (N m) about the model's body axes
        (2D: pitch; 3D: roll, pitch, yaw). ``u`` in N.
    """
    _check_system(env)
    allocation = env.system.wrench_allocation
    z_row, torque_rows = allocation.vertical_acceleration, allocation.angular_accelerations
    inertia_fields = allocation.inertia_fields
    nx, nu = env.nx, env.nu
    dtype = jnp.result_type(float)
    x_level = jnp.zeros(nx, dtype)

    def x_dot(u):
        return env.system.dynamics(x_level, u, physics, jax_backend)

    base = x_dot(jnp.zeros(nu, dtype))
    columns = jnp.stack([x_dot(jnp.eye(nu, dtype=dtype)[i]) - base for i in range(nu)], axis=1)  # (nx, nu)
    scale = jnp.stack(
        [jnp.asarray(physics.mass, dtype)] + [jnp.asarray(getattr(physics, f), dtype) for f in inertia_fields]
    )
    rows = columns[jnp.asarray((z_row, *torque_rows))]
    return scale[:, None] * rows


def motor_mixer(env, physics):
    """The inverse of ``allocation_matrix``: motor thrusts ``u = mixer @ [T, M...]`` (nu, nu)."""
    return jnp.linalg.inv(allocation_matrix(env, physics))


def _wrap(angle):
    return jnp.arctan2(jnp.sin(angle), jnp.cos(angle))


def _world_vectors(env, x):
    """Position and velocity (3,) in the world frame of state ``x`` (zeros on the axes the model lacks)."""
    p = jnp.zeros(3, x.dtype)
    v = jnp.zeros(3, x.dtype)
    for axis, pos_index, vel_index in env.system.tracking_axes:
        p = p.at[axis].set(x[pos_index])
        v = v.at[axis].set(x[vel_index])
    return p, v


def make_pid(env, prior_params, options=None) -> JaxController:
    """Cascaded PID for the 1D, 2D and 3D quadrotor (see the module docstring).

    Args:
        env: an ``scg_jax.Env`` of ``quadrotor_1d``, ``quadrotor_2d`` or ``quadrotor_3d``.
        prior_params: ``EnvParams`` of the controller's model: ``physics.mass``, ``gravity``, the inertia and the
            geometry (through ``allocation_matrix``) and the input bounds come from here.
        options: mapping of ``Options`` fields (``controllers.pid``), or ``None`` for the defaults.

    Returns:
        ``JaxController`` named ``"pid"``: ``reset(key, reference) -> PIDState`` (zeros) and
        ``act(state, obs, step, reference) -> (u (nu,) N, state)``, pure JAX per copy.

    Raises:
        ValueError: for the cart-pole (naming the supported systems) or a bad option (naming
            ``controllers.pid.<field>``).
    """
    _check_system(env)
    opts = parse_options(Options, options, "controllers.pid")
    name = env.system.name
    physics = prior_params.physics
    dt = env.dt
    mass = jnp.asarray(physics.mass)
    gravity = jnp.asarray(physics.gravity)
    mixer = motor_mixer(env, physics)
    u_low, u_high = env.input_bounds(physics)
    inertia = jnp.stack([jnp.asarray(physics.ixx), jnp.asarray(physics.iyy), jnp.asarray(physics.izz)])
    torque_axes = np.asarray(env.system.wrench_allocation.torque_axes, dtype=int)

    kp, ki, kd = (jnp.asarray(opts.vector(f"position_{g}")) for g in ("kp", "ki", "kd"))
    i_limit = jnp.asarray(opts.vector("integral_limit"))
    att_kp, att_kd, att_ki = (jnp.asarray(opts.vector(f"attitude_{g}")) for g in ("kp", "kd", "ki"))
    att_limit = jnp.asarray(opts.vector("attitude_integral_limit"))
    tan_tilt = float(np.tan(opts.max_tilt))
    e_z = jnp.array([0.0, 0.0, 1.0])

    def reset_fn(key, reference):
        del key
        dtype = jnp.asarray(reference.x_ref).dtype
        return PIDState(jnp.zeros(3, dtype), jnp.zeros(3, dtype))

    def act_fn(ctrl_state, obs, step, reference):
        x = state_from_obs(env, obs)
        x_ref_all = reference.x_ref
        last = x_ref_all.shape[0] - 1
        k = jnp.clip(step, 0, last)
        x_ref = x_ref_all[k]
        p, v = _world_vectors(env, x)
        p_ref, v_ref = _world_vectors(env, x_ref)

        # Outer loop: position PID with a clamped integral.
        error = p_ref - p
        integral = jnp.clip(ctrl_state.position_integral + error * dt, -i_limit, i_limit)
        accel = kp * error + ki * integral + kd * (v_ref - v)
        if opts.feedforward:
            _, v_next = _world_vectors(env, x_ref_all[jnp.clip(k + 1, 0, last)])
            accel = accel + jnp.where(k < last, (v_next - v_ref) / dt, 0.0)
        force = mass * (accel + gravity * e_z)
        # Keep the thrust vector upward and within max_tilt of vertical.
        fz = jnp.maximum(force[2], 0.1 * mass * gravity)
        horizontal = force[:2]
        h_norm = jnp.sqrt(jnp.sum(horizontal**2) + 1e-20)
        horizontal = horizontal * jnp.minimum(1.0, fz * tan_tilt / h_norm)
        force = jnp.stack([horizontal[0], horizontal[1], fz])

        if name == "quadrotor_1d":
            wrench = force[2:]
            att_integral = ctrl_state.attitude_integral
        else:
            if name == "quadrotor_2d":
                theta = x[4]
                angles = jnp.stack([0.0 * theta, theta, 0.0 * theta])
                rates = jnp.stack([0.0 * theta, x[5], 0.0 * theta])
                body_z = jnp.stack([jnp.sin(theta), 0.0 * theta, jnp.cos(theta)])
                desired = jnp.stack([0.0 * theta, jnp.arctan2(force[0], force[2]), 0.0 * theta])
                angle_error = _wrap(desired - angles)
                body_error = angle_error
            else:
                phi, theta, psi = x[6], x[7], x[8]
                angles = x[6:9]
                rates = x[9:12]
                s_phi, c_phi = jnp.sin(phi), jnp.cos(phi)
                s_theta, c_theta = jnp.sin(theta), jnp.cos(theta)
                s_psi, c_psi = jnp.sin(psi), jnp.cos(psi)
                body_z = jnp.stack(
                    [c_psi * s_theta * c_phi + s_psi * s_phi, s_psi * s_theta * c_phi - c_psi * s_phi, c_theta * c_phi]
                )
                psi_des = x_ref[8]
                c_d, s_d = jnp.cos(psi_des), jnp.sin(psi_des)
                f_yaw = jnp.stack([c_d * force[0] + s_d * force[1], -s_d * force[0] + c_d * force[1], force[2]])
                theta_des = jnp.arctan2(f_yaw[0], f_yaw[2])
                phi_des = jnp.arctan2(-f_yaw[1], jnp.sqrt(f_yaw[0] ** 2 + f_yaw[2] ** 2))
                angle_error = _wrap(jnp.stack([phi_des, theta_des, psi_des]) - angles)
                # Euler-angle error to body axes (the Euler-rate to body-rate map), so that yaw error with the
                # vehicle tilted is corrected about the right body axes.
                body_from_euler = jnp.stack(
                    [
                        jnp.stack([1.0 + 0.0 * phi, 0.0 * phi, -s_theta]),
                        jnp.stack([0.0 * phi, c_phi, s_phi * c_theta]),
                        jnp.stack([0.0 * phi, -s_phi, c_phi * c_theta]),
                    ]
                )
                body_error = body_from_euler @ angle_error
            thrust = force @ body_z
            att_integral = jnp.clip(ctrl_state.attitude_integral + body_error * dt, -att_limit, att_limit)
            alpha = att_kp * body_error + att_ki * att_integral - att_kd * rates
            torque = inertia * alpha + jnp.cross(rates, inertia * rates)
            wrench = jnp.concatenate([thrust[None], torque[torque_axes]])
        u = jnp.clip(mixer @ wrench, u_low, u_high)
        return u.astype(obs.dtype), PIDState(integral, att_integral)

    info = {"system": name, "options": dataclasses.asdict(opts), "dt": dt}
    return JaxController(name="pid", reset_fn=reset_fn, act_fn=act_fn, info=info)


__all__ = ["SUPPORTED_SYSTEMS", "Options", "PIDState", "allocation_matrix", "make_pid", "motor_mixer"]
