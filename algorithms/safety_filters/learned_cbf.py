"""Learned CBF (Taylor et al. 2020, "Learning for safety-critical control with control barrier functions").

The CBF-QP of ``scg_algorithms.safety_filters.cbf`` on a wrong prior model, with the barrier's time derivative
corrected from data by an MLP ``x -> (a(x) (m, nu), b(x) (m,))``::

    h_dot_est(x, u) = Lf h_prior(x) + Lg h_prior(x) u + a(x)^T u + b(x),

so the filter stays one affine constraint per barrier (closed form for one). Untrained (the last layer starts at
zero) it is the prior CBF exactly.

Data (``train_learned_cbf``): ``num_episodes`` blending episodes, each run by ``num_copies`` copies of the env at
once (one ``jit``-ed ``vmap`` of a ``lax.scan``): episode ``i`` applies ``(1 - w_i) u_L + w_i u_cert`` with
``w_i = i / (num_episodes - 1)``, ``u_L`` uniformly random inputs (the uncertified controller) and ``u_cert`` the
current learned filter's. Each transition ``(x_k, u_k, x_k+1)`` gives the regression target

    r_k = (h(x_k+1) - h(f_prior(x_k, u_k))) / dt,

the barrier's change over the step that the prior's own discrete step ``f_prior`` (same integrator) did not
predict, divided by the control period: the model error's share of ``h_dot``, without the O(dt) bias of a finite
difference of ``h`` (the original's central difference also pairs ``u_k`` with the state after it). After each
episode, ``train_iterations`` Adam steps on ``(a(x_k)^T u_k + b(x_k) - r_k)^2``, then an evaluation of the filter
on ``eval_episodes`` episodes of random inputs logs the violations against the seconds of simulated data so far.

``save_run``/``load_learned_cbf`` write and read the trained filter's folder (``learned_cbf.json``,
``learned_cbf.msgpack``, ``progress.csv``, ``learning_curve.png``), which ``scg-jax eval --filter DIR`` loads.
"""

from __future__ import annotations

import csv
import dataclasses
import io
import json
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from scg_algorithms.base import option, parse_options
from scg_algorithms.safety_filters import cbf as cbf_lib
from scg_algorithms.safety_filters.base import filtered
from scg_jax.tracing import batched_like
from scg_jax.validation import FieldError

PATH = "safety_filters.learned_cbf"
RUN_NAME = "learned_cbf"
FORMAT = 1


@dataclasses.dataclass(frozen=True)
class Options(cbf_lib.Options):
    """The CBF's options (``scg_algorithms.safety_filters.cbf.Options``) and the learning ones; a config's
    ``safety_filters.learned_cbf`` section. Errors name ``safety_filters.learned_cbf.KEY``."""

    hidden_sizes: tuple | None = option((64, 64), "hidden layer sizes of the MLP x -> (a, b)")
    activation: str = option("relu", "hidden activation", ("relu", "tanh", "elu", "gelu", "silu"))
    num_episodes: int = option(20, "blending episodes (the first uncertified, the last fully certified)")
    num_copies: int = option(256, "env copies that run each blending episode at once")
    train_iterations: int = option(200, "Adam steps after each episode")
    batch_size: int = option(256, "transitions per Adam step")
    learning_rate: float = option(1e-3, "Adam step size")
    eval_episodes: int = option(256, "episodes of random inputs that evaluate the filter after each episode")
    seed: int = option(0, "PRNG seed of the network, the data and the evaluations")

    def _check(self, path: str) -> None:
        super()._check(path)
        for name in ("num_episodes", "num_copies", "train_iterations", "batch_size", "eval_episodes"):
            if getattr(self, name) < 1:
                raise FieldError(f"{path}.{name}", f"must be >= 1, got {getattr(self, name)!r}")
        if not self.learning_rate > 0:
            raise FieldError(f"{path}.learning_rate", f"must be > 0, got {self.learning_rate!r}")
        if self.hidden_sizes is not None and any(int(v) != v or v < 1 for v in self.hidden_sizes):
            raise FieldError(f"{path}.hidden_sizes", f"expected positive integers, got {list(self.hidden_sizes)}")


