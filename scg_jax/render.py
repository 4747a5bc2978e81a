"""Headless rendering: RGB frames of a state and GIF/MP4 animations of (batched) rollouts.

Everything is drawn with matplotlib's Agg canvas (no display, no pyplot state), deterministically: the same
input gives the same pixels. One figure is kept per ``(env, width, height)``; the static part of a view (axes,
failure bounds, constraint boundaries, reference, goal) is drawn once into a background and reused while it is
unchanged, and each frame only redraws the moving bodies on top of it.

Views (world z up, lengths in m, equal scale on every axis):

- ``cartpole``: side view of the track (x to the right). The cart is a 0.5 m x 0.3 m box centred on the
  cart position, the pole a thick line of length ``2 * pole_half_length`` from the top of the cart, leaning
  towards +x for ``theta > 0``. The failure bounds ``|x| <= 2.4`` are solid red vertical lines.
- ``quadrotor_1d``: side view x-z; the body sits at height ``z`` (x = 0; an animation of several copies
  spaces them along x, which the 1D model does not have).
- ``quadrotor_2d``: side view x-z; the body is a bar along the body x axis ``(cos theta, -sin theta)`` with
  rotors at its ends (front, +x body, in red) and a short line along the thrust axis ``(sin theta, cos theta)``,
  so ``theta > 0`` tilts the thrust towards +x.
- ``quadrotor_3d``: mplot3d perspective; the body is an X of two arms with a rotor ring at each motor (front
  ones, motors 1 and 4, in red), rotated by ``R = Rz(psi) Ry(theta) Rx(phi)``, with its shadow on the floor.

The Crazyflie's arm (0.0397 m) would be under two pixels at these scales, so the quadrotors are drawn with a
``DRAWN_ARM`` = 0.15 m arm (rotor radius 0.06 m): the bodies are exaggerated about 4x; positions and angles are
exact. Quadrotor failure bounds (``|x|, |y| <= 2``, ``z`` in [-0.05, 2]) are the solid red box.

Constraint boundaries: every ``bounded``, ``abs_bound`` or ``default`` constraint on the state (or on the state
part of ``input_and_state``) that bounds a position coordinate is drawn as a dashed orange line or box, with the
values in ``params.constraints[i]`` (``A z - b``: a row ``+e_j`` is an upper bound ``b``, ``-e_j`` a lower bound
``-b``). The reference path is dashed black; a stabilization goal is a black cross (a triangle under the
cart-pole's track).
"""

from __future__ import annotations

import math
import os
import threading
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.collections import LineCollection, PolyCollection
from matplotlib.colors import to_rgba
from matplotlib.figure import Figure
from matplotlib.ticker import MaxNLocator

from scg_jax.caching import CompileCache, jitted_method
from scg_jax.video import MAX_GIF_FPS, SUFFIXES, write_gif, write_mp4

__all__ = ["DRAWN_ARM", "SUFFIXES", "VIEWS", "animate", "animate_rollout_file", "animation_frames", "render_frame"]

DRAWN_ARM = 0.15  # m: drawn quadrotor arm (centre to motor); the real one is 0.0397 m
DRAWN_ROTOR = 0.06  # m: drawn rotor radius
CART_WIDTH, CART_HEIGHT = 0.5, 0.3  # m
_CART_RAIL = -0.5 * CART_HEIGHT - 0.04  # drawing height of the rail (the cart's centre is at 0)
_CART_REF_Y = _CART_RAIL - 0.12  # drawing height of the cart-pole's reference and goal, under the rail

_COPY_COLORS = ("#1f77b4", "#2ca02c", "#9467bd", "#8c564b", "#e377c2", "#17becf", "#bcbd22", "#393b79")
_FRONT_COLOR = "#d62728"
_BOUND_COLOR = "#c00000"
_CONSTRAINT_COLOR = "#ff8c00"
_ENDED_COLOR = "#a0a0a0"
_DPI = 100


# --------------------------------------------------------------------------------------------- scene data
@dataclass(frozen=True)
class _Static:
    """What the background shows; world coordinates (x, y, z), NaN where a system has no such axis."""

    ref: np.ndarray | None  # (M, 3) reference path
    goal: np.ndarray | None  # (3,)
    fail_lo: np.ndarray  # (3,) failure bounds, +-inf where unbounded
    fail_hi: np.ndarray
    boxes: tuple  # ((lo (3,), hi (3,)), ...) constraint bounds, +-inf where unbounded
    reach: float  # cart-pole: the longest pole, m
    title: str

    def key(self) -> tuple:
        arrays = [self.fail_lo, self.fail_hi, *[a for box in self.boxes for a in box]]
        ref = None if self.ref is None else self.ref.tobytes()
        goal = None if self.goal is None else self.goal.tobytes()
        return (ref, goal, tuple(a.tobytes() for a in arrays), self.reach, self.title)


@dataclass
class _Frame:
    """One frame: the copies' states and how to draw them."""

    states: np.ndarray  # (N, nx)
    colors: list  # N colours
    alpha: float
    pole_half_length: np.ndarray  # (N,) cart-pole only
    trails: list | None = None  # N arrays (K, nx) of past states, oldest first
    ref_point: np.ndarray | None = None  # (nx,) current reference state
    text: str = ""


def _darker(color, factor: float = 0.55):
    r, g, b, a = to_rgba(color)
    return (r * factor, g * factor, b * factor, a)


# Every colour the views draw with: the GIF writer keeps them (and their blends over white) exact.
_KEY_COLORS = (
    *_COPY_COLORS,
    *(_darker(c) for c in _COPY_COLORS),
    *(_darker(c, 0.75) for c in _COPY_COLORS),
    _FRONT_COLOR,
    _BOUND_COLOR,
    _CONSTRAINT_COLOR,
    _ENDED_COLOR,
    "black",
)


