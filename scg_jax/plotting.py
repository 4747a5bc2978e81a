"""Plots of saved rollouts. Results are data first: everything here reads the arrays the CLI saves in
``rollout.npz`` (or the same keys in a dict) and never re-runs an environment.

Keys read (T control steps, N copies):

- ``t`` (T,): time of each row of ``x``, s; ``dt``: control period, s (optional, else ``t[1] - t[0]``).
- ``x`` (T, N, nx): state before each step; ``x_final`` (N, nx), optional: state after the last step.
- ``x_ref`` (T + 1, nx): reference at ``k dt``, k = 0..T.
- ``terminated``, ``truncated`` (T, N): cut each copy's curve at the end of its first episode.
- ``state_names`` (nx,), ``system``, ``task``.
- ``plane`` ("xz", ...) and ``plane_indices`` (2,), optional: the state indices of the position coordinates along
  the plane's two axes; when present, a spatial subplot of the path in that plane is added.
- ``x_low``, ``x_high`` (nx,), optional: constraint bounds of each state coordinate (``+-inf`` where none), drawn
  as red dotted lines (``scg_jax.constraints.box_bounds``) where they are near the data: within one data range
  of the traces and reference of that panel. A bound further away (e.g. the cart-pole's failure bound of 2.4 m
  under a controller that keeps the cart within centimetres) would squash the traces into a flat line; it is
  named in the panel title instead.
- ``u`` (T, N, nu), ``input_names`` (nu,), optional: the applied inputs, one more subplot each, with the input
  bounds ``u_low``, ``u_high`` (nu,) when present.
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping
from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.lines import Line2D

from scg_jax.files import write_atomic
from scg_jax.metrics import episode_lengths


def plane_indices(env) -> tuple[str, tuple[int, int]] | None:
    """The plane a path plot shows and the state indices of its two position coordinates, or ``None``.

    Derived from the system's record: systems whose position has fewer than two world axes
    (``System.path_plane is None``: the cart-pole, the 1D quadrotor) have no path plot. The plane is the env's
    trajectory plane when the system has both of its axes (a 2D quadrotor asked for ``xy`` falls back to its own
    ``default_plane``), else the system's ``path_plane``.
    """
    system = env.system
    if system.path_plane is None:
        return None
    position_index = {axis: pos for axis, pos, _ in system.tracking_axes}
    plane = getattr(env, "trajectory_plane", None) or system.path_plane
    if not all("xyz".index(letter) in position_index for letter in plane):
        plane = system.path_plane
    first, second = ("xyz".index(letter) for letter in plane)
    return plane, (position_index[first], position_index[second])


def _load(data) -> dict:
    if isinstance(data, Mapping):
        return dict(data)
    with np.load(os.fspath(data), allow_pickle=False) as archive:
        return {name: archive[name] for name in archive.files}


def _episode_paths(data: dict) -> tuple[np.ndarray, np.ndarray]:
    """Times (T + 1,) and states (T + 1, N, nx), NaN after each copy's first episode so lines stop there."""
    x = np.asarray(data["x"], dtype=np.float64)
    num_steps = x.shape[0]
    t = np.asarray(data["t"], dtype=np.float64)
    dt = float(data["dt"]) if "dt" in data else float(t[1] - t[0]) if num_steps > 1 else 1.0
    if "x_final" in data:
        x = np.concatenate([x, np.asarray(data["x_final"], dtype=np.float64)[None]], axis=0)
    else:  # without the final state the last step's outcome is unknown; show what there is
        x = np.concatenate([x, np.full_like(x[:1], np.nan)], axis=0)
    times = t[0] + dt * np.arange(num_steps + 1)
    length = episode_lengths(data["terminated"], data["truncated"])
    # An episode of L steps visits x_0 .. x_L.
    after_end = np.arange(num_steps + 1)[:, None] > length[None, :]
    x = np.where(after_end[..., None], np.nan, x)
    return times, x