def _cbf_options(opts: Options) -> cbf_lib.Options:
    return cbf_lib.Options(**{f.name: getattr(opts, f.name) for f in dataclasses.fields(cbf_lib.Options)})


def _network(opts: Options, num_barriers: int, nu: int):
    from scg_algorithms.rl.networks import MLP

    hidden = tuple(int(v) for v in (opts.hidden_sizes or ()))
    # The last layer starts at zero: the untrained learned CBF is the prior CBF.
    return MLP(features=(*hidden, num_barriers * (nu + 1)), activation=opts.activation, final_scale=0.0)


def make_learned_cbf(env, prior_params, options=None, net_params=None):
    """The learned CBF for ``env`` on the prior ``prior_params``: untrained (the prior CBF), or with
    ``net_params`` (the MLP's flax parameters). Options: ``Options``. Returns a ``CBFFilter`` named
    ``learned_cbf`` whose ``params["correction"]`` holds the network parameters (traced)."""
    opts = parse_options(Options, options, PATH)
    if opts.solver == "casadi":
        raise FieldError(
            f"{PATH}.solver", "the learned correction is JAX only; allowed values are auto, closed_form, qpax"
        )
    _, functions, _ = cbf_lib.barrier_setup(env, prior_params, _cbf_options(opts), PATH)
    m, nu = len(functions), env.nu
    network = _network(opts, m, nu)
    if net_params is None:
        net_params = network.init(jax.random.key(opts.seed), jnp.zeros(env.nx))

    def correction(x, params):
        out = network.apply(params, x).reshape(m, nu + 1)
        return out[:, :nu], out[:, nu]

    flt = cbf_lib.make_cbf(
        env, prior_params, _cbf_options(opts), correction=correction, correction_params=net_params, name="learned_cbf"
    )
    return dataclasses.replace(flt, info={**flt.info, "hidden_sizes": [int(v) for v in opts.hidden_sizes or ()]})


# --------------------------------------------------------------------------------------------- training
def _collector(env, flt, prior_step, uncertified):
    """``collect(net_params, weight, keys (C,), params, filter_params) -> (x (C, T, nx), u (C, T, nu), valid (C, T),
    residual (C, T, m))``: one blending episode of ``C`` copies of the plant ``params`` under ``uncertified`` and the
    filter with ``filter_params`` (its network left out); ``residual`` is the regression target (module docstring).
    Compiled once per shapes: the plant, the filter's parameters and the network are arguments."""
    nx = env.nx

    def one_copy(net_params, weight, key, params, base_params):
        filter_params = {**base_params, "correction": net_params}
        env_key, ctrl_key = jax.random.split(key)
        obs, state = env.reset(env_key, params)
        ctrl_state = uncertified.reset(ctrl_key, None)

        def body(carry, _):
            obs, state, ctrl_state = carry
            u_l, ctrl_state = uncertified.act(ctrl_state, obs, state.step, None)
            u_cert, _, _ = flt.certify(obs, u_l, filter_params, ())
            u = (1.0 - weight) * u_l + weight * u_cert
            out = env.step(state, env.input_to_action(u, params), params)
            x, x_next = obs[:nx], out.obs[:nx]
            h_next = _barrier_values(flt, base_params, x_next)
            h_pred = _barrier_values(flt, base_params, prior_step(x, u))
            residual = (h_next - h_pred) / env.dt
            return (out.obs, out.state, ctrl_state), (x, u, ~out.terminated, residual)

        carry = batched_like((obs, state, ctrl_state), obs)  # vmap batches the body once (scg_jax.tracing)
        _, records = jax.lax.scan(body, carry, None, length=env.num_steps)
        return records

    return jax.jit(jax.vmap(one_copy, in_axes=(None, None, 0, None, None)))


