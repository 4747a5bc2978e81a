"""Reference trajectories: analytic velocities, the square's geometry, and the env's reference layout."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import scg_jax
from scg_jax import trajectories

PERIOD = 4.0


@pytest.mark.parametrize("shape", trajectories.SHAPES)
@pytest.mark.parametrize("scale", [0.7, -0.4])
def test_velocity_is_the_time_derivative_of_position(shape, scale):
    offset = jnp.array([0.3, 1.1])
    position = lambda t: trajectories.world_reference(shape, "xz", t, PERIOD, scale, offset)[0]  # noqa: E731
    # Times away from the square's corners (multiples of PERIOD / 4), where its velocity jumps.
    times = np.array([0.13, 0.77, 1.41, 2.29, 2.9, 3.61, 5.3])
    speeds = []
    for t in times:
        pos, vel = trajectories.world_reference(shape, "xz", jnp.float32(t), PERIOD, scale, offset)
        _, tangent = jax.jvp(position, (jnp.float32(t),), (jnp.float32(1.0),))
        np.testing.assert_allclose(np.asarray(vel), np.asarray(tangent), rtol=1e-5, atol=1e-5)
        speeds.append(float(jnp.abs(vel).max()))
    assert max(speeds) > 0.3  # the comparison is not between zeros


def test_square_has_constant_speed_per_side_and_visits_its_corners():
    scale = 0.5
    speed = 4 * scale / PERIOD
    times = np.linspace(0.0, PERIOD, 401)[:-1]
    pos, vel = jax.vmap(lambda t: trajectories.planar("square", t, PERIOD, scale))(jnp.asarray(times))
    pos, vel = np.asarray(pos), np.asarray(vel)
    np.testing.assert_allclose(np.linalg.norm(vel, axis=1), speed, rtol=1e-6)
    for side, direction in enumerate([(0, 1), (-1, 0), (0, -1), (1, 0)]):
        in_side = (times >= side * PERIOD / 4 + 1e-6) & (times < (side + 1) * PERIOD / 4 - 1e-6)
        np.testing.assert_allclose(vel[in_side], np.tile(np.array(direction) * speed, (in_side.sum(), 1)), atol=1e-6)
    corners = np.asarray(
        jax.vmap(lambda t: trajectories.planar("square", t, PERIOD, scale)[0])(jnp.array([0.0, 1.0, 2.0, 3.0, 4.0]))
    )
    np.testing.assert_allclose(corners, [[0, 0], [0, 0.5], [-0.5, 0.5], [-0.5, 0], [0, 0]], atol=1e-6)


def test_figure8_and_circle_closed_forms():
    s, t = 0.8, PERIOD / 8  # w t = pi / 4
    fig8, _ = trajectories.planar("figure8", t, PERIOD, s)
    circle, _ = trajectories.planar("circle", t, PERIOD, s)
    sinusoid, _ = trajectories.planar("sinusoid", t, PERIOD, s)
    np.testing.assert_allclose(np.asarray(fig8), [s * np.sqrt(0.5), s / 2], rtol=1e-6)
    np.testing.assert_allclose(np.asarray(circle), [s * np.sqrt(0.5), s * np.sqrt(0.5)], rtol=1e-6)
    np.testing.assert_allclose(np.asarray(sinusoid), [s * np.sqrt(0.5), 0.0], rtol=1e-6, atol=1e-7)


def test_env_reference_holds_one_point_per_control_step_plus_the_final_one():
    env = scg_jax.make(
        "quadrotor_2d",
        "tracking",
        ctrl_freq=20,
        episode_len_sec=3.0,
        trajectory={"shape": "figure8", "num_cycles": 2, "plane": "xz", "offset": [0.2, 1.0], "scale": 0.6},
    )
    x_ref, u_ref = env.reference(env.default_params)
    assert x_ref.shape == (61, 6) and u_ref.shape == (60, 2)
    # Point for point with the original's definition: t_k = k dt, period = episode length / cycles.
    t = np.arange(61) / 20.0
    w = 2 * np.pi / 1.5
    expected_x = 0.6 * np.sin(w * t) + 0.2
    expected_z = 0.6 * np.sin(w * t) * np.cos(w * t) + 1.0
    np.testing.assert_allclose(np.asarray(x_ref[:, 0]), expected_x, atol=2e-6)
    np.testing.assert_allclose(np.asarray(x_ref[:, 2]), expected_z, atol=2e-6)
    np.testing.assert_allclose(np.asarray(x_ref[:, 1]), 0.6 * w * np.cos(w * t), atol=2e-5)
    np.testing.assert_allclose(np.asarray(x_ref[:, 4:]), 0.0)
    np.testing.assert_allclose(np.asarray(u_ref), 0.1323, rtol=1e-6)


@pytest.mark.parametrize(
    ("system", "plane", "filled"),
    [("cartpole", "xz", [0, 1]), ("quadrotor_1d", "zx", [0, 1]), ("quadrotor_3d", "yz", [2, 3, 4, 5])],
)
def test_plane_letters_select_the_state_entries(system, plane, filled):
    env = scg_jax.make(system, "tracking", trajectory={"shape": "circle", "plane": plane, "offset": [0.0, 0.0]})
    x_ref, _ = env.reference(env.default_params)
    moving = np.flatnonzero(np.abs(np.asarray(x_ref)).max(axis=0) > 1e-3)
    np.testing.assert_array_equal(moving, filled)
