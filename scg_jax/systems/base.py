"""The static description every system module exports as ``SYSTEM``.

A ``System`` is plain Python structure (decided at ``make``, never traced). The physics lives in the module's
``Params`` pytree and its single ``dynamics`` function; everything here is layout and defaults.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any

import numpy as np

from scg_jax.validation import FieldError


@dataclasses.dataclass(frozen=True)
class WrenchAllocation:
    """Where a multirotor's collective thrust and body torques enter its ``dynamics``.

    The dynamics are affine in the motor thrusts ``u``; at a level state with zero rates, the mass times the
    vertical acceleration is the collective thrust and each body angular acceleration times its moment of inertia
    the torque about that axis. These indices turn the input Jacobian of ``dynamics`` into the allocation
    ``[T, M...] = A u`` (``scg_algorithms.pid.allocation_matrix``), so no geometry is retyped outside the system.

    Attributes:
        vertical_acceleration: index in ``x_dot`` of the vertical acceleration (m/s^2).
        angular_accelerations: indices in ``x_dot`` of the body angular accelerations (rad/s^2) the model has, in
            roll, pitch, yaw order.
        inertia_fields: the ``Params`` fields of the matching moments of inertia (kg m^2).
        torque_axes: the body axes of those torques (0 roll, 1 pitch, 2 yaw).
    """

    vertical_acceleration: int
    angular_accelerations: tuple[int, ...]
    inertia_fields: tuple[str, ...]
    torque_axes: tuple[int, ...]


@dataclasses.dataclass(frozen=True)
class System:
    """Layout, defaults and conversions of one system.

    Attributes:
        name: registry name, e.g. ``"cartpole"``.
        params_cls: the frozen ``Params`` pytree class of primitive physical quantities.
        dynamics: ``dynamics(x, u, params, xp, f_ext=None) -> x_dot``, the one set of equations.
        state_names, input_names: names of the entries of ``x`` (nx,) and ``u`` (nu,).
        f_ext_dim: number of components of the external force ``f_ext`` (N).
        velocity_mask: (nx,) 1.0 for entries semi-implicit Euler advances first (velocities, rates).
        state_low, state_high: (nx,) bounds whose violation ends an episode (``inf`` where unbounded).
        init_low, init_high: (nx,) default uniform initial-state range.
        goal: (nx,) default stabilization goal state.
        tracking_axes: ``(world_axis, position_index, velocity_index)`` per world axis (0=x, 1=y, 2=z) the
            tracking reference drives; other state entries of the reference are zero.
        default_plane: default two-letter trajectory plane.
        default_offset: default (2,) trajectory offset in that plane (m).
        default_scale: default trajectory scale (m).
        q_diag, r_diag: default diagonals of the cost weights Q (nx,) and R (nu,).
        mse_weight: (nx,) default weights of the tracking error reported as ``info["mse"]``.
        input_bounds: ``input_bounds(params) -> (u_low, u_high)`` actuator limits (nu,) each.
        equilibrium_input: ``equilibrium_input(params) -> u_eq`` (nu,), the input holding the goal (hover).
        action_to_input: ``action_to_input(action, params) -> u``, normalised RL action to physical input.
        input_to_action: the inverse of ``action_to_input``.
        gymnasium_id: the id ``import scg_jax`` registers with Gymnasium, e.g. ``"scg_jax/CartPole-v0"``.
        view: how ``scg_jax.render`` draws the system: ``"cartpole"`` (cart on a track, side view),
            ``"quadrotor_1d"`` (body at height z, side view), ``"quadrotor_2d"`` (x-z side view) or
            ``"quadrotor_3d"`` (perspective); a new system reuses one of these views or adds one there.
        validate_params: raises ValueError naming the field when a parameter value is not physical.
        inertial_fields: the ``Params`` fields a prior model scales by default (masses, lengths, inertias).
        wrench_allocation: where the collective thrust and the body torques show in ``dynamics`` (a
            ``WrenchAllocation``), from which thrust/torque mixers (the PID's) are read off; ``None`` for a system
            without motors that make a wrench (the cart-pole).
    """

    name: str
    params_cls: type
    dynamics: Callable[..., Any]
    state_names: tuple[str, ...]
    input_names: tuple[str, ...]
    f_ext_dim: int
    velocity_mask: np.ndarray
    state_low: np.ndarray
    state_high: np.ndarray
    init_low: np.ndarray
    init_high: np.ndarray
    goal: np.ndarray
    tracking_axes: tuple[tuple[int, int, int], ...]
    default_plane: str
    default_offset: tuple[float, float]
    default_scale: float
    q_diag: np.ndarray
    r_diag: np.ndarray
    mse_weight: np.ndarray
    input_bounds: Callable[[Any], tuple[Any, Any]]
    equilibrium_input: Callable[[Any], Any]
    action_to_input: Callable[[Any, Any], Any]
    input_to_action: Callable[[Any, Any], Any]
    gymnasium_id: str
    view: str
    validate_params: Callable[[Any], None]
    inertial_fields: tuple[str, ...]
    wrench_allocation: WrenchAllocation | None

    @property
    def nx(self) -> int:
        return len(self.state_names)

    @property
    def nu(self) -> int:
        return len(self.input_names)

    @property
    def path_plane(self) -> str | None:
        """The two-letter plane a plot of the position path is drawn in (the default trajectory plane), or
        ``None`` for systems whose position has fewer than two world axes (nothing to draw a path of)."""
        return self.default_plane if len(self.tracking_axes) >= 2 else None


def require_positive(params, names, system: str) -> None:
    """Raise a ``FieldError`` naming ``physics.<field>`` (the ``make`` option) for each non-positive or non-finite
    value."""
    for name in names:
        value = np.asarray(getattr(params, name), dtype=float)
        if not np.all(np.isfinite(value)) or np.any(value <= 0.0):
            raise FieldError(
                f"physics.{name}", f"must be a positive finite number for {system}, got {value.tolist()!r}"
            )