def _barrier_values(flt, params, x):
    """The barrier values (m,) at ``x`` (without the Lie derivatives: only ``h``)."""
    return flt.terms_fn(x, params).h


def _trainer(network, m: int, nu: int, opts: Options):
    import optax

    optimizer = optax.adam(opts.learning_rate)

    def loss_fn(net_params, x, u, r):
        out = jax.vmap(lambda xi: network.apply(net_params, xi))(x).reshape(-1, m, nu + 1)
        predicted = jnp.einsum("bmu,bu->bm", out[:, :, :nu], u) + out[:, :, nu]
        return jnp.mean(jnp.square(predicted - r))

    @jax.jit
    def train(net_params, opt_state, key, X, U, R, count):
        def step(carry, key):
            net_params, opt_state = carry
            idx = jax.random.randint(key, (opts.batch_size,), 0, count)
            loss, grads = jax.value_and_grad(loss_fn)(net_params, X[idx], U[idx], R[idx])
            updates, opt_state = optimizer.update(grads, opt_state, net_params)
            return (optax.apply_updates(net_params, updates), opt_state), loss

        (net_params, opt_state), losses = jax.lax.scan(
            step, (net_params, opt_state), jax.random.split(key, opts.train_iterations)
        )
        return net_params, opt_state, losses[-1]

    @jax.jit
    def rmse(net_params, x, u, r, mask):
        """RMSE of the correction over the rows of ``mask`` (an episode's fixed-size records: one compilation)."""
        out = jax.vmap(lambda xi: network.apply(net_params, xi))(x).reshape(-1, m, nu + 1)
        predicted = jnp.einsum("bmu,bu->bm", out[:, :, :nu], u) + out[:, :, nu]
        squared = jnp.where(mask[:, None], jnp.square(predicted - r), 0.0)
        return jnp.sqrt(jnp.sum(squared) / (jnp.maximum(jnp.sum(mask), 1) * m))

    return optimizer, train, rmse


def _evaluator(env, params, flt, eval_episodes: int):
    from scg_algorithms.evaluation import make_evaluator
    from scg_algorithms.safety_filters.uncertified import random_input

    uncertified = random_input(env, params)

    def build(net_params):
        return filtered(uncertified, flt.replace(params={**flt.params, "correction": net_params}), env)

    build.__name__ = "learned_cbf"
    return make_evaluator(env, build, eval_episodes)


def _violation_row(evaluation) -> dict:
    per = evaluation.per_episode
    steps = float(np.sum(per["length"]))
    return {
        "violation_fraction": float(np.sum(per["violation_steps"]) / max(steps, 1.0)),
        "episodes_with_violation": float(np.mean(np.asarray(per["violation_steps"]) > 0)),
        "intervention_fraction": evaluation.summary.get("intervention_fraction"),
        "mean_correction": evaluation.summary.get("mean_correction"),
    }


@dataclasses.dataclass(frozen=True)
class LearnedCBF:
    """What ``train_learned_cbf`` returns: the trained ``filter``, its ``options``, the per-episode ``history``
    (dicts, see ``train_learned_cbf``) and the network parameters ``net_params``."""

    filter: object
    options: Options
    history: list
    net_params: object


