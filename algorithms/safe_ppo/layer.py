"""The safety layer of Dalal et al. (2018): linear models of the state constraints and the closed-form projection.

Constraint rows ``c_i(x) <= 0`` (the env's linear ``state`` constraints, ``c = A x - b``, in the env's row order).
Each row has a model ``g_i(obs) in R^d`` of how the normalised action ``a in [-1, 1]^d`` moves it in one control
step, ``c_i(next) ~= c_i + g_i(obs)^T a``; the models are small MLPs, one per row, with their parameters stacked
on a leading row axis and applied with ``jax.vmap``. They are fitted before PPO from random-action rollouts of the
batched env (``pretrain``) and then frozen.

The projection of a policy mean ``mu`` solves ``min ||a - mu||^2 s.t. c_i + g_i^T a + slack_i <= 0`` for the single
row with the largest multiplier (the closed form of the original, exact when at most one row is active)::

    lambda_i = max(0, (g_i^T mu + c_i + slack_i) / (g_i^T g_i + 1e-8)),   i* = argmax_i lambda_i,
    mu_safe = mu - lambda_i* g_i*.

The constraint values are computed from the observation (its first ``nx`` entries are the state, noisy where the
env adds observation noise), so a trained policy needs only its observation to act, like any controller.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import optax

from scg_algorithms.rl.collector import ActOutput, collect, init_collector
from scg_algorithms.rl.networks import MLP

DENOMINATOR_EPS = 1e-8  # as the original: a row whose model predicts no effect gets no correction


def project_mean(mean, g, c, slack):
    """The safety layer's closed-form correction of ``mean``.

    Args:
        mean: (..., d) policy mean (normalised action). g: (..., m, d) the rows' action gradients ``g_i(obs)``.
        c: (..., m) constraint values now (``<= 0`` satisfied). slack: (m,) or scalar margin per row (>= 0).

    Returns:
        (..., d): ``mean - lambda_i* g_i*`` with ``lambda`` and ``i*`` as in the module docstring (``mean`` itself
        where no row is predicted to exceed ``-slack``).
    """
    lam = jax.nn.relu((jnp.einsum("...md,...d->...m", g, mean) + c + slack) / (jnp.sum(g * g, -1) + DENOMINATOR_EPS))
    row = jnp.argmax(lam, axis=-1)
    lam_max = jnp.take_along_axis(lam, row[..., None], axis=-1)
    g_max = jnp.take_along_axis(g, row[..., None, None], axis=-2)[..., 0, :]
    return mean - lam_max * g_max


def state_constraint_rows(env, params, path: str = "env.constraints"):
    """The env's linear state-constraint rows as ``(A (m, nx), b (m,))`` with ``c = A x - b`` (rows in the env's
    order; input constraints are left to the action box).

    Raises:
        ValueError: no state constraint, a quadratic one, or one on ``input_and_state`` (the layer models state
            rows only), naming ``path`` and what is allowed.
    """
    nx = env.system.nx
    rows_A, rows_b = [], []
    for i, (spec, values) in enumerate(zip(env.constraint_specs, params.constraints, strict=True)):
        if spec.on == "input":
            continue
        if spec.on != "state" or spec.form != "linear":
            raise ValueError(
                f"{path}[{i}]: the safety layer (training.safe_ppo) models linear state constraints only (types "
                f"bounded, abs_bound, linear or default with on: state), got type {spec.type} on {spec.on}"
            )
        A = jnp.zeros((spec.num_rows, nx), jnp.float32).at[:, np.asarray(spec.active_dims)].set(values.A)
        rows_A.append(A)
        rows_b.append(jnp.asarray(values.b, jnp.float32))
    if not rows_A:
        raise ValueError(
            f"{path}: the safety layer (training.safe_ppo) needs at least one state constraint (e.g. "
            "{type: bounded, on: state, active_dims: [2, 3], low: [-0.2, -0.2], high: [0.2, 0.2]}); the env has none"
        )
    return jnp.concatenate(rows_A), jnp.concatenate(rows_b)


def constraint_values(layer, obs):
    """``c = A obs[..., :nx] - b`` (..., m) from the layer's rows (``layer["A"]`` (m, nx), ``layer["b"]`` (m,))."""
    nx = layer["A"].shape[-1]
    return obs[..., :nx] @ layer["A"].T - layer["b"]


def make_constraint_model(hidden: tuple[int, ...], action_size: int):
    """``(init(key, obs_size, m) -> params stacked over m rows, apply(params, obs (..., o)) -> g (..., m, d))``."""
    # A small last layer starts every row near "the action has no effect" (c_next ~= c), the regression's baseline.
    net = MLP((*hidden, action_size), "tanh", final_scale=0.1)

    def init(key, obs_size: int, num_rows: int):
        return jax.vmap(net.init, in_axes=(0, None))(jax.random.split(key, num_rows), jnp.zeros((1, obs_size)))

    def apply(model_params, obs):
        return jax.vmap(net.apply, in_axes=(0, None), out_axes=-2)(model_params, obs)

    return init, apply


