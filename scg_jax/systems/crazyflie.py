"""Physical parameters of the Crazyflie 2.x quadrotor, shared by the 1D, 2D and 3D quadrotor systems.

The 1D, 2D and 3D models are the same vehicle constrained to fewer degrees of freedom: each physical input
of a reduced model drives a group of motors together (1D: all four, 2D: the front and the back pair), so its
thrust limits and hover thrust are those of one motor times the group size.
"""

from __future__ import annotations

import numpy as np

from scg_jax._pytree import pytree_dataclass
from scg_jax.systems.base import require_positive
from scg_jax.validation import FieldError

DEG = np.pi / 180.0


@pytree_dataclass
class Params:
    """Crazyflie 2.x parameters (primitive quantities only; totals and moment arms are derived in dynamics).

    Attributes:
        mass: m, kg.
        arm_length: L, m, from the centre of mass to each motor (2D effective arm d = L / sqrt(2)).
        ixx, iyy, izz: principal moments of inertia, kg m^2.
        kf: thrust coefficient, N / (rad/s)^2.
        km: drag-torque coefficient, N m / (rad/s)^2; the yaw moment per newton of thrust is km / kf (m).
        gravity: g, m/s^2.
        motor_thrust_min, motor_thrust_max: limits of one motor's thrust, N.
    """

    mass: float = 0.027
    arm_length: float = 0.0397
    ixx: float = 1.4e-5
    iyy: float = 1.4e-5
    izz: float = 2.17e-5
    kf: float = 3.16e-10
    km: float = 7.94e-12
    gravity: float = 9.8
    motor_thrust_min: float = 0.02816
    motor_thrust_max: float = 0.14834


def validate_params(params: Params, system: str) -> None:
    require_positive(params, ("mass", "arm_length", "ixx", "iyy", "izz", "kf", "km", "gravity"), system)
    require_positive(params, ("motor_thrust_max",), system)
    low = np.asarray(params.motor_thrust_min, dtype=float)
    high = np.asarray(params.motor_thrust_max, dtype=float)
    if np.any(low < 0.0) or np.any(low >= high):
        raise FieldError(
            "physics.motor_thrust_min",
            f"must satisfy 0 <= motor_thrust_min < motor_thrust_max for {system}, got {low.tolist()!r} and "
            f"{high.tolist()!r}",
        )


class ThrustGroups:
    """Input conversions for a model whose ``nu`` inputs each drive ``motors_per_input`` motors.

    Normalised action ``a`` in [-1, 1] maps to thrust ``hover * (1 + 0.1 a)`` per input (N), where ``hover`` is
    the thrust per input that balances gravity for the given mass.
    """

    ACTION_SCALE = 0.1

    def __init__(self, nu: int, motors_per_input: int):
        self.nu = nu
        self.motors_per_input = motors_per_input

    def input_bounds(self, params: Params):
        ones = np.ones(self.nu)
        k = self.motors_per_input
        return k * params.motor_thrust_min * ones, k * params.motor_thrust_max * ones

    def equilibrium_input(self, params: Params):
        return params.mass * params.gravity / self.nu * np.ones(self.nu)

    def action_to_input(self, action, params: Params):
        return self.equilibrium_input(params) * (1.0 + self.ACTION_SCALE * action)

    def input_to_action(self, u, params: Params):
        return (u / self.equilibrium_input(params) - 1.0) / self.ACTION_SCALE

    def system_fields(self, name: str) -> dict:
        """The ``System`` fields every Crazyflie model shares, wired to these thrust groups: input bounds and
        conversions, the parameter check, and the Gymnasium id and render view named after the model."""
        return {
            "input_bounds": self.input_bounds,
            "equilibrium_input": self.equilibrium_input,
            "action_to_input": self.action_to_input,
            "input_to_action": self.input_to_action,
            "validate_params": lambda params: validate_params(params, name),
            "gymnasium_id": f"scg_jax/Quadrotor{name.removeprefix('quadrotor_').upper()}-v0",
            "view": name,
        }


# Bounds of the original suite: x, y in +-2 m, z in [-0.05, 2] m, velocities +-30 m/s, roll and pitch
# +-85 deg, body rates +-500 deg/s.
POSITION_BOUND = 2.0
Z_LOW, Z_HIGH = -0.05, 2.0
VELOCITY_BOUND = 30.0
ANGLE_BOUND = 85.0 * DEG
RATE_BOUND = 500.0 * DEG