def _with_alpha(color, alpha: float):
    r, g, b, _ = to_rgba(color)
    return (r, g, b, alpha)


def _world(system, x: np.ndarray) -> np.ndarray:
    """World positions (..., 3) of states (..., nx); NaN on the axes the system does not have."""
    out = np.full((*x.shape[:-1], 3), np.nan)
    for axis, pos_index, _ in system.tracking_axes:
        out[..., axis] = x[..., pos_index]
    return out


def _nanmin(values) -> float:
    return float(np.nanmin(values)) if np.any(np.isfinite(values)) else np.nan


def _nanmax(values) -> float:
    return float(np.nanmax(values)) if np.any(np.isfinite(values)) else np.nan


def _np(value) -> np.ndarray:
    """``value`` (numpy, JAX or a number) as a float64 numpy array."""
    return np.asarray(value, dtype=np.float64)


def _state_bounds_world(system, low, high) -> tuple[np.ndarray, np.ndarray]:
    lo, hi = np.full(3, -np.inf), np.full(3, np.inf)
    for axis, pos_index, _ in system.tracking_axes:
        lo[axis], hi[axis] = low[pos_index], high[pos_index]
    return lo, hi


def _constraint_boxes(system, specs, constraint_params) -> tuple:
    """Position bounds ``(lo (3,), hi (3,))`` of the bounded/abs_bound/default state constraints."""
    world_of = {pos_index: axis for axis, pos_index, _ in system.tracking_axes}
    boxes = []
    for spec, values in zip(specs, constraint_params, strict=True):
        if spec.form != "linear" or spec.type not in ("bounded", "abs_bound", "default") or spec.on == "input":
            continue
        A, b = _np(values.A), _np(values.b)
        if A.ndim == 3:  # batched params: the first copy's bounds
            A, b = A[0], b[0]
        lo, hi = np.full(3, -np.inf), np.full(3, np.inf)
        found = False
        for row, bound in zip(A, b, strict=True):
            (nonzero,) = np.nonzero(row)
            if len(nonzero) != 1:
                continue
            dim = spec.active_dims[nonzero[0]]
            if dim not in world_of:  # not a position (or an input entry of input_and_state)
                continue
            value = bound / row[nonzero[0]]
            axis = world_of[dim]
            if row[nonzero[0]] > 0:
                hi[axis] = min(hi[axis], value)
            else:
                lo[axis] = max(lo[axis], value)
            found = True
        if found:
            boxes.append((lo, hi))
    return tuple(boxes)


# --------------------------------------------------------------------------------------------- scenes
class _Scene:
    """A cached figure for one view and size: a background of static artists, and the moving ones drawn on it.

    The figure, the title and time labels and the background cache live here; what is drawn is the ``view``'s
    (``_PlanarView`` with a body, or ``_Quadrotor3DView``), which implements ``build(scene)``,
    ``draw_static(scene, static)``, ``update(scene, frame)`` and ``draw_artist(fig, artist)``.
    """

    def __init__(self, view, width: int, height: int):
        self.view = view
        self.width, self.height = width, height
        self.scale = s = min(width, height) / 480.0
        # A hair over the size so the Agg buffer's int() truncation never loses a pixel row or column.
        self.fig = Figure(figsize=((width + 0.01) / _DPI, (height + 0.01) / _DPI), dpi=_DPI, facecolor="white")
        self.canvas = FigureCanvasAgg(self.fig)
        self.lock = threading.Lock()
        self.static_key = None
        self.background = None
        self.static_artists: list = []
        self.dynamic: list = []
        self.title = self.fig.text(0.5, 1 - 6 * s / height, "", ha="center", va="top", fontsize=9 * s)
        self.text = self.fig.text(
            8 * s / width, 1 - 6 * s / height, "", ha="left", va="top", fontsize=8 * s, animated=True,
            family="monospace",
        )  # fmt: skip
        view.build(self)

    def render(self, static: _Static, frame: _Frame) -> np.ndarray:
        with self.lock:
            key = static.key()
            if key != self.static_key:
                for artist in self.static_artists:
                    artist.remove()
                self.static_artists = []
                self.title.set_text(static.title)
                self.view.draw_static(self, static)
                self.canvas.draw()
                self.background = self.canvas.copy_from_bbox(self.fig.bbox)
                self.static_key = key
            self.canvas.restore_region(self.background)
            self.view.update(self, frame)
            self.text.set_text(frame.text)
            for artist in self.dynamic:
                self.view.draw_artist(self.fig, artist)
            self.fig.draw_artist(self.text)
            buffer = np.asarray(self.canvas.buffer_rgba())
            return np.array(buffer[: self.height, : self.width, :3])


# ------------------------------------------------------------------------------------------ planar view
def _bound_segments(lo, hi, xlim, zlim) -> list:
    """Segments of the finite x and z bounds of a box, each spanning the other axis's bounds (or the view)."""

    def span(a, b, limits):
        return (a if np.isfinite(a) else limits[0] - 1, b if np.isfinite(b) else limits[1] + 1)

    segments = []
    z_span, x_span = span(lo[2], hi[2], zlim), span(lo[0], hi[0], xlim)
    segments += [[(v, z_span[0]), (v, z_span[1])] for v in (lo[0], hi[0]) if np.isfinite(v)]
    segments += [[(x_span[0], v), (x_span[1], v)] for v in (lo[2], hi[2]) if np.isfinite(v)]
    return segments