def train_learned_cbf(env, params, prior_params, options=None, progress=None) -> LearnedCBF:
    """Learn the CBF's Lie-derivative correction from blending episodes on the true plant ``params``.

    Args:
        env: the environment (its state constraints define the barrier's default limit). params: the true plant's
            ``EnvParams`` (what is simulated). prior_params: the filter's model. options: ``Options``.
        progress: optional ``progress(row)`` called after the evaluation before training and after each episode.

    Returns:
        ``LearnedCBF``; ``history`` rows hold ``episode`` (0: before any data), ``blend_weight``, ``data_steps``
        (transitions so far, all copies), ``data_seconds`` (``data_steps * dt``), ``violation_fraction`` (steps
        in violation / steps of the evaluation episodes), ``episodes_with_violation``, ``intervention_fraction``,
        ``mean_correction`` (N), ``heldout_rmse`` (RMSE of the learned correction on the episode's new data before
        training on it, the barrier's units per second), ``prior_rmse`` (RMSE of the residual itself:
        the prior-only error on the same data), ``loss`` (last minibatch loss), ``wall_s``.
    """
    from scg_algorithms.controller_setup import prior_step_fn
    from scg_algorithms.safety_filters.uncertified import random_input

    opts = parse_options(Options, options, PATH)
    flt = make_learned_cbf(env, prior_params, opts)
    m = int(flt.info["num_barriers"])
    nu, nx = env.nu, env.nx
    network = _network(opts, m, nu)
    net_params = flt.params["correction"]
    prior_step = prior_step_fn(env, prior_params, "env")
    collect = _collector(env, flt, prior_step, random_input(env, params))
    optimizer, train, rmse = _trainer(network, m, nu, opts)
    opt_state = optimizer.init(net_params)
    evaluate_fn = _evaluator(env, params, flt, opts.eval_episodes)

    # Host buffers of every transition so far, passed whole to the compiled training step (one shape throughout).
    capacity = opts.num_episodes * opts.num_copies * env.num_steps
    dtype = np.dtype(jnp.result_type(float))
    X, U, R = (np.zeros((capacity, n), dtype) for n in (nx, nu, m))
    count = 0
    key = jax.random.key(opts.seed)
    key, eval_key = jax.random.split(key)
    start = time.perf_counter()
    history = []

    def log(row):
        history.append(row)
        if progress is not None:
            progress(row)

    evaluation = evaluate_fn(net_params, eval_key, params)
    log({"episode": 0, "blend_weight": 0.0, "data_steps": 0, "data_seconds": 0.0, **_violation_row(evaluation),
         "heldout_rmse": None, "prior_rmse": None, "loss": None, "wall_s": time.perf_counter() - start})  # fmt: skip
    for episode in range(opts.num_episodes):
        weight = episode / (opts.num_episodes - 1) if opts.num_episodes > 1 else 1.0
        key, data_key, train_key = jax.random.split(key, 3)
        records = collect(
            net_params, jnp.asarray(weight, dtype), jax.random.split(data_key, opts.num_copies), params, flt.params
        )
        x, u, valid, r = (np.asarray(a).reshape(opts.num_copies * env.num_steps, -1) for a in records)
        keep = valid[:, 0] & np.all(np.isfinite(x), axis=1) & np.all(np.isfinite(r), axis=1)
        x, u, r = (np.where(keep[:, None], a, 0.0).astype(dtype) for a in (x, u, r))
        heldout = float(rmse(net_params, x, u, r, keep)) if keep.any() else float("nan")
        prior_rmse = float(np.sqrt(np.mean(np.square(r[keep])))) if keep.any() else float("nan")
        n_new = min(int(keep.sum()), capacity - count)
        X[count : count + n_new], U[count : count + n_new], R[count : count + n_new] = (
            a[keep][:n_new] for a in (x, u, r)
        )
        count += n_new
        net_params, opt_state, loss = train(net_params, opt_state, train_key, X, U, R, max(count, 1))
        evaluation = evaluate_fn(net_params, eval_key, params)
        log({"episode": episode + 1, "blend_weight": weight, "data_steps": count,
             "data_seconds": count * env.dt, **_violation_row(evaluation), "heldout_rmse": heldout,
             "prior_rmse": prior_rmse, "loss": float(loss), "wall_s": time.perf_counter() - start})  # fmt: skip
    trained = flt.replace(params={**flt.params, "correction": net_params})
    return LearnedCBF(filter=trained, options=opts, history=history, net_params=net_params)


# --------------------------------------------------------------------------------------------- files
def is_run(path: Path) -> bool:
    """Whether ``path`` holds a learned CBF written by ``save_run``."""
    return (Path(path) / f"{RUN_NAME}.json").is_file() and (Path(path) / f"{RUN_NAME}.msgpack").is_file()


