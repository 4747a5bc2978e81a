"""The MPSC acceptance experiment, shared by the tests and ``benchmarks/mpsc.py``: a cart-pole whose cart must stay
in ``|x| <= POSITION_BOUND``, driven by an LQR towards a set-point beyond the bound (the uncertified controller),
with and without a safety filter, over a batch of episodes in one jitted ``lax.scan``.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

import scg_jax
from scg_algorithms.lqr import discrete_lqr_gain
from scg_jax.tracing import batched_like

POSITION_BOUND = 0.5  # m, the cart's constraint |x| <= 0.5
SETPOINT = 1.0  # m, where the uncertified LQR drives the cart
CTRL_FREQ, PHYSICS_FREQ = 15, 750  # Hz, the original's MPSC cart-pole example
SAMPLE_HALF_WIDTH = (0.6, 1.0, 0.15, 1.0)  # m, m/s, rad, rad/s: the box of model-error samples around the goal


def make_env(episode_len_sec: float = 5.0):
    """The cart-pole of the experiment (stabilisation task, position box as a linear state constraint)."""
    constraints = [
        {"type": "bounded", "on": "state", "active_dims": [0], "low": [-POSITION_BOUND], "high": [POSITION_BOUND]}
    ]
    return scg_jax.make(
        "cartpole",
        ctrl_freq=CTRL_FREQ,
        physics_freq=PHYSICS_FREQ,
        episode_len_sec=episode_len_sec,
        constraints=constraints,
    )


def setpoint_lqr(env, params, setpoint: float = SETPOINT):
    """``u(x)``: the discrete LQR (Q = I, R = 0.1) of the model about the upright pole, towards the cart position
    ``setpoint`` (m), clipped to the actuator limits (N). Pure JAX."""
    model = env.symbolic_model(params)
    lin = model.linearize(np.zeros(env.nx), np.zeros(env.nu))
    K, _ = discrete_lqr_gain(lin.Ad, lin.Bd, np.eye(env.nx), 0.1 * np.eye(env.nu))
    target = jnp.zeros(env.nx).at[0].set(setpoint)
    low, high = env.input_bounds(params.physics)
    K = jnp.asarray(K)
    return lambda x: jnp.clip(-K @ (x[: env.nx] - target), low, high)


def closed_loop(env, params, controller, safety_filter, key, num_episodes: int):
    """Run ``num_episodes`` episodes of ``controller`` (``u(obs)``, JAX) certified by ``safety_filter`` (a JAX
    filter, or ``None`` for none) in one jitted scan.

    Returns:
        dict of numpy arrays: ``violating`` (episodes, steps) bool, ``feasible`` (episodes, steps) bool,
        ``correction`` (episodes, steps) |u - u_L| in N, ``x`` (episodes, steps + 1, nx).
    """

    def episode(key):
        obs, state = env.reset(key, params)
        fstate = safety_filter.reset(key) if safety_filter is not None else ()

        def step(carry, _):
            obs, state, fstate = carry
            u_l = controller(obs)
            if safety_filter is None:
                u, feasible = u_l, jnp.ones((), bool)
            else:
                u, fstate, info = safety_filter.certify(obs, u_l, safety_filter.params, fstate)
                feasible = info.feasible
            out = env.step(state, u, params)
            record = (out.info["constraint_violation"], feasible, jnp.abs(u - u_l).max(), out.state.x)
            return (out.obs, out.state, fstate), record

        carry = batched_like((obs, state, fstate), obs)  # vmap batches the body once (scg_jax.tracing)
        _, (violating, feasible, correction, xs) = jax.lax.scan(step, carry, None, env.num_steps)
        return violating, feasible, correction, jnp.concatenate([state.x[None], xs])

    run = jax.jit(jax.vmap(episode))
    violating, feasible, correction, xs = run(jax.random.split(key, num_episodes))
    return {
        "violating": np.asarray(violating),
        "feasible": np.asarray(feasible),
        "correction": np.asarray(correction),
        "x": np.asarray(xs),
    }


def closed_loop_host(env, params, controller, safety_filter, key, num_episodes: int):
    """``closed_loop`` for a host filter (``safety_filter.is_jax`` false: the CasADi qpOASES reference), one copy and
    step at a time: the same episodes (the same ``key``), the env and the controller jitted. Returns what
    ``closed_loop`` returns."""
    reset, step, act = jax.jit(env.reset), jax.jit(env.step), jax.jit(controller)
    episodes = []
    for episode_key in jax.random.split(key, num_episodes):
        obs, state = reset(episode_key, params)
        fstate = safety_filter.reset(episode_key)
        records, xs = [], [np.asarray(state.x)]
        for _ in range(env.num_steps):
            u_l = np.asarray(act(obs), np.float64)
            u, fstate, info = safety_filter.certify(np.asarray(obs, np.float64), u_l, safety_filter.params, fstate)
            out = step(state, jnp.asarray(u, obs.dtype), params)
            records.append((bool(out.info["constraint_violation"]), bool(info.feasible), np.abs(u - u_l).max()))
            obs, state = out.obs, out.state
            xs.append(np.asarray(state.x))
        episodes.append((np.array(records), np.stack(xs)))
    records = np.stack([r for r, _ in episodes])
    return {
        "violating": records[..., 0].astype(bool),
        "feasible": records[..., 1].astype(bool),
        "correction": records[..., 2],
        "x": np.stack([x for _, x in episodes]),
    }