def _planar_limits(static: _Static) -> tuple[tuple[float, float], tuple[float, float]]:
    """World x and z ranges that hold the failure bounds, the constraint boxes and the reference, padded."""
    xs = [static.fail_lo[0], static.fail_hi[0]]
    zs = [static.fail_lo[2], static.fail_hi[2]]
    for lo, hi in static.boxes:
        xs += [lo[0], hi[0]]
        zs += [lo[2], hi[2]]
    if static.ref is not None:
        xs += [_nanmin(static.ref[:, 0]), _nanmax(static.ref[:, 0])]
        zs += [_nanmin(static.ref[:, 2]), _nanmax(static.ref[:, 2])]
    xs = [v for v in xs if np.isfinite(v) and abs(v) < 50]  # ignore missing axes and far-off bounds
    zs = [v for v in zs if np.isfinite(v) and abs(v) < 50]
    pad = 0.2
    return (min(xs, default=-1.0) - pad, max(xs, default=1.0) + pad), (
        min(zs, default=0.0) - pad,
        max(zs, default=2.0) + pad,
    )


def _ground(ax, static: _Static, xlim, zlim, s) -> list:
    """The floor under the lower z failure bound, if there is one."""
    if not np.isfinite(static.fail_lo[2]):
        return []
    return [ax.fill_between(xlim, zlim[0], static.fail_lo[2], color="#e8e4dc", zorder=0, lw=0)]


def _path_and_goal(ax, static: _Static, s) -> list:
    """The reference path (dashed) and the stabilization goal (a cross) in the x-z plane."""
    artists = []
    if static.ref is not None:
        artists += ax.plot(static.ref[:, 0], static.ref[:, 2], "--", color="black", lw=1.1 * s)
    if static.goal is not None:
        artists += ax.plot([static.goal[0]], [static.goal[2]], "x", color="black", ms=9 * s, mew=2 * s, zorder=3)
    return artists


class _PlanarView:
    """Side view, world x to the right and world z up, with equal scale; the moving bodies are the ``body``'s.

    A body (``_CartPoleBody``, ``_PlanarQuadrotorBody``) provides ``below`` (share of the vertical room added
    for equal scaling that goes under the content), ``hide_ticks`` (``"left"``, ``"bottom"`` or None),
    ``limits(static)``, ``ground(ax, static, xlim, zlim, s)``, ``reference(ax, static, s)``,
    ``shapes(frame, s) -> (segments, colors, widths, boxes, faces, edges)``, ``trail(frame, i) -> (K, 2)`` and
    ``ref_marker(frame, ref) -> (xs, zs)``.
    """

    def __init__(self, body):
        self.body = body

    def build(self, scene: _Scene) -> None:
        s, w, h = scene.scale, scene.width, scene.height
        left, bottom, right, top = 40 * s, 26 * s, 10 * s, 24 * s
        self.ax = ax = scene.fig.add_axes((left / w, bottom / h, 1 - (left + right) / w, 1 - (bottom + top) / h))
        self.box_ratio = (w - left - right) / (h - bottom - top)  # width / height of the axes in pixels
        ax.tick_params(labelsize=7 * s, length=3 * s, pad=2 * s)
        if self.body.hide_ticks == "left":  # the cart-pole's drawing height is not a coordinate of the model
            ax.tick_params(left=False, labelleft=False)
        elif self.body.hide_ticks == "bottom":  # the 1D quadrotor has no x
            ax.tick_params(bottom=False, labelbottom=False)
        ax.grid(alpha=0.25, lw=0.6 * s)
        ax.set_axisbelow(True)
        self.trails = LineCollection([], animated=True, linewidths=1.0 * s)
        self.bodies = LineCollection([], animated=True, capstyle="round")
        self.boxes = PolyCollection([], animated=True)
        self.ref_marker = ax.plot([], [], "o", ms=6 * s, mfc="none", mec="black", mew=1.2 * s, animated=True)[0]
        for artist in (self.trails, self.boxes, self.bodies):
            ax.add_collection(artist, autolim=False)
        scene.dynamic = [self.trails, self.boxes, self.bodies, self.ref_marker]

    def draw_static(self, scene: _Scene, static: _Static) -> None:
        ax, s = self.ax, scene.scale
        (x0, x1), (z0, z1) = self.body.limits(static)
        # Equal scale on both axes: widen whichever range is short for the axes' pixel aspect.
        if (x1 - x0) / (z1 - z0) < self.box_ratio:
            extra = (z1 - z0) * self.box_ratio - (x1 - x0)
            x0, x1 = x0 - 0.5 * extra, x1 + 0.5 * extra
        else:
            extra = (x1 - x0) / self.box_ratio - (z1 - z0)
            z0, z1 = z0 - self.body.below * extra, z1 + (1 - self.body.below) * extra
        ax.set_xlim(x0, x1)
        ax.set_ylim(z0, z1)
        add = scene.static_artists.extend
        add(self.body.ground(ax, static, (x0, x1), (z0, z1), s))
        # Failure bounds (solid red) and constraint boundaries (dashed orange): a line per finite bound.
        segments = _bound_segments(static.fail_lo, static.fail_hi, (x0, x1), (z0, z1))
        add([ax.add_collection(LineCollection(segments, colors=_BOUND_COLOR, linewidths=1.6 * s, zorder=2))])
        for lo, hi in static.boxes:
            dashed = LineCollection(
                _bound_segments(lo, hi, (x0, x1), (z0, z1)), colors=_CONSTRAINT_COLOR, linewidths=1.6 * s,
                linestyles=(0, (5, 3)), zorder=2,
            )  # fmt: skip
            add([ax.add_collection(dashed)])
        add(self.body.reference(ax, static, s))

    def update(self, scene: _Scene, frame: _Frame) -> None:
        segments, colors, widths, boxes, faces, edges = self.body.shapes(frame, scene.scale)
        self.bodies.set_segments(segments)
        self.bodies.set_colors(colors)
        self.bodies.set_linewidths(widths)
        self.boxes.set_verts(boxes)
        if boxes:
            self.boxes.set_facecolors(faces)
            self.boxes.set_edgecolors(edges)
            self.boxes.set_linewidths(1.0 * scene.scale)
        trails, trail_colors = [], []
        if frame.trails is not None:
            for i, color in enumerate(frame.colors):
                points = self.body.trail(frame, i)
                if len(points) > 1:
                    trails.append(points)
                    trail_colors.append(_with_alpha(color, 0.45))
        self.trails.set_segments(trails)
        self.trails.set_colors(trail_colors)
        if frame.ref_point is None:
            self.ref_marker.set_data([], [])
        else:
            self.ref_marker.set_data(*self.body.ref_marker(frame, frame.ref_point))

    @staticmethod
    def draw_artist(fig, artist) -> None:
        fig.draw_artist(artist)