HISTORY_COLUMNS = (
    "episode", "blend_weight", "data_steps", "data_seconds", "violation_fraction", "episodes_with_violation",
    "intervention_fraction", "mean_correction", "heldout_rmse", "prior_rmse", "loss", "wall_s",
)  # fmt: skip


def save_run(directory, result: LearnedCBF, *, system: str, prior_scale: float, extra: dict | None = None) -> None:
    """Write ``learned_cbf.json`` (options, system, prior scale, history), ``learned_cbf.msgpack`` (the network),
    ``progress.csv`` and ``learning_curve.png`` (violations vs seconds of data) to ``directory``."""
    from flax import serialization

    from scg_jax.files import write_atomic, write_json

    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    write_atomic(directory / f"{RUN_NAME}.msgpack", lambda f: f.write(serialization.to_bytes(result.net_params)))
    text = io.StringIO()
    writer = csv.DictWriter(text, fieldnames=HISTORY_COLUMNS)
    writer.writeheader()
    for row in result.history:
        writer.writerow({k: ("" if row.get(k) is None else row[k]) for k in HISTORY_COLUMNS})
    write_atomic(directory / "progress.csv", lambda f: f.write(text.getvalue().encode()))
    plot_learning_curve(result.history, directory / "learning_curve.png")
    record = {
        "format": FORMAT,
        "filter": RUN_NAME,
        "system": system,
        "prior_scale": float(prior_scale),
        "options": dataclasses.asdict(result.options),
        "history": result.history,
        **(extra or {}),
    }
    write_json(directory / f"{RUN_NAME}.json", record)


def plot_learning_curve(history, png_path) -> None:
    """Violating steps (fraction) against seconds of simulated training data, as the paper's Fig 7 (top)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from scg_jax.files import write_atomic

    seconds = [row["data_seconds"] for row in history]
    fig, ax = plt.subplots(figsize=(6, 4))
    ax.plot(seconds, [100 * row["violation_fraction"] for row in history], marker="o", label="learned CBF")
    ax.set_xlabel("training data (s of simulated time, all copies)")
    ax.set_ylabel("steps in violation (%)")
    ax.set_title("learned CBF: constraint violations vs training data")
    ax.grid(True, alpha=0.3)
    ax.legend()
    fig.tight_layout()
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=100)
    plt.close(fig)
    write_atomic(png_path, lambda f: f.write(buffer.getvalue()))


def load_learned_cbf(directory, env, params, options=None):
    """The trained learned CBF in ``directory`` for ``env``; ``params`` are the true plant's (the saved prior scale
    is applied). ``options`` override saved filter options (e.g. ``slope``)."""
    from flax import serialization

    from scg_jax.env import prior_params as make_prior

    directory = Path(directory)
    if not is_run(directory):
        raise ValueError(
            f"{directory}: no {RUN_NAME}.json and {RUN_NAME}.msgpack (write one with scg-jax train --algo learned_cbf)"
        )
    record = json.loads((directory / f"{RUN_NAME}.json").read_text())
    if record.get("system") != env.system.name:
        raise ValueError(f"{directory}: a learned CBF for the {record.get('system')} system, not for {env.system.name}")
    saved = {k: (tuple(v) if isinstance(v, list) else v) for k, v in record["options"].items()}
    merged = {**saved, **dict(options or {})}
    scale = float(record["prior_scale"])
    prior = params if scale == 1.0 else make_prior(env, params, scale)
    untrained = make_learned_cbf(env, prior, merged)
    net_params = serialization.from_bytes(
        untrained.params["correction"], (directory / f"{RUN_NAME}.msgpack").read_bytes()
    )
    return untrained.replace(params={**untrained.params, "correction": net_params})


__all__ = [
    "HISTORY_COLUMNS",
    "PATH",
    "RUN_NAME",
    "LearnedCBF",
    "Options",
    "is_run",
    "load_learned_cbf",
    "make_learned_cbf",
    "plot_learning_curve",
    "save_run",
    "train_learned_cbf",
]
