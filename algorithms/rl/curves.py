"""The learning curve of a JAX learner's run: ``progress.csv`` plotted against env steps, and the RMSE axis label."""

from __future__ import annotations

import csv as csv_lib
import math
from pathlib import Path

import numpy as np

from scg_jax.files import write_atomic

# Position entries of each system's state (m): a RMSE weighted only on these is a distance.
_POSITION_INDICES = {"cartpole": (0,), "quadrotor_1d": (0,), "quadrotor_2d": (0, 2), "quadrotor_3d": (0, 2, 4)}


def rmse_label(env, params) -> str:
    """Axis label of the episode RMSE: ``"RMSE (m)"`` when ``params.mse_weight`` weighs only positions with 1
    (the quadrotors' default), otherwise a weighted full-state error of mixed units (the cart-pole's default)."""
    weights = np.asarray(params.mse_weight)
    weighted = set(np.flatnonzero(weights).tolist())
    positions = set(_POSITION_INDICES.get(env.system.name, ()))
    if weighted and weighted <= positions and np.all(weights[list(weighted)] == 1.0):
        return "RMSE (m)"
    return "RMSE (weighted state error, mixed units)"


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
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    with Path(csv_path).open(newline="") as file:
        rows = list(csv_lib.DictReader(file))
    if not rows:
        return
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
        ax.set_xlabel("env steps")
        ax.set_ylabel(label, fontsize=9)
        ax.set_title(label, fontsize=10)
        ax.grid(alpha=0.3)
    if violation_panel:
        ax = fig.add_subplot(nrows, ncols, len(panels) + 1)
        cost, length = (np.array([float(row[n]) if row[n] != "" else math.nan for row in rows]) for n in
                        ("episode_cost", "episode_length"))  # fmt: skip
        ax.plot(steps / ctrl_freq, cost / length, lw=1.2)
        ax.set_xscale("log")
        ax.set_xlabel("simulated training data (s)")
        ax.set_title("fraction of steps in violation", fontsize=10)
        ax.grid(alpha=0.3)
    write_atomic(png_path, lambda file: fig.savefig(file, format="png", dpi=100))