class _CartPoleBody:
    """The cart (a box centred on x) and the pole from the top of the cart, on a rail; reference under the rail."""

    below = 0.25
    hide_ticks = "left"

    @staticmethod
    def limits(static):
        (x0, x1), _ = _planar_limits(static)
        return (min(x0, -1.0), max(x1, 1.0)), (_CART_REF_Y - 0.25, 0.5 * CART_HEIGHT + 2 * static.reach + 0.2)

    @staticmethod
    def ground(ax, static, xlim, zlim, s):
        return ax.plot(xlim, [_CART_RAIL] * 2, color="#606060", lw=2.5 * s, zorder=1)

    @staticmethod
    def reference(ax, static, s):
        artists = []
        if static.ref is not None:
            span = [_nanmin(static.ref[:, 0]), _nanmax(static.ref[:, 0])]
            artists += ax.plot(span, [_CART_REF_Y] * 2, "--", color="black", lw=1.1 * s)
        if static.goal is not None:
            artists += ax.plot([static.goal[0]], [_CART_REF_Y], "^", color="black", ms=7 * s, zorder=3)
        return artists

    @staticmethod
    def shapes(frame, s):
        w, h = 0.5 * CART_WIDTH, 0.5 * CART_HEIGHT
        poles, pole_colors, carts, faces, edges = [], [], [], [], []
        for state, color, length in zip(frame.states, frame.colors, frame.pole_half_length, strict=True):
            x, theta = state[0], state[2]
            carts.append([(x - w, -h), (x + w, -h), (x + w, h), (x - w, h)])
            faces.append(_with_alpha(color, frame.alpha))
            edges.append(_with_alpha(_darker(color, 0.75), frame.alpha))
            hinge = np.array([x, h])
            poles.append([hinge, hinge + 2 * length * np.array([np.sin(theta), np.cos(theta)])])
            pole_colors.append(_with_alpha(_darker(color), frame.alpha))
        return poles, pole_colors, 5.0 * s, carts, faces, edges

    @staticmethod
    def trail(frame, i):  # the pole's tip
        trail, length = frame.trails[i], frame.pole_half_length[i]
        tip_x = trail[:, 0] + 2 * length * np.sin(trail[:, 2])
        return np.stack([tip_x, 0.5 * CART_HEIGHT + 2 * length * np.cos(trail[:, 2])], axis=-1)

    @staticmethod
    def ref_marker(frame, ref):
        return [ref[0]], [_CART_REF_Y]


def _side_offsets(n: int) -> np.ndarray:
    """x positions of n 1D quadrotors side by side (the 1D model has no x)."""
    if n == 1:
        return np.zeros(1)
    return min(0.45, 1.6 / (n - 1)) * (np.arange(n) - 0.5 * (n - 1))


class _PlanarQuadrotorBody:
    """A quadrotor in side view: a bar along the body x axis with rotors at its ends (front, +x body, in red) and
    a short line along the thrust axis. ``one_d``: the 1D quadrotor (state ``[z, z_dot]``), drawn level at
    height z, several copies side by side; else the 2D one (``[x, x_dot, z, z_dot, theta, theta_dot]``)."""

    def __init__(self, one_d: bool):
        self.one_d = one_d
        self.below = 0.2
        self.hide_ticks = "bottom" if one_d else None

    def _poses(self, frame):
        """(N, 3): x, z, theta of each copy."""
        states = np.asarray(frame.states)
        if self.one_d:
            return np.stack([_side_offsets(len(states)), states[:, 0], np.zeros(len(states))], axis=-1)
        return states[:, [0, 2, 4]]

    def limits(self, static):
        (x0, x1), z = _planar_limits(static)
        return ((min(x0, -0.8), max(x1, 0.8)), z) if self.one_d else ((x0, x1), z)

    @staticmethod
    def ground(ax, static, xlim, zlim, s):
        return _ground(ax, static, xlim, zlim, s)

    def reference(self, ax, static, s):
        if not self.one_d:
            return _path_and_goal(ax, static, s)
        artists = []
        if static.ref is not None:
            z = static.ref[:, 2]
            artists += ax.plot([0.0, 0.0], [_nanmin(z), _nanmax(z)], "--", color="black", lw=1.1 * s)
        if static.goal is not None:
            artists += ax.plot([-0.85, 0.85], [static.goal[2]] * 2, ":", color="black", lw=1.1 * s, zorder=1)
            artists += ax.plot([0.0], [static.goal[2]], "x", color="black", ms=9 * s, mew=2 * s, zorder=3)
        return artists

    def shapes(self, frame, s):
        segments, colors, widths = [], [], []
        for (x, z, theta), color in zip(self._poses(frame), frame.colors, strict=True):
            center = np.array([x, z])
            body_x = np.array([np.cos(theta), -np.sin(theta)])
            body_z = np.array([np.sin(theta), np.cos(theta)])  # theta > 0 tilts the thrust towards +x
            front, back = center + DRAWN_ARM * body_x, center - DRAWN_ARM * body_x
            body_color = _with_alpha(color, frame.alpha)
            segments += [[back, front], [center, center + 0.09 * body_z]]
            colors += [body_color, _with_alpha(_darker(color), frame.alpha)]
            widths += [4.0 * s, 1.8 * s]
            for end, rotor_color in ((front, _FRONT_COLOR), (back, _darker(color))):
                hub = end + 0.035 * body_z
                segments += [[end, hub], [hub - DRAWN_ROTOR * body_x, hub + DRAWN_ROTOR * body_x]]
                colors += [body_color, _with_alpha(rotor_color, frame.alpha)]
                widths += [1.6 * s, 2.6 * s]
        return segments, colors, widths, [], [], []

    def trail(self, frame, i):
        trail = frame.trails[i]
        if self.one_d:
            return np.stack([np.full(len(trail), _side_offsets(len(frame.states))[i]), trail[:, 0]], axis=-1)
        return np.stack([trail[:, 0], trail[:, 2]], axis=-1)

    def ref_marker(self, frame, ref):
        if self.one_d:  # the current reference height, across every copy
            offsets = _side_offsets(len(frame.states))
            return offsets, np.full(len(offsets), ref[0])
        return [ref[0]], [ref[2]]


