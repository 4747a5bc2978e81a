"""Rendering: frame shape and determinism, and where things land in the image (measured in pixels)."""

import imageio.v3 as iio
import imageio_ffmpeg
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from matplotlib.colors import to_rgba
from PIL import Image

import scg_jax
from scg_jax.backends import jax_backend
from scg_jax.metrics import episode_lengths
from scg_jax.render import (
    _BOUND_COLOR,
    _CONSTRAINT_COLOR,
    _COPY_COLORS,
    _FRONT_COLOR,
    _darker,
    _rotation,
    animate,
    animate_rollout_file,
    animation_frames,
    render_frame,
)
from tests.conftest import SYSTEM_NAMES

STATES = {
    "cartpole": ([0.0, 0.0, 0.0, 0.0], [1.0, 0.0, 0.4, 0.0]),
    "quadrotor_1d": ([1.0, 0.0], [1.5, 0.0]),
    "quadrotor_2d": ([0.0, 0.0, 1.0, 0.0, 0.0, 0.0], [0.5, 0.0, 1.2, 0.0, 0.4, 0.0]),
    "quadrotor_3d": (
        [0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0],
        [0.5, 0, 0.3, 0, 1.2, 0, 0.3, 0.2, 0.5, 0, 0, 0],
    ),
}


def _rgb(color) -> np.ndarray:
    return np.round(255 * np.asarray(to_rgba(color)[:3])).astype(int)


def _mask(frame, color, tol=12) -> np.ndarray:
    return np.all(np.abs(frame.astype(int) - _rgb(color)) <= tol, axis=-1)


def _centroid(mask) -> np.ndarray:
    """(row, col) of the True pixels."""
    rows, cols = np.nonzero(mask)
    assert len(rows) > 0, "colour not found in the frame"
    return np.array([rows.mean(), cols.mean()])


def _tracking_ref(env) -> np.ndarray:
    return np.asarray(jax.jit(env.reference)(env.default_params)[0])


@pytest.mark.parametrize("name", SYSTEM_NAMES)
def test_frames_have_the_documented_shape_and_change_with_the_state(envs, name):
    env = envs[name]
    a, b = (np.asarray(x, dtype=float) for x in STATES[name])
    frame = render_frame(env, a)
    assert frame.shape == (480, 480, 3) and frame.dtype == np.uint8
    small = render_frame(env, jnp.asarray(b), width=321, height=203)  # JAX input, odd non-square size
    assert small.shape == (203, 321, 3) and small.dtype == np.uint8
    moved = render_frame(env, b)
    changed = np.any(frame != moved, axis=-1)
    assert changed.sum() > 300  # the body moved: hundreds of pixels differ
    # The moving parts only: the background (axes, bounds, labels) is the same in both frames.
    assert changed[:, :30].sum() == 0 or name == "quadrotor_3d"


def test_every_system_and_task_renders_its_reference():
    for name in SYSTEM_NAMES:
        env = scg_jax.make(name, "tracking", episode_len_sec=1.0)
        x = np.asarray(STATES[name][0])
        with_ref = render_frame(env, x, x_ref=_tracking_ref(env))
        without = render_frame(env, x)
        assert np.any(with_ref != without, axis=-1).sum() > 100, name  # the dashed reference is drawn


def test_rendering_is_deterministic_and_independent_of_what_was_drawn_before(envs):
    env = envs["quadrotor_3d"]
    a, b = (np.asarray(x, dtype=float) for x in STATES["quadrotor_3d"])
    first = render_frame(env, b)
    render_frame(env, a, x_ref=np.tile(a, (5, 1)) + 0.3)  # another background in between
    render_frame(env, a, width=200, height=200)
    assert np.array_equal(render_frame(env, b), first)
    # A fresh env (a fresh figure) draws the same pixels.
    assert np.array_equal(render_frame(scg_jax.make("quadrotor_3d"), b), first)


def _cart(frame) -> np.ndarray:
    return _centroid(_mask(frame, _COPY_COLORS[0]))


def test_cart_moves_along_the_track_linearly(envs):
    env = envs["cartpole"]
    cols = {x: _cart(render_frame(env, np.array([x, 0.0, 0.0, 0.0])))[1] for x in (-1.0, 0.0, 1.0, 2.0)}
    per_metre = cols[1.0] - cols[0.0]
    assert per_metre > 50  # moves right, by tens of pixels per metre (about 85 at 480 px)
    assert cols[0.0] - cols[-1.0] == pytest.approx(per_metre, abs=1.0)  # within a pixel (edge snapping)
    assert cols[2.0] - cols[0.0] == pytest.approx(2 * per_metre, abs=1.0)
    # x = 0 is the middle of the track: the red failure lines at +-2.4 m are symmetric about it.
    red_cols = np.nonzero(_mask(render_frame(env, np.zeros(4)), _BOUND_COLOR, tol=30).sum(axis=0) > 100)[0]
    assert red_cols.min() + red_cols.max() == pytest.approx(2 * cols[0.0], abs=2)
    assert red_cols.max() - red_cols.min() == pytest.approx(4.8 * per_metre, abs=3)


