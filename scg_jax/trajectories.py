"""Reference trajectories for the tracking task: pure ``jax.numpy`` functions of time.

Every shape is drawn in a plane named by two distinct letters of ``xyz`` (``"xz"``: first coordinate along
world x, second along world z). With period ``P = episode_len_sec / num_cycles``, ``w = 2 pi / P`` and scale
``s`` (m; negative flips the shape), the in-plane coordinates ``(a, b)`` before the offset are:

- ``circle``:   ``(s cos wt, s sin wt)``
- ``sinusoid``: ``(s sin wt, 0)``, a sine along the plane's first axis
- ``figure8``:  ``(s sin wt, s sin wt cos wt)``, a lemniscate of Gerono
- ``square``:   four sides of length ``|s|`` at constant speed ``4 s / P``, starting at the origin and going
  through ``(0, s)``, ``(-s, s)``, ``(-s, 0)`` and back, one side per quarter period

The offset ``(o_a, o_b)`` (m) is added to ``(a, b)``. Velocities are the exact time derivatives (the square's
is piecewise constant). These are the shapes and parametrisation of the original suite, so a reference built
with the same settings matches it point for point.
"""

from __future__ import annotations

import jax.numpy as jnp

SHAPES = ("circle", "sinusoid", "figure8", "square")
_AXES = "xyz"


def plane_axes(plane: str) -> tuple[int, int]:
    """World-axis indices (0=x, 1=y, 2=z) of a two-letter plane such as ``"xz"``; ValueError otherwise."""
    if not (isinstance(plane, str) and len(plane) == 2 and set(plane) <= set(_AXES) and plane[0] != plane[1]):
        raise ValueError(
            f"trajectory.plane: unknown value {plane!r}; allowed values are two distinct letters of x, y, z "
            "(xy, xz, yx, yz, zx, zy)"
        )
    return _AXES.index(plane[0]), _AXES.index(plane[1])


def check_shape(shape: str) -> str:
    if shape not in SHAPES:
        raise ValueError(f"trajectory.shape: unknown value {shape!r}; allowed values are {', '.join(SHAPES)}")
    return shape


def planar(shape: str, t, period, scale):
    """In-plane position and velocity of ``shape`` at time ``t`` (s).

    Returns:
        ``(position (2,), velocity (2,))`` in m and m/s, without the offset.
    """
    w = 2.0 * jnp.pi / period
    phase = w * t
    sin, cos = jnp.sin(phase), jnp.cos(phase)
    if shape == "circle":
        pos = (scale * cos, scale * sin)
        vel = (-scale * w * sin, scale * w * cos)
    elif shape == "sinusoid":
        pos = (scale * sin, 0.0 * sin)
        vel = (scale * w * cos, 0.0 * cos)
    elif shape == "figure8":
        pos = (scale * sin, scale * sin * cos)
        vel = (scale * w * cos, scale * w * (cos**2 - sin**2))
    elif shape == "square":
        return _square(t, period, scale)
    else:
        check_shape(shape)
    return jnp.stack(pos), jnp.stack(vel)


def _square(t, period, scale):
    side_time = period / 4.0
    speed = scale / side_time
    cycle_time = jnp.mod(t, period)
    side = jnp.clip(jnp.floor(cycle_time / side_time), 0, 3).astype(jnp.int32)
    along = speed * (cycle_time - side * side_time)
    corners = scale * jnp.array([[0.0, 0.0], [0.0, 1.0], [-1.0, 1.0], [-1.0, 0.0]])
    directions = jnp.array([[0.0, 1.0], [-1.0, 0.0], [0.0, -1.0], [1.0, 0.0]])
    return corners[side] + directions[side] * along, directions[side] * speed


def world_reference(shape: str, plane: str, t, period, scale, offset):
    """Position and velocity in the world frame at time ``t``.

    Args:
        shape: one of ``SHAPES``. plane: two-letter plane. t: time (s). period: P (s). scale: s (m).
        offset: (2,) in-plane offset (m).

    Returns:
        ``(position (3,), velocity (3,))``; the axis normal to the plane is zero.
    """
    axis_a, axis_b = plane_axes(plane)
    pos2, vel2 = planar(shape, t, period, scale)
    pos2 = pos2 + jnp.asarray(offset)
    zero = jnp.zeros(3, dtype=pos2.dtype)
    position = zero.at[axis_a].set(pos2[0]).at[axis_b].set(pos2[1])
    velocity = zero.at[axis_a].set(vel2[0]).at[axis_b].set(vel2[1])
    return position, velocity