# ------------------------------------------------------------------------------------------ 3D view
def _rotation(phi, theta, psi) -> np.ndarray:
    """``R = Rz(psi) Ry(theta) Rx(phi)``, body to world."""
    cf, sf, ct, st, cp, sp = np.cos(phi), np.sin(phi), np.cos(theta), np.sin(theta), np.cos(psi), np.sin(psi)
    rx = np.array([[1, 0, 0], [0, cf, -sf], [0, sf, cf]])
    ry = np.array([[ct, 0, st], [0, 1, 0], [-st, 0, ct]])
    rz = np.array([[cp, -sp, 0], [sp, cp, 0], [0, 0, 1]])
    return rz @ ry @ rx


_D = DRAWN_ARM / math.sqrt(2.0)
_MOTORS = np.array([[_D, _D, 0.0], [-_D, _D, 0.0], [-_D, -_D, 0.0], [_D, -_D, 0.0]])  # 1 FL, 2 BL, 3 BR, 4 FR
_RING = np.stack(
    [DRAWN_ROTOR * np.cos(np.linspace(0, 2 * np.pi, 17)), DRAWN_ROTOR * np.sin(np.linspace(0, 2 * np.pi, 17))], -1
)


class _Quadrotor3DView:
    """mplot3d perspective of the 3D quadrotor: an X of two arms with a rotor ring per motor, and its shadow."""

    def build(self, scene: _Scene) -> None:
        from mpl_toolkits.mplot3d import Axes3D  # noqa: F401  (registers the projection)
        from mpl_toolkits.mplot3d.art3d import Line3DCollection

        s = scene.scale
        self.ax = scene.fig.add_axes((-0.02, -0.1, 1.04, 1.08), projection="3d")
        self.ax.view_init(elev=24, azim=-58)
        self.ax.set_proj_type("persp", focal_length=1.5)
        for axis in (self.ax.xaxis, self.ax.yaxis, self.ax.zaxis):
            axis.set_major_locator(MaxNLocator(5, steps=[1, 2, 5, 10]))
        self.ax.tick_params(labelsize=6.5 * s, pad=0)
        for axis, name in zip((self.ax.xaxis, self.ax.yaxis, self.ax.zaxis), "xyz", strict=True):
            axis.set_label_text(f"{name} [m]", fontsize=7.5 * s)
            axis.labelpad = -4 * s
        self._Line3DCollection = Line3DCollection
        self.trails = Line3DCollection([], animated=True, linewidths=1.0 * s)
        self.shadows = Line3DCollection([], animated=True, linewidths=1.6 * s, colors=[(0, 0, 0, 0.22)])
        self.bodies = Line3DCollection([], animated=True, capstyle="round")
        for artist in (self.trails, self.shadows, self.bodies):
            self.ax.add_collection3d(artist, autolim=False)
        self.ref_marker = self.ax.plot([], [], [], "o", ms=6 * s, mfc="none", mec="black", mew=1.2 * s)[0]
        self.ref_marker.set_animated(True)
        scene.dynamic = [self.shadows, self.trails, self.bodies, self.ref_marker]
        self.floor = 0.0

    @staticmethod
    def draw_artist(fig, artist) -> None:
        if hasattr(artist, "do_3d_projection"):
            artist.do_3d_projection()
        fig.draw_artist(artist)

    @staticmethod
    def _box_edges(lo, hi) -> list:
        corners = [(i, j, k) for i in (0, 1) for j in (0, 1) for k in (0, 1)]
        bounds = np.stack([lo, hi])
        edges = []
        for a in corners:
            for b in corners:
                if a < b and sum(x != y for x, y in zip(a, b, strict=True)) == 1:
                    edges.append([[bounds[c, d] for d, c in enumerate(a)], [bounds[c, d] for d, c in enumerate(b)]])
        return edges

    def draw_static(self, scene: _Scene, static: _Static) -> None:
        ax, s = self.ax, scene.scale
        lows = [static.fail_lo, *(lo for lo, _ in static.boxes)]
        highs = [static.fail_hi, *(hi for _, hi in static.boxes)]
        if static.ref is not None:
            lows.append(np.nanmin(static.ref, axis=0))
            highs.append(np.nanmax(static.ref, axis=0))
        stack_lo = np.where(np.isfinite(lows) & (np.abs(lows) < 50), lows, np.nan)
        stack_hi = np.where(np.isfinite(highs) & (np.abs(highs) < 50), highs, np.nan)
        lo = np.nan_to_num(np.nanmin(np.concatenate([stack_lo, stack_hi]), axis=0), nan=-1.0)
        hi = np.nan_to_num(np.nanmax(np.concatenate([stack_lo, stack_hi]), axis=0), nan=1.0)
        lo, hi = np.minimum(lo, hi - 0.5), np.maximum(hi, lo + 0.5)
        ax.set_xlim(lo[0], hi[0])
        ax.set_ylim(lo[1], hi[1])
        ax.set_zlim(lo[2], hi[2])
        ax.set_box_aspect(tuple(hi - lo), zoom=0.92)
        self.floor = lo[2]
        # The failure box (solid red) and the constraint boxes (dashed orange), unbounded sides at the view's edge.
        styles = [{"colors": _BOUND_COLOR, "linewidths": 1.3 * s}] + [
            {"colors": _CONSTRAINT_COLOR, "linewidths": 1.4 * s, "linestyles": (0, (5, 3))} for _ in static.boxes
        ]
        for (box_lo, box_hi), style in zip([(static.fail_lo, static.fail_hi), *static.boxes], styles, strict=True):
            edges = self._box_edges(
                np.where(np.isfinite(box_lo), box_lo, lo), np.where(np.isfinite(box_hi), box_hi, hi)
            )
            scene.static_artists.append(ax.add_collection3d(self._Line3DCollection(edges, **style), autolim=False))
        if static.ref is not None:
            ref = np.nan_to_num(static.ref)
            scene.static_artists += ax.plot(ref[:, 0], ref[:, 1], ref[:, 2], "--", color="black", lw=1.1 * s)
            scene.static_artists += ax.plot(
                ref[:, 0], ref[:, 1], np.full(len(ref), self.floor), "-", color="black", lw=0.8 * s, alpha=0.18
            )
        if static.goal is not None:
            goal = np.nan_to_num(static.goal)
            scene.static_artists += ax.plot([goal[0]], [goal[1]], [goal[2]], "x", color="black", ms=9 * s, mew=2 * s)
            scene.static_artists += ax.plot(
                [goal[0]] * 2, [goal[1]] * 2, [goal[2], self.floor], ":", color="black", lw=1.0 * s, alpha=0.5
            )

    def update(self, scene: _Scene, frame: _Frame) -> None:
        s = scene.scale
        segments, colors, widths, shadows = [], [], [], []
        for state, color in zip(frame.states, frame.colors, strict=True):
            center = np.array([state[0], state[2], state[4]])
            rotation = _rotation(state[6], state[7], state[8])
            motors = center + _MOTORS @ rotation.T
            body_color = _with_alpha(color, frame.alpha)
            arms = [[motors[0], motors[2]], [motors[1], motors[3]]]
            segments += arms + [[center, center + 0.09 * rotation[:, 2]]]
            colors += [body_color, body_color, _with_alpha(_darker(color), frame.alpha)]
            widths += [3.0 * s, 3.0 * s, 1.6 * s]
            hub_offset = 0.03 * rotation[:, 2]
            for m, motor in enumerate(motors):
                ring = motor + hub_offset + np.c_[_RING, np.zeros(len(_RING))] @ rotation.T
                segments.append(ring)
                colors.append(_with_alpha(_FRONT_COLOR if m in (0, 3) else _darker(color), frame.alpha))
                widths.append(1.3 * s)
            for a, b in arms:
                shadows.append([[a[0], a[1], self.floor], [b[0], b[1], self.floor]])
            shadows.append([center, [center[0], center[1], self.floor]])  # drop line: where it is over the floor
        self.bodies.set_segments(segments)
        self.bodies.set_color(colors)
        self.bodies.set_linewidth(widths)
        self.shadows.set_segments(shadows)
        trails, trail_colors = [], []
        if frame.trails is not None:
            for trail, color in zip(frame.trails, frame.colors, strict=True):
                if len(trail) > 1:
                    trails.append(trail[:, [0, 2, 4]])
                    trail_colors.append(_with_alpha(color, 0.45))
        self.trails.set_segments(trails)
        self.trails.set_color(trail_colors)
        ref = frame.ref_point
        if ref is None:
            self.ref_marker.set_data_3d([], [], [])
        else:
            self.ref_marker.set_data_3d([ref[0]], [ref[2]], [ref[4]])