def _pca(mask) -> tuple[float, float, np.ndarray]:
    """Main axis of the True pixels: (angle from image-up, positive leaning right; extent along it; centroid)."""
    rows, cols = np.nonzero(mask)
    points = np.stack([cols, -rows], axis=-1).astype(float)  # x right, y up
    centre = points.mean(axis=0)
    values, vectors = np.linalg.eigh(np.cov((points - centre).T))
    axis = vectors[:, np.argmax(values)]
    axis = axis if axis[1] >= 0 else -axis
    along = (points - centre) @ axis
    return float(np.arctan2(axis[0], axis[1])), float(along.max() - along.min()), centre


def _pole_mask(frame):
    """Pole pixels above the cart's top edge."""
    mask = _mask(frame, _darker(_COPY_COLORS[0]))
    top = np.nonzero(_mask(frame, _COPY_COLORS[0]))[0].min()
    mask[top - 1 :] = False
    return mask


def test_pole_leans_towards_plus_x_for_positive_theta_with_the_right_angle_and_length(envs):
    env = envs["cartpole"]
    per_metre = _cart(render_frame(env, np.array([1.0, 0, 0, 0])))[1] - _cart(render_frame(env, np.zeros(4)))[1]
    for theta in (-0.5, 0.0, 0.3, 0.6):
        frame = render_frame(env, np.array([0.0, 0.0, theta, 0.0]))
        cart_row, cart_col = _cart(frame)
        angle, extent, (pole_col, _) = _pca(_pole_mask(frame))
        assert angle == pytest.approx(theta, abs=0.03)  # theta > 0 leans right (+x), at the state's angle
        assert np.sign(round(pole_col - cart_col)) == np.sign(theta)
        # 2 l = 1 m long (plus the round caps, about the line width, 5 px).
        assert extent == pytest.approx(1.0 * per_metre, abs=4)  # 2 l = 1 m (give or take the line's caps)


def test_pole_length_comes_from_params(envs):
    env = envs["cartpole"]
    base = env.default_params
    per_metre = _cart(render_frame(env, np.array([1.0, 0, 0, 0])))[1] - _cart(render_frame(env, np.zeros(4)))[1]
    for half_length in (0.25, 0.75):
        params = base.replace(physics=base.physics.replace(pole_half_length=half_length))
        _, extent, _ = _pca(_pole_mask(render_frame(env, np.array([0.0, 0.0, 0.2, 0.0]), params=params)))
        assert extent == pytest.approx(2 * half_length * per_metre, abs=4)


def test_quadrotor_2d_tilts_its_thrust_towards_plus_x_for_positive_theta(envs):
    env = envs["quadrotor_2d"]
    body = _COPY_COLORS[0]
    for theta in (-0.4, 0.0, 0.4):
        frame = render_frame(env, np.array([0.5, 0.0, 1.2, 0.0, theta, 0.0]), width=720, height=720)
        body_row, body_col = _centroid(_mask(frame, body))
        front_row, front_col = _centroid(_mask(frame, _FRONT_COLOR))
        assert front_col > body_col + 10  # the front rotors (T1) are on the +x side
        # Body x axis (cos theta, -sin theta): for theta > 0 the front end dips (a larger image row), and the
        # thrust axis (sin theta, cos theta), perpendicular to the bar, leans towards +x.
        if theta != 0.0:
            assert np.sign(front_row - body_row) == np.sign(theta)
        # The bar lies along (cos theta, -sin theta): measured from image-up that is theta -+ pi/2.
        angle, _, _ = _pca(_mask(frame, body))
        assert (angle + np.pi / 2 if angle < 0 else angle - np.pi / 2) == pytest.approx(theta, abs=0.04)


def test_quadrotor_1d_body_height_is_linear_in_z(envs):
    env = envs["quadrotor_1d"]
    # Heights away from the goal (z = 1), whose marker would touch the body's outline.
    rows = {z: _centroid(_mask(render_frame(env, np.array([z, 0.0])), _COPY_COLORS[0]))[0] for z in (0.4, 0.7, 1.3)}
    assert rows[0.4] > rows[0.7] > rows[1.3]  # higher z is higher in the image
    assert (rows[0.4] - rows[0.7]) / 0.3 == pytest.approx((rows[0.7] - rows[1.3]) / 0.6, rel=0.02)


