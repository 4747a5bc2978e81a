"""Uncertified controllers that drive a plant out of its safe set, to exercise and train safety filters."""

from __future__ import annotations

import jax
import jax.numpy as jnp

from scg_algorithms.base import JaxController
from scg_algorithms.controller_setup import input_limits


def random_input(env, params, name: str = "random_input") -> JaxController:
    """Inputs drawn uniformly from the actuator box of ``params`` at every step (N), from the copy's own key.

    The 1D quadrotor's box mean (0.353 N) exceeds hover (0.265 N), so it climbs: the altitude-ceiling test's
    uncertified controller. State: the PRNG key.
    """
    low, high = input_limits(env, params)

    def reset_fn(key, reference):
        return key

    def act_fn(key, obs, step, reference):
        key, sample = jax.random.split(key)
        dtype = jnp.asarray(obs).dtype  # float32 unless x64 is on, also for numpy observations (host loops)
        lo, hi = jnp.asarray(low).astype(dtype), jnp.asarray(high).astype(dtype)
        return jax.random.uniform(sample, lo.shape, dtype, lo, hi), key

    return JaxController(name=name, reset_fn=reset_fn, act_fn=act_fn, info={"u_low": low, "u_high": high})


__all__ = ["random_input"]