_VIEW_FACTORIES = {
    "cartpole": lambda: _PlanarView(_CartPoleBody()),
    "quadrotor_1d": lambda: _PlanarView(_PlanarQuadrotorBody(one_d=True)),
    "quadrotor_2d": lambda: _PlanarView(_PlanarQuadrotorBody(one_d=False)),
    "quadrotor_3d": _Quadrotor3DView,
}
VIEWS = tuple(_VIEW_FACTORIES)
"""The views a ``System.view`` may name."""
# A figure per env and size (drawing one costs more than the frames drawn on it) and the env's default params.
_SCENES = CompileCache(maxsize=16)


def _scene(env, width: int, height: int) -> _Scene:
    view = env.system.view
    if view not in _VIEW_FACTORIES:
        raise ValueError(
            f"render: system {env.system.name!r} asks for view {view!r}; allowed views are {', '.join(VIEWS)}"
        )
    return _SCENES.get((width, height), lambda: _Scene(_VIEW_FACTORIES[view](), width, height), owners=(env,))


def _default_params(env):
    return _SCENES.get("params", lambda: env.default_params, owners=(env,))


def _static(env, params, x_ref, title: str, reach: float) -> _Static:
    system = env.system
    low, high = _np(params.state_low), _np(params.state_high)
    if low.ndim == 2:
        low, high = low[0], high[0]
    fail_lo, fail_hi = _state_bounds_world(system, low, high)
    ref = goal = None
    if x_ref is not None:
        x_ref = _np(x_ref)
        if x_ref.ndim != 2 or x_ref.shape[1] != system.nx:
            raise ValueError(f"x_ref: expected shape (T + 1, {system.nx}), got {x_ref.shape}")
        ref = _world(system, x_ref)
    if env.task == "stabilization":
        goal_state = _np(params.goal)
        goal = _world(system, goal_state[0] if goal_state.ndim == 2 else goal_state)
    boxes = _constraint_boxes(system, env.constraint_specs, params.constraints)
    return _Static(ref, goal, fail_lo, fail_hi, boxes, float(reach), title)