def test_3d_body_rotation_matches_the_dynamics():
    """The drawn thrust axis R e_z is the direction the model accelerates in with zero net torque."""
    env = scg_jax.make("quadrotor_3d")
    params = env.default_params
    for angles in ((0.3, 0.0, 0.0), (0.0, 0.4, 0.0), (0.2, -0.3, 0.7)):
        x = np.zeros(12)
        x[6:9] = angles
        u = np.full(4, 2 * 0.0662)  # twice hover: the thrust dominates gravity
        acc = np.asarray(env.system.dynamics(jnp.asarray(x), jnp.asarray(u), params.physics, jax_backend))
        specific = acc[[1, 3, 5]] + np.array([0.0, 0.0, 9.8])
        np.testing.assert_allclose(specific / np.linalg.norm(specific), _rotation(*angles)[:, 2], atol=1e-5)
    # Positive pitch tilts the thrust towards +x, as in 2D; positive roll towards -y.
    assert _rotation(0.0, 0.4, 0.0)[0, 2] > 0 and _rotation(0.4, 0.0, 0.0)[1, 2] < 0


def test_3d_view_shows_attitude_changes(envs):
    env = envs["quadrotor_3d"]
    x = np.array(STATES["quadrotor_3d"][0])
    level = render_frame(env, x)
    for index in (6, 7, 8):  # roll, pitch, yaw each move the drawn body
        turned = x.copy()
        turned[index] = 0.5
        assert np.any(render_frame(env, turned) != level, axis=-1).sum() > 50


def _orange_box(frame):
    rows, cols = np.nonzero(_mask(frame, _CONSTRAINT_COLOR, tol=40))
    return rows.min(), rows.max(), cols.min(), cols.max()


def test_state_constraint_boundaries_are_drawn_where_their_params_put_them():
    constraint = {"type": "bounded", "on": "state", "active_dims": [0, 2], "low": [-1.0, 0.25], "high": [1.0, 1.75]}
    plain = scg_jax.make("quadrotor_2d")
    env = scg_jax.make("quadrotor_2d", constraints=[constraint, {"type": "abs_bound", "on": "input", "bound": 0.2}])
    x = np.array([0.0, 0.0, 1.0, 0.0, 0.0, 0.0])
    base = render_frame(plain, x)
    frame = render_frame(env, x)
    assert np.any(frame != base, axis=-1).sum() > 500
    assert _mask(base, _CONSTRAINT_COLOR, tol=40).sum() == 0
    # Pixel scale from the red failure box: x in [-2, 2], z in [-0.05, 2].
    red = _mask(frame, _BOUND_COLOR, tol=30)
    red_cols = np.nonzero(red.sum(axis=0) > 100)[0]
    red_rows = np.nonzero(red.sum(axis=1) > 100)[0]
    col_of = lambda x: red_cols.min() + (x + 2.0) / 4.0 * (red_cols.max() - red_cols.min())  # noqa: E731
    row_of = lambda z: red_rows.max() - (z + 0.05) / 2.05 * (red_rows.max() - red_rows.min())  # noqa: E731
    top, bottom, left, right = _orange_box(frame)
    assert (left, right) == (pytest.approx(col_of(-1.0), abs=2.5), pytest.approx(col_of(1.0), abs=2.5))
    assert (top, bottom) == (pytest.approx(row_of(1.75), abs=2.5), pytest.approx(row_of(0.25), abs=2.5))
    # The values are read from params: tightening b moves the lines.
    params = env.default_params
    c0 = params.constraints[0]
    tight = params.replace(constraints=(c0.replace(b=c0.b.at[0].set(0.5)), params.constraints[1]))  # x <= 0.5
    _, _, left2, right2 = _orange_box(render_frame(env, x, params=tight))
    assert left2 == left and right2 == pytest.approx(col_of(0.5), abs=2.5)


def test_cartpole_track_constraint_is_a_pair_of_dashed_lines():
    env = scg_jax.make("cartpole", constraints=[{"type": "abs_bound", "on": "state", "active_dims": [0], "bound": 1.2}])
    frame = render_frame(env, np.zeros(4))
    cart_col = _cart(frame)[1]
    per_metre = _cart(render_frame(env, np.array([1.0, 0, 0, 0])))[1] - cart_col
    _, _, left, right = _orange_box(frame)
    assert left == pytest.approx(cart_col - 1.2 * per_metre, abs=2.5)
    assert right == pytest.approx(cart_col + 1.2 * per_metre, abs=2.5)


def _sweep_states(num_steps, num_envs):
    xs = np.zeros((num_steps, num_envs, 6))
    xs[:, :, 0] = np.linspace(-1.0, 1.0, num_steps)[:, None] + 0.1 * np.arange(num_envs)
    xs[:, :, 2] = 1.0
    xs[:, :, 4] = np.linspace(-0.3, 0.3, num_steps)[:, None]
    return xs


