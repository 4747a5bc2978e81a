"""A learned GP-MPC on disk, and its learning curve.

``save_run`` writes ``DIR/gp_mpc.json`` (algorithm, system, prior scale, options, the per-round history) and
``DIR/gp_mpc.npz`` (the GP's arrays), each whole or not at all; ``load_run`` rebuilds the controller, and
``scg-jax eval --controller DIR`` and ``compare`` use it. ``write_learning_curve`` writes the history as
``learning_curve.csv`` and ``learning_curve.png``: RMSE against seconds of simulated training data (the paper's
x-axis).
"""

from __future__ import annotations

import dataclasses
import io
import json
from pathlib import Path

import numpy as np

from scg_algorithms import gp
from scg_algorithms.base import parse_options
from scg_algorithms.gp_mpc.controller import GPMPC, PATH, LearningResult, Options, make_gp_mpc
from scg_jax.files import write_atomic, write_json

RUN_NAME = "gp_mpc"  # DIR/gp_mpc.json (what was learned and how) and DIR/gp_mpc.npz (the GP's arrays)


def save_run(directory, result: LearningResult, options, *, system: str, prior_scale: float, extra=None) -> None:
    """Write a learned GP-MPC to ``directory``: ``gp_mpc.npz`` (the posterior) and ``gp_mpc.json`` (algorithm,
    system, prior scale, options, per-round history, ``extra``), each whole or not at all."""
    if result.posterior is None:
        raise ValueError(f"{PATH}.rounds: nothing was learned (0 rounds); ask for at least 1")
    opts = parse_options(Options, options, PATH)
    post = gp.to_numpy(result.posterior)
    arrays = {
        "inputs": post.inputs, "weights": post.weights, "var_matrix": post.var_matrix,
        "length_scales": post.hyperparams.length_scales, "signal_var": post.hyperparams.signal_var,
        "noise_var": post.hyperparams.noise_var,
    }  # fmt: skip
    buffer = io.BytesIO()
    np.savez(buffer, **arrays)
    directory = Path(directory)
    write_atomic(directory / f"{RUN_NAME}.npz", lambda file: file.write(buffer.getvalue()))
    write_json(
        directory / f"{RUN_NAME}.json",
        {
            "algo": "gp_mpc",
            "system": system,
            "prior_scale": prior_scale,
            "kernel": post.kernel,
            "options": dataclasses.asdict(opts),
            "history": result.history,
            **(extra or {}),
        },
    )


def is_run(directory) -> bool:
    """Whether ``directory`` holds a saved GP-MPC (``save_run``)."""
    return (Path(directory) / f"{RUN_NAME}.json").is_file()


def load_run(directory, env, prior_params, options=None) -> GPMPC:
    """The GP-MPC saved in ``directory`` for ``env`` and the prior ``prior_params``; ``options`` override the saved
    MPC options (the GP stays as learned). Refuses a run learned on another system."""
    directory = Path(directory)
    meta = json.loads((directory / f"{RUN_NAME}.json").read_text())
    if meta.get("system") != env.system.name:
        raise ValueError(
            f"{directory / RUN_NAME}.json: the GP was learned on the {meta.get('system')} and cannot control the "
            f"{env.system.name}"
        )
    with np.load(directory / f"{RUN_NAME}.npz") as arrays:
        hyper = gp.hyperparams(arrays["length_scales"], arrays["signal_var"], arrays["noise_var"])
        posterior = gp.GPPosterior(arrays["inputs"], arrays["weights"], arrays["var_matrix"], hyper, meta["kernel"])
    saved = {k: (tuple(v) if isinstance(v, list) else v) for k, v in meta["options"].items()}
    return make_gp_mpc(env, prior_params, {**saved, **dict(options or {})}, posterior)


CURVE_COLUMNS = ("round", "transitions", "data_seconds", "rmse", "rmse_std", "failure_rate",
                 "constraint_violation_steps", "compute_time_per_step_s", "fit_s", "eval_s")  # fmt: skip


def write_learning_curve(directory, history, rmse_label: str = "RMSE") -> None:
    """``learning_curve.csv`` (one row per round, ``CURVE_COLUMNS``) and ``learning_curve.png`` (RMSE with its
    std against seconds of simulated data) in ``directory``, each whole or not at all."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    directory = Path(directory)
    lines = [",".join(CURVE_COLUMNS)] + [",".join(repr(entry.get(c, float("nan"))) for c in CURVE_COLUMNS)
                                         for entry in history]  # fmt: skip
    text = ("\n".join(lines) + "\n").encode()
    write_atomic(directory / "learning_curve.csv", lambda file: file.write(text))
    seconds = np.array([entry["data_seconds"] for entry in history])
    rmse = np.array([entry["rmse"] for entry in history])
    spread = np.array([entry["rmse_std"] for entry in history])
    figure, axis = plt.subplots(figsize=(5, 3.5), constrained_layout=True)
    axis.plot(seconds, rmse, "o-", label="GP-MPC")
    axis.fill_between(seconds, rmse - spread, rmse + spread, alpha=0.2)
    axis.set_xlabel("training data (s of simulated time)")
    axis.set_ylabel(rmse_label)
    axis.set_title("GP-MPC learning curve (round 0: the prior's MPC)")
    axis.grid(alpha=0.3)
    buffer = io.BytesIO()
    figure.savefig(buffer, format="png", dpi=120)
    plt.close(figure)
    write_atomic(directory / "learning_curve.png", lambda file: file.write(buffer.getvalue()))