def _pole_half_lengths(env, params, n: int) -> np.ndarray:
    if env.system.view != "cartpole":  # the only view that draws a length from params
        return np.zeros(n)
    length = _np(params.physics.pole_half_length)
    if length.ndim == 1 and length.shape[0] == n:
        return length
    return np.full(n, length.reshape(-1)[0])


def _check_size(width, height) -> tuple[int, int]:
    for name, value in (("width", width), ("height", height)):
        if isinstance(value, bool) or not float(value).is_integer() or not 16 <= value <= 4096:
            raise ValueError(f"{name}: expected an integer number of pixels in [16, 4096], got {value!r}")
    return int(width), int(height)


def render_frame(env, x, params=None, x_ref=None, width: int = 480, height: int = 480) -> np.ndarray:
    """An RGB image of one state.

    Args:
        env: an ``scg_jax.Env`` (its system picks the view; see the module docstring).
        x: (nx,) physical state, numpy or JAX.
        params: ``EnvParams`` for the goal, the failure bounds, the constraint values and the cart-pole's pole
            length (default: ``env.default_params``); a batched (sweep) params draws its first copy's values.
        x_ref: optional (T + 1, nx) reference (e.g. ``env.reference(params)[0]``), drawn dashed in the view's
            plane. A stabilization task always shows its goal (``params.goal``).
        width, height: image size in pixels.

    Returns:
        (height, width, 3) uint8 RGB array. The same arguments give the same pixels.
    """
    width, height = _check_size(width, height)
    params = _default_params(env) if params is None else params
    x = _np(x)
    if x.shape != (env.nx,):
        raise ValueError(f"x: expected shape ({env.nx},) for {env.system.name}, got {x.shape}")
    lengths = _pole_half_lengths(env, params, 1)
    static = _static(env, params, x_ref, f"{env.system.name} {env.task}", lengths.max())
    frame = _Frame(states=x[None], colors=[_COPY_COLORS[0]], alpha=1.0, pole_half_length=lengths)
    return _scene(env, width, height).render(static, frame)


# --------------------------------------------------------------------------------------------- animations
def _as_rollout(xs, x_ref, dt):
    """``(x (T, N, nx), x_ref, dt, first-episode lengths (N,) or None)`` from an array, Trajectory or npz dict."""
    lengths = None
    terminated = truncated = None
    if isinstance(xs, Mapping):
        data = xs
        xs = data["x"]
        if x_ref is None and "x_ref" in data:
            x_ref = data["x_ref"]
        if dt is None and "dt" in data:
            dt = float(data["dt"])
        terminated, truncated = data.get("terminated"), data.get("truncated")
    elif hasattr(xs, "x") and hasattr(xs, "terminated"):  # scg_jax.Trajectory
        terminated, truncated = xs.terminated, xs.truncated
        xs = xs.x
    x = _np(xs)
    if x.ndim == 2:
        x = x[:, None]
        terminated = truncated = None
    if terminated is not None and truncated is not None:
        from scg_jax.metrics import episode_lengths

        lengths = episode_lengths(np.asarray(terminated), np.asarray(truncated))
    return x, x_ref, dt, lengths


class _Animation:
    """A rollout prepared for drawing: ``frame(k)`` renders control step ``k``; ``steps`` are the drawn ones."""

    def __init__(
        self, env, xs, params=None, x_ref=None, *, max_copies: int = 8, width: int = 480, height: int = 480,
        stride: int | None = None, trail: float = 1.0, dt: float | None = None,
    ):  # fmt: skip
        self.width, self.height = _check_size(width, height)
        if isinstance(max_copies, bool) or not float(max_copies).is_integer() or max_copies < 1:
            raise ValueError(f"max_copies: expected a positive integer, got {max_copies!r}")
        params = _default_params(env) if params is None else params
        x, x_ref, dt, lengths = _as_rollout(xs, x_ref, dt)
        if x.ndim != 3 or x.shape[2] != env.nx or x.shape[0] == 0:
            raise ValueError(f"xs: expected shape (T, {env.nx}) or (T, N, {env.nx}) with T >= 1, got {x.shape}")
        self.dt = env.dt if dt is None else float(dt)
        if not (np.isfinite(self.dt) and self.dt > 0):
            raise ValueError(f"dt: expected a positive number, got {dt!r}")
        if x_ref is None and env.task == "tracking":
            x_ref = np.asarray(jitted_method(env, "reference")(params)[0])
        if stride is None:
            stride = max(1, math.ceil(1.0 / (self.dt * MAX_GIF_FPS) - 1e-9))
        if isinstance(stride, bool) or not float(stride).is_integer() or stride < 1:
            raise ValueError(f"stride: expected a positive integer, got {stride!r}")
        self.stride = int(stride)
        self.trail_steps = max(0, round(float(trail) / self.dt))
        num_steps, num_envs, _ = x.shape
        shown = min(int(max_copies), num_envs)
        self.x = x[:, :shown]
        self.steps = range(0, num_steps, self.stride)
        self.lengths = (
            np.full(shown, num_steps) if lengths is None else np.minimum(np.asarray(lengths)[:shown], num_steps)
        )
        self.pole = _pole_half_lengths(env, params, num_envs)[:shown]
        copies = f"{shown} of {num_envs} copies" if num_envs > 1 else "1 copy"
        self.static = _static(env, params, x_ref, f"{env.system.name} {env.task}, {copies}", self.pole.max())
        self.scene = _scene(env, self.width, self.height)
        self.ref = None if x_ref is None or env.task != "tracking" else _np(x_ref)
        self.alpha = 1.0 if shown == 1 else 0.75

    def frame(self, k: int) -> np.ndarray:
        shown = self.x.shape[1]
        rows = np.minimum(k, self.lengths - 1)  # a copy whose first episode ended stays at its last state, greyed
        colors = [_COPY_COLORS[i % len(_COPY_COLORS)] if k < self.lengths[i] else _ENDED_COLOR for i in range(shown)]
        trails = None
        if self.trail_steps > 0:
            trails = [self.x[max(0, r - self.trail_steps) : r + 1, i] for i, r in enumerate(rows)]
        frame = _Frame(
            states=self.x[rows, np.arange(shown)],
            colors=colors,
            alpha=self.alpha,
            pole_half_length=self.pole,
            trails=trails,
            ref_point=None if self.ref is None else self.ref[min(k, len(self.ref) - 1)],
            text=f"t = {k * self.dt:5.2f} s",
        )
        return self.scene.render(self.static, frame)

    def __iter__(self):
        return (self.frame(k) for k in self.steps)