def test_animate_writes_a_gif_with_one_frame_per_stride(envs, tmp_path):
    env = envs["quadrotor_2d"]
    xs = _sweep_states(23, 3)
    path = animate(env, xs, tmp_path / "sub" / "run.gif", width=200, height=160, stride=2)
    assert path == tmp_path / "sub" / "run.gif"
    with Image.open(path) as image:
        assert image.n_frames == 12 and image.size == (200, 160)
        assert image.info["duration"] == 40  # real time: 50 Hz control, every 2nd step -> 25 fps
    frames = iio.imread(path, index=None)
    assert frames.shape == (12, 160, 200, 3)
    # The GIF holds the rendered frames up to its 256-colour palette.
    rendered = np.stack(list(animation_frames(env, xs, width=200, height=160, stride=2)))
    error = np.abs(frames.astype(int) - rendered).max(axis=-1)
    assert error.mean() < 0.5 and np.percentile(error, 99.9) <= 16
    assert np.array_equal(frames[:, 0, 0], np.full((12, 3), 255))  # white stays exactly white
    assert [p.name for p in path.parent.iterdir()] == ["run.gif"]  # no temporary file left behind


@pytest.mark.filterwarnings("ignore:os.fork:RuntimeWarning")  # the ffmpeg readers start a subprocess
def test_animate_writes_an_mp4_with_the_right_frame_count(envs, tmp_path):
    env = envs["quadrotor_2d"]
    path = animate(env, _sweep_states(17, 2)[:, 0], tmp_path / "run.mp4", width=161, height=121, fps=10)
    num_frames, seconds = imageio_ffmpeg.count_frames_and_secs(str(path))
    assert num_frames == 17 and seconds == pytest.approx(1.7, abs=0.11)
    first = next(iio.imiter(path, plugin="FFMPEG"))
    assert first.shape == (122, 162, 3)  # odd sizes padded to even for yuv420p


def test_animate_rejects_other_suffixes_by_name(envs, tmp_path):
    for name in ("run.png", "run", "run.avi"):
        with pytest.raises(ValueError, match=r"\.gif, \.mp4"):
            animate(envs["cartpole"], np.zeros((3, 4)), tmp_path / name)
    assert list(tmp_path.iterdir()) == []


def test_animate_a_trajectory_and_a_saved_rollout(tmp_path):
    env = scg_jax.make("cartpole", episode_len_sec=1.0)

    def policy(obs, state, params, key):
        return jnp.array([10.0])  # push right: the pole falls back and every copy terminates early

    traj = scg_jax.make_rollout(env, policy, 3, auto_reset=False)(jax.random.key(0), env.default_params)
    lengths = episode_lengths(traj.terminated, traj.truncated)
    assert lengths.max() < env.num_steps
    path = animate(env, traj, tmp_path / "traj.gif", width=240, height=160, stride=1, trail=0.0)
    frames = iio.imread(path, index=None)
    assert frames.shape[0] == env.num_steps

    # After its first episode a copy is frozen and greyed: neutral grey pixels (the three carts overlap).
    def grey(frame):
        f = frame.astype(int)
        neutral = (np.ptp(f, axis=-1) <= 4) & (f[..., 0] >= 150) & (f[..., 0] <= 200)
        return neutral.sum()

    assert grey(frames[0]) < 50 and grey(frames[-1]) > 300  # a cart is about 20 x 12 px at this size
    # The same data through the npz of `scg-jax rollout` (system and task rebuild the env; dt sets the speed).
    data = {
        "x": np.asarray(traj.x),
        "x_ref": np.zeros((env.num_steps + 1, 4)),
        "dt": np.float64(0.04),
        "terminated": np.asarray(traj.terminated),
        "truncated": np.asarray(traj.truncated),
        "system": np.asarray("cartpole"),
        "task": np.asarray("stabilization"),
    }
    np.savez(tmp_path / "rollout.npz", **data)
    out = animate_rollout_file(tmp_path / "rollout.npz", tmp_path / "file.gif", width=240, height=160, stride=1)
    with Image.open(out) as image:
        assert image.n_frames == env.num_steps and image.info["duration"] == 40


def test_animate_checks_its_arguments(envs, tmp_path):
    env = envs["cartpole"]
    with pytest.raises(ValueError, match="xs: expected shape"):
        animate(env, np.zeros((3, 6)), tmp_path / "a.gif")
    with pytest.raises(ValueError, match="stride"):
        animate(env, np.zeros((3, 4)), tmp_path / "a.gif", stride=0)
    with pytest.raises(ValueError, match="x: expected shape"):
        render_frame(env, np.zeros(6))
    with pytest.raises(ValueError, match="width"):
        render_frame(env, np.zeros(4), width=0)
