"""Training data for GP-MPC, collected by the batched JAX environments.

- ``exploring(controller, std)``: any JAX controller with Gaussian exploration noise on its input (the original
  suite collects its first data with the prior controller plus noise).
- ``transitions(trajectory)``: the ``(x, u, x_next)`` triples of an evaluation's trajectories, each episode cut at
  its end (the rows after a copy terminated are the plant running on and are dropped).
- ``model_error(fd, x, u, x_next)``: the GP's regression data: inputs ``z = [x; u]`` and targets
  ``e = x_next - f_prior(x, u)``, with ``f_prior`` the MPC's own discrete prior model (a CasADi ``Function``), so
  the GP learns exactly what the prediction model misses.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from scg_algorithms.base import JaxController


def exploring(controller: JaxController, std) -> JaxController:
    """``controller`` with ``u + N(0, diag(std²))`` (N) added to every input; noise from the controller key.

    Args:
        controller: a JAX controller. std: scalar or (nu,) noise standard deviation, N; 0 gives the controller's
            own inputs.
    """
    if not getattr(controller, "is_jax", False):
        raise ValueError(f"exploring: needs a JAX controller, got {getattr(controller, 'name', controller)!r}")
    std = np.asarray(std, dtype=float)
    if not np.all(np.isfinite(std)) or np.any(std < 0):
        raise ValueError(f"exploration_std: must be finite and >= 0, got {std.tolist()}")

    def reset_fn(key, reference):
        inner_key, noise_key = jax.random.split(key)
        return controller.reset(inner_key, reference), noise_key

    def act_fn(ctrl_state, obs, step, reference):
        inner, noise_key = ctrl_state
        u, inner = controller.act(inner, obs, step, reference)
        noise = jax.random.normal(jax.random.fold_in(noise_key, step), jnp.shape(u)) * std
        return u + noise.astype(u.dtype), (inner, noise_key)

    return JaxController(f"{controller.name}+noise", reset_fn, act_fn, {**controller.info, "exploration_std": std})


def episode_lengths(trajectory) -> np.ndarray:
    """(N,) control steps of each copy's first episode: up to and including its first terminated/truncated step."""
    done = np.asarray(trajectory["terminated"]) | np.asarray(trajectory["truncated"])  # (T, N)
    T = done.shape[0]
    first = np.where(done.any(axis=0), done.argmax(axis=0) + 1, T)
    return first.astype(int)


def transitions(trajectory) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(x (n, nx), u (n, nu), x_next (n, nx))`` of every step inside each copy's episode, episode-major.

    ``trajectory`` is ``Evaluation.trajectory``: ``x`` (T + 1, N, nx), ``u`` (T, N, nu) the applied inputs,
    ``terminated`` and ``truncated`` (T, N). Non-finite rows (a diverged copy) are dropped.
    """
    x, u = np.asarray(trajectory["x"], float), np.asarray(trajectory["u"], float)
    lengths = episode_lengths(trajectory)
    xs, us, nexts = [], [], []
    for i, n in enumerate(lengths):
        xs.append(x[:n, i])
        us.append(u[:n, i])
        nexts.append(x[1 : n + 1, i])
    x_all, u_all, next_all = np.concatenate(xs), np.concatenate(us), np.concatenate(nexts)
    finite = np.isfinite(x_all).all(1) & np.isfinite(u_all).all(1) & np.isfinite(next_all).all(1)
    return x_all[finite], u_all[finite], next_all[finite]


def model_error(fd, x, u, x_next) -> tuple[np.ndarray, np.ndarray]:
    """GP inputs ``z = [x, u]`` (n, nx + nu) and targets ``x_next - fd(x, u)`` (n, nx).

    Args:
        fd: the prior's discrete model, a CasADi ``Function`` ``(x (nx,), u (nu,)) -> (nx,)`` (e.g.
            ``env.symbolic_model(prior, discretization="rk4").fd``); evaluated with ``map`` over the data.
        x, u, x_next: (n, nx), (n, nu), (n, nx).
    """
    x, u, x_next = (np.asarray(a, dtype=np.float64) for a in (x, u, x_next))
    if len(x) == 0:
        raise ValueError("data: no transitions to learn from")
    predicted = np.asarray(fd.map(len(x))(x.T, u.T)).T
    return np.concatenate([x, u], axis=1), x_next - predicted