def animation_frames(env, xs, params=None, x_ref=None, **options):
    """The frames ``animate`` writes, as an iterator of (height, width, 3) uint8 arrays (for video loggers).

    Arguments and ``options`` (``max_copies``, ``width``, ``height``, ``stride``, ``trail``, ``dt``) as for
    ``animate``; one frame per ``stride`` control steps, ``len(range(0, T, stride))`` in all.
    """
    return iter(_Animation(env, xs, params, x_ref, **options))


def animate(env, xs, path, params=None, x_ref=None, fps=None, **options) -> Path:
    """Write an animation of a rollout as a GIF or an MP4 (by the suffix of ``path``).

    Args:
        env: the ``scg_jax.Env`` the rollout came from.
        xs: states (T, nx), a batched rollout (T, N, nx), an ``scg_jax.Trajectory``, or the data dict of
            ``scg-jax rollout``'s npz (keys ``x``, ``x_ref``, ``dt``, ``terminated``, ``truncated``). With a
            Trajectory or a dict, a copy whose first episode ended is frozen at its last state and greyed (as in
            ``plot_rollout``).
        path: output file, ``.gif`` or ``.mp4``; written to a temporary file beside it and renamed, so it is
            whole or absent.
        params: ``EnvParams`` (default: ``env.default_params``); batched params give each cart-pole copy its own
            pole length.
        x_ref: (T + 1, nx) reference to draw (default: the dict's ``x_ref``, else ``env.reference(params)`` for
            tracking). Tracking also marks the current reference point (open circle).
        fps: frames per second (default: real time, ``1 / (dt * stride)``, i.e. ``env.ctrl_freq / stride``).
        options: keywords of the drawing.
            max_copies: draw the first this many copies, overlaid with some transparency (default 8).
            width, height: frame size in pixels (default 480 x 480).
            stride: draw every ``stride``-th step (default: the smallest stride that keeps real time at <= 50 fps).
            trail: seconds of past positions drawn behind each copy (pole tip for the cart-pole); 0 for none
                (default 1).
            dt: seconds per row of ``xs`` (default: the dict's ``dt``, else ``env.dt``).

    Returns:
        ``path`` as a ``Path``.

    Raises:
        ValueError: an unsupported suffix (allowed: .gif, .mp4) or inconsistent shapes.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in SUFFIXES:
        raise ValueError(f"path: unsupported suffix {path.suffix!r}; allowed suffixes are {', '.join(SUFFIXES)}")
    animation = _Animation(env, xs, params, x_ref, **options)
    fps = 1.0 / (animation.dt * animation.stride) if fps is None else float(fps)
    if not (np.isfinite(fps) and fps > 0):
        raise ValueError(f"fps: expected a positive number, got {fps!r}")
    if suffix == ".gif":
        steps = animation.steps
        sample = [animation.frame(steps[i]) for i in sorted({0, len(steps) // 2, len(steps) - 1})]
        write_gif(path, iter(animation), fps, sample, key_colors=_KEY_COLORS)
    else:
        write_mp4(path, iter(animation), fps, animation.width, animation.height)
    return path


def animate_rollout_file(npz_path, out_path, env=None, params=None, **kwargs) -> Path:
    """Animate the ``rollout.npz`` written by ``scg-jax rollout``.

    Unless ``env`` is given, the env is rebuilt from the file's ``config`` (the resolved YAML config the CLI
    stores, so constraints and bounds are drawn as they were), or for older files as ``scg_jax.make(system,
    task)``; the file's ``x_ref`` and ``dt`` are used either way.

    Args:
        npz_path: the ``.npz``. out_path: ``.gif`` or ``.mp4``. kwargs: as for ``animate``.
    """
    with np.load(os.fspath(npz_path), allow_pickle=False) as archive:
        data = {name: archive[name] for name in archive.files}
    if env is None:
        import scg_jax

        if "config" in data:
            env, file_params = scg_jax.make_from_config(scg_jax.load_config(str(data["config"])))
            params = file_params if params is None else params
        else:
            env = scg_jax.make(str(data["system"]), str(data["task"]))
    return animate(env, data, out_path, params=params, **kwargs)