def plot_rollout(data, png_path, max_copies: int = 8) -> Figure:
    """Plot a saved rollout and write it as a PNG.

    One subplot per state dimension (time in s on the x axis, up to ``max_copies`` copies as thin lines, the
    reference dashed black, an ``x`` where an episode terminated early, constraint bounds red dotted where they are
    near the data) and, when ``plane_indices`` is in the data (the CLI saves it for quadrotor_2d and quadrotor_3d),
    a spatial subplot of the position path in the trajectory plane against the reference. The figure legend lists
    only what is drawn.

    Args:
        data: dict of arrays or the path of a ``.npz`` with the keys listed in the module docstring.
        png_path: output file; written to a temporary file in the same folder and renamed, so it is whole or
            absent.
        max_copies: how many copies to draw (the first ones).

    Returns:
        The matplotlib ``Figure`` (Agg canvas; no pyplot state is touched).
    """
    data = _load(data)
    times, x = _episode_paths(data)
    x_ref = np.asarray(data["x_ref"], dtype=np.float64)
    terminated = np.asarray(data["terminated"], dtype=bool)
    names = [str(name) for name in np.asarray(data["state_names"]).tolist()]
    nx, num_envs = x.shape[2], x.shape[1]
    shown = min(max_copies, num_envs)
    length = episode_lengths(data["terminated"], data["truncated"])
    ended_early = terminated[length - 1, np.arange(num_envs)]
    ref_times = times[0] + (times[1] - times[0] if len(times) > 1 else 1.0) * np.arange(x_ref.shape[0])

    spatial = "plane_indices" in data
    u = np.asarray(data["u"], dtype=np.float64) if "u" in data else None
    nu = 0 if u is None else u.shape[2]
    num_panels = nx + nu + int(spatial)
    ncols = 2 if num_panels <= 4 else 3 if num_panels <= 9 else 4
    nrows = math.ceil(num_panels / ncols)
    fig = Figure(figsize=(4.2 * ncols, 2.8 * nrows), layout="constrained")
    FigureCanvasAgg(fig)
    axes = fig.subplots(nrows, ncols, squeeze=False).ravel()
    colors = [f"C{i % 10}" for i in range(shown)]
    drawn_bounds = False

    for j in range(nx):
        ax = axes[j]
        for i in range(shown):
            ax.plot(times, x[:, i, j], color=colors[i], lw=0.8, alpha=0.85)
            if ended_early[i]:
                ax.plot(times[length[i]], x[length[i], i, j], "x", color=colors[i], ms=5)
        ax.plot(ref_times, x_ref[:, j], "k--", lw=1.2, label="reference")
        drawn, off_scale = _draw_bounds(ax, data, "x", j, [x[:, :shown, j], x_ref[:, j]])
        drawn_bounds |= drawn
        ax.set_title(names[j] + off_scale, fontsize=10)
        ax.set_xlabel("t [s]")
        ax.grid(alpha=0.3)

    if u is not None:
        input_names = [str(n) for n in np.asarray(data.get("input_names", [f"u{j}" for j in range(nu)])).tolist()]
        step_times = times[:-1]
        # An input after the episode's end is not part of it; blank it like the states.
        after_end = np.arange(u.shape[0])[:, None] >= length[None, :]
        u = np.where(after_end[..., None], np.nan, u)
        for j in range(nu):
            ax = axes[nx + j]
            for i in range(shown):
                ax.step(step_times[: u.shape[0]], u[:, i, j], where="post", color=colors[i], lw=0.8, alpha=0.85)
            drawn, off_scale = _draw_bounds(ax, data, "u", j, [u[:, :shown, j]])
            drawn_bounds |= drawn
            ax.set_title(f"{input_names[j]} (applied){off_scale}", fontsize=10)
            ax.set_xlabel("t [s]")
            ax.grid(alpha=0.3)

    if spatial:
        ax = axes[nx + nu]
        ia, ib = (int(i) for i in np.asarray(data["plane_indices"]))
        plane = str(data.get("plane", f"{names[ia]}{names[ib]}"))
        for i in range(shown):
            ax.plot(x[:, i, ia], x[:, i, ib], color=colors[i], lw=0.8, alpha=0.85)
            ax.plot(x[0, i, ia], x[0, i, ib], "o", color=colors[i], ms=3)
        ax.plot(x_ref[:, ia], x_ref[:, ib], "k--", lw=1.2, label="reference")
        ax.plot(x_ref[0, ia], x_ref[0, ib], "ks", ms=4)
        ax.set_xlabel(f"{plane[0]} [m]")
        ax.set_ylabel(f"{plane[1]} [m]")
        ax.set_title(f"path in the {plane} plane (o: start)", fontsize=10)
        ax.set_aspect("equal", adjustable="datalim")
        ax.grid(alpha=0.3)
        ax.legend(loc="best", fontsize=8)

    for ax in axes[num_panels:]:
        ax.set_visible(False)
    fig.suptitle(f"{data.get('system', '')} {data.get('task', '')}: {shown} of {num_envs} copies", fontsize=11)
    # The legend names only what is drawn: no bound entry when no bound is on screen, no termination marker when
    # every shown copy ran to the end.
    handles = [Line2D([], [], color="k", ls="--", lw=1.2, label="reference")]
    if drawn_bounds:
        handles.append(Line2D([], [], color="red", ls=":", lw=1.0, label="constraint bound"))
    if np.any(ended_early[:shown]):
        handles.append(Line2D([], [], color="gray", marker="x", ls="", ms=5, label="terminated early"))
    fig.legend(handles=handles, loc="outside lower center", ncols=len(handles), fontsize=9, frameon=False)
    _save_png(fig, Path(png_path))
    return fig


def _draw_bounds(ax, data: dict, prefix: str, j: int, values) -> tuple[bool, str]:
    """Red dotted lines at the finite constraint bounds ``<prefix>_low[j]``, ``<prefix>_high[j]`` that lie within
    one data range of ``values`` (the panel's traces and reference).

    Returns:
        whether a line was drawn, and a title suffix naming the bounds left out (``""`` when none).
    """
    finite = np.concatenate([np.ravel(np.asarray(v, dtype=np.float64)) for v in values])
    finite = finite[np.isfinite(finite)]
    drawn, skipped = False, []
    for side in ("low", "high"):
        name = f"{prefix}_{side}"
        bound = float(np.asarray(data[name], dtype=np.float64)[j]) if name in data else np.inf
        if not np.isfinite(bound):
            continue
        if finite.size:
            lo, hi = float(finite.min()), float(finite.max())
            # Nearly constant data (a held input) gets a range of 10% of its size, so a bound close to it shows.
            span = max(hi - lo, 0.1 * max(abs(lo), abs(hi)), 1e-9)
            near = lo - span <= bound <= hi + span
        else:
            near = True
        if near:
            ax.axhline(bound, color="red", ls=":", lw=1.0)
            drawn = True
        else:
            skipped.append(f"{bound:.3g}")
    word = "bound" if len(skipped) == 1 else "bounds"
    return drawn, f" ({word} {', '.join(skipped)} off scale)" if skipped else ""


def _save_png(fig: Figure, path: Path) -> None:
    write_atomic(path, lambda file: fig.savefig(file, format="png", dpi=110))
