"""The learning curve of a JAX learner's run: ``progress.csv`` plotted against env steps, and the RMSE axis label."""

from __future__ import annotations

import csv as csv_lib
import math
from pathlib import Path

import numpy as np

from scg_jax.files import write_atomic

# Position entries of each system's state (m): a RMSE weighted only on these is a distance.
_POSITION_INDICES = {"cartpole": (0,), "quadrotor_1d": (0,), "quadrotor_2d": (0, 2), "quadrotor_3d": (0, 2, 4)}


def rmse_unit(env, params) -> str:
    """What the episode RMSE measures, as every table and plot names it: ``"m"`` when ``params.mse_weight`` weighs
    only positions with 1 (the quadrotors' default: the position error), otherwise ``"weighted state error, mixed
    units"`` (the cart-pole's default weighs all four states, m, m/s, rad and rad/s, with 1)."""
    weights = np.asarray(params.mse_weight)
    weighted = set(np.flatnonzero(weights).tolist())
    positions = set(_POSITION_INDICES.get(env.system.name, ()))
    if weighted and weighted <= positions and np.all(weights[list(weighted)] == 1.0):
        return "m"
    return "weighted state error, mixed units"


def rmse_label(env, params) -> str:
    """Axis label of the episode RMSE: ``"RMSE (<rmse_unit>)"``, e.g. ``"RMSE (m)"``."""
    return f"RMSE ({rmse_unit(env, params)})"


CURVE_PANELS = (
    ("episode_return", "return (sum of rewards)"),
    ("episode_rmse", None),  # the label comes from rmse_label
    ("episode_cost", "cost (steps in violation)"),
    ("episode_length", "length (control steps)"),
)


def plot_learning_curve(
    csv_path, png_path, rmse_label: str = "RMSE (weighted state error)", ctrl_freq: float | None = None
) -> None:
    """Plot ``progress.csv`` against env steps: return, RMSE, cost and length per episode, plus every ``*loss*``
    column, one panel each (the panels whose column is missing are left out); written atomically as a PNG.

    With ``ctrl_freq`` (Hz) and the ``episode_cost`` and ``episode_length`` columns, one more panel plots the
    fraction of steps in violation (episode cost over episode length) against seconds of simulated training data
    (``env_steps / ctrl_freq``, log scale), the x-axis of the paper's constraint figure.

    ``nan`` entries (no episode had ended yet) are left out of the lines rather than drawn as 0.
    """
    fig = learning_curve_figure(csv_path, rmse_label, ctrl_freq)
    if fig is not None:
        write_atomic(png_path, lambda file: fig.savefig(file, format="png", dpi=100))


def learning_curve_figure(csv_path, rmse_label: str = "RMSE (weighted state error)", ctrl_freq: float | None = None):
    """The matplotlib ``Figure`` that ``plot_learning_curve`` saves (None for a CSV without rows). Each panel's title
    names its quantity (no y label, which would crowd the panel to its left), and the x tick labels are compact
    (``compact_number``)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    with Path(csv_path).open(newline="") as file:
        rows = list(csv_lib.DictReader(file))
    if not rows:
        return None
    columns = rows[0].keys()
    panels = [(name, label or rmse_label) for name, label in CURVE_PANELS if name in columns]
    panels += [(name, name) for name in columns if "loss" in name]
    steps = np.array([float(row["env_steps"]) for row in rows])
    violation_panel = ctrl_freq is not None and {"episode_cost", "episode_length"} <= set(columns)
    num_panels = len(panels) + int(violation_panel)
    ncols = min(3, max(num_panels, 1))
    nrows = max(1, math.ceil(num_panels / ncols))
    fig = Figure(figsize=(4.2 * ncols, 3.0 * nrows), layout="constrained")
    FigureCanvasAgg(fig)
    for i, (name, label) in enumerate(panels):
        ax = fig.add_subplot(nrows, ncols, i + 1)
        values = np.array([float(row[name]) if row[name] != "" else math.nan for row in rows])
        ax.plot(steps, values, lw=1.2)
        _compact_axis(ax.xaxis, log=False)
        ax.set_xlabel("env steps")
        ax.set_title(label, fontsize=10)  # the title names the quantity: a long y label would crowd the next panel
        ax.grid(alpha=0.3)
    if violation_panel:
        ax = fig.add_subplot(nrows, ncols, len(panels) + 1)
        cost, length = (np.array([float(row[n]) if row[n] != "" else math.nan for row in rows]) for n in
                        ("episode_cost", "episode_length"))  # fmt: skip
        ax.plot(steps / ctrl_freq, cost / length, lw=1.2)
        ax.set_xscale("log")
        _compact_axis(ax.xaxis, log=True)
        ax.set_xlabel("simulated training data (s)")
        ax.set_title("fraction of steps in violation", fontsize=10)
        ax.grid(alpha=0.3)
    return fig


def compact_number(value: float, _position=None) -> str:
    """A tick label of at most a few characters: ``500``, ``30k``, ``1.5M`` (no offset text or ``x10^n`` factors,
    which overlapped the neighbouring labels)."""
    for scale, suffix in ((1e9, "G"), (1e6, "M"), (1e3, "k")):
        if abs(value) >= scale:
            return f"{value / scale:.3g}{suffix}"
    return f"{value:.3g}"


def _compact_axis(axis, log: bool) -> None:
    """At most about five labelled ticks, each ``compact_number``; on a log axis 1, 2 and 5 per decade (so a range
    inside one decade still gets labels) and no minor labels."""
    from matplotlib.ticker import FuncFormatter, LogLocator, MaxNLocator, NullFormatter

    if log:
        axis.set_major_locator(LogLocator(base=10, subs=(1.0, 2.0, 5.0), numticks=6))
        axis.set_minor_formatter(NullFormatter())
    else:
        axis.set_major_locator(MaxNLocator(nbins=5))
    axis.set_major_formatter(FuncFormatter(compact_number))
