"""Shared fixtures. Tests that need float64 wrap their body in ``with jax.enable_x64(True):``."""

import jax
import pytest

import scg_jax

SYSTEM_NAMES = tuple(scg_jax.SYSTEMS)


@pytest.fixture(scope="session")
def envs():
    """One stabilization env per system, built once for the session (jitted functions cache per env)."""
    return {name: scg_jax.make(name) for name in SYSTEM_NAMES}


@pytest.fixture(scope="session")
def jitted_step(envs):
    """A jitted ``step`` per system, so tests reuse one compilation."""
    return {name: jax.jit(env.step) for name, env in envs.items()}