def model_loss(apply, model_params, obs, action, c, c_next):
    """Mean over samples and rows of ``(c + g(obs)^T a - c_next)^2``; obs (B, o), action (B, d), c, c_next (B, m)."""
    predicted = c + jnp.einsum("bmd,bd->bm", apply(model_params, obs), action)
    return jnp.mean((predicted - c_next) ** 2)


def pretrain(config, train_env, key, params, rows):
    """Fit the constraint models on random-action rollouts of ``train_env`` (pure; jit it or call it in ``init``).

    Each of ``constraint_epochs`` epochs collects ``constraint_steps_per_epoch`` fresh env steps (all copies
    together) under uniform random actions in [-1, 1]^d and takes one Adam pass over them in minibatches of
    ``constraint_batch_size``; a last collection of ``constraint_eval_steps`` steps, never trained on, gives the
    held-out MSE.

    Args:
        config: ``scg_algorithms.safe_ppo.Config``. train_env: ``TrainEnv``. key: raw PRNG key. params: unbatched
            ``EnvParams``. rows: ``(A, b)`` from ``state_constraint_rows``.

    Returns:
        ``(layer, stats)``: ``layer = {"model": stacked MLP params, "A": A, "b": b}``; ``stats`` a dict of scalars:
        ``constraint_model_mse`` (held-out), ``constraint_model_baseline_mse`` (held-out, of ``c_next ~= c``),
        ``constraint_model_train_mse`` (last epoch's mean minibatch loss),
        ``pretrain_env_steps``.
    """
    A, b = rows
    layer_init, apply = make_constraint_model(config.constraint_hidden_dim, train_env.action_size)
    optimizer = optax.adam(config.constraint_lr)
    n, d = train_env.num_envs, train_env.action_size
    batch = config.constraint_batch_size
    key_model, key_env, key_epochs, key_eval = jax.random.split(key, 4)
    model_params = layer_init(key_model, train_env.obs_size, A.shape[0])
    layer_rows = {"A": A, "b": b}

    def random_act(obs, step_key):
        return ActOutput(jax.random.uniform(step_key, (n, d), obs.dtype, -1.0, 1.0), {})

    def dataset(collector, collect_key, num_steps):
        collector, steps, _, _ = collect(train_env, params, collector, random_act, collect_key, num_steps // n,
                                         update_normalizer=False)  # fmt: skip
        flat = lambda x: jnp.reshape(x, (-1, *x.shape[2:]))  # noqa: E731
        obs, next_obs = flat(steps.obs), flat(steps.next_obs)
        data = (obs, flat(steps.action), constraint_values(layer_rows, obs), constraint_values(layer_rows, next_obs))
        return collector, data

    grad_fn = jax.value_and_grad(lambda p, *mb: model_loss(apply, p, *mb))

    def sgd_step(carry, mb):
        model_params, opt_state = carry
        loss, grads = grad_fn(model_params, *mb)
        updates, opt_state = optimizer.update(grads, opt_state, model_params)
        return (optax.apply_updates(model_params, updates), opt_state), loss

    def epoch(carry, epoch_key):
        collector, model_params, opt_state = carry
        key_collect, key_perm = jax.random.split(epoch_key)
        collector, data = dataset(collector, key_collect, config.constraint_steps_per_epoch)
        size = data[0].shape[0]
        permutation = jax.random.permutation(key_perm, size)[: (size // batch) * batch]
        minibatches = jax.tree.map(lambda x: jnp.reshape(x[permutation], (-1, batch, *x.shape[1:])), data)
        (model_params, opt_state), loss = jax.lax.scan(sgd_step, (model_params, opt_state), minibatches)
        return (collector, model_params, opt_state), jnp.mean(loss)

    collector = init_collector(train_env, key_env, params)
    (collector, model_params, _), losses = jax.lax.scan(
        epoch,
        (collector, model_params, optimizer.init(model_params)),
        jax.random.split(key_epochs, config.constraint_epochs),
    )
    _, held_out = dataset(collector, key_eval, config.constraint_eval_steps)
    steps_per_epoch = (config.constraint_steps_per_epoch // n) * n
    stats = {
        "constraint_model_mse": model_loss(apply, model_params, *held_out),
        # The same error of the model without an action effect (c_next ~= c): what the models explain.
        "constraint_model_baseline_mse": jnp.mean((held_out[3] - held_out[2]) ** 2),
        "constraint_model_train_mse": losses[-1],
        "pretrain_env_steps": jnp.asarray(
            config.constraint_epochs * steps_per_epoch + (config.constraint_eval_steps // n) * n, jnp.float32
        ),
    }
    return {"model": model_params, **layer_rows}, stats
