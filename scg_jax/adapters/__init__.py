"""Adapters that expose scg-jax environments through other libraries' interfaces (Gymnasium, brax).

Nothing heavy is imported here: each adapter lives in its own module (``scg_jax.adapters.gymnasium``, ...) and
imports its library only when it is used.
"""

from __future__ import annotations

from scg_jax.systems import SYSTEMS

# Gymnasium ids, from each system's record (``System.gymnasium_id``). The environments truncate themselves at
# ``episode_len_sec``, so no ``TimeLimit`` wrapper is registered (``max_episode_steps=None``).
GYMNASIUM_IDS = {name: system.gymnasium_id for name, system in SYSTEMS.items()}


def register_gymnasium_envs() -> None:
    """Register the ids of ``GYMNASIUM_IDS`` with Gymnasium (idempotent; ``import scg_jax`` calls it).

    Each id takes the options of ``scg_jax.make`` (``task``, ``trajectory``, ``constraints``, ``disturbances``,
    ...) or ``config=`` (a path or ``Config``) with ``overrides=[...]``; ``gymnasium.make_vec`` builds the
    batched ``ScgVectorEnv`` through ``vector_entry_point``.
    """
    import gymnasium

    for system, env_id in GYMNASIUM_IDS.items():
        if env_id in gymnasium.registry:
            continue
        gymnasium.register(
            id=env_id,
            entry_point="scg_jax.adapters.gymnasium:ScgGymEnv",
            vector_entry_point="scg_jax.adapters.gymnasium:ScgVectorEnv",
            kwargs={"system": system},
            max_episode_steps=None,
            nondeterministic=False,
        )
