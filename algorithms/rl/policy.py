"""A trained policy saved by ``run_training`` as a controller the evaluation harness can run."""

from __future__ import annotations

from pathlib import Path

import jax
import jax.numpy as jnp
import yaml

from scg_algorithms.base import JaxController, parse_options
from scg_algorithms.learners import LEARNERS, learner_part
from scg_algorithms.rl.checkpoint import load_checkpoint, load_metadata
from scg_algorithms.rl.envs import policy_action_to_input
from scg_algorithms.rl.training import POLICY_NAME


def algorithm_module(algo: str, part: str):
    """``Config``, ``make_learner`` or ``make_policy_learner`` of the JAX learner ``algo`` in the registry
    (``scg_algorithms.learners.learner_part``; kept under this name for its callers)."""
    return learner_part(algo, part)


def trained_system(meta: dict) -> str | None:
    """The system a policy was trained on: ``policy.json``'s ``system`` (recorded since it exists), else the
    ``env.system`` of its stored env config; None if neither says."""
    if isinstance(meta.get("system"), str):
        return meta["system"]
    text = meta.get("env_config")
    if not isinstance(text, str):
        return None
    try:
        env_section = (yaml.safe_load(text) or {}).get("env") or {}
    except (yaml.YAMLError, AttributeError):
        return None
    system = env_section.get("system") if isinstance(env_section, dict) else None
    return system if isinstance(system, str) else None


def load_learner(directory, env):
    """The ``Learner`` whose policy was saved in ``directory`` (rebuilt from ``policy.json``), and the metadata.

    Raises:
        ValueError: the policy was trained on another system than ``env``'s (even with the same observation
            size, its inputs would mean something else), or observes another number of values.
    """
    meta = load_metadata(directory, POLICY_NAME)
    algo = meta.get("algo")
    jax_learners = [name for name, spec in LEARNERS.items() if spec.is_jax]
    if algo not in jax_learners:
        raise ValueError(
            f"{Path(directory) / POLICY_NAME}.json: algo must name a JAX learner ({', '.join(jax_learners)}), got "
            f"{algo!r}"
        )
    system = trained_system(meta)
    if system is not None and system != env.system.name:
        raise ValueError(
            f"{Path(directory) / POLICY_NAME}.json: the policy was trained on the {system} and cannot control the "
            f"{env.system.name}; evaluate it on the {system} (its config: env.system: {system})"
        )
    if meta.get("obs_size") is not None and meta["obs_size"] != env.observation_size:
        raise ValueError(
            f"{Path(directory) / POLICY_NAME}.json: the policy observes {meta['obs_size']} values but the env gives "
            f"{env.observation_size} (a different obs_goal_horizon or system?)"
        )
    config = parse_options(algorithm_module(algo, "Config"), meta.get("config") or {}, f"training.{algo}")
    return algorithm_module(algo, "make_policy_learner")(config, env), meta


def load_policy(directory, env, params) -> JaxController:
    """The deterministic policy saved in ``directory`` as a stateless ``JaxController``.

    Args:
        directory: a folder with ``policy.json`` and ``policy.msgpack`` (``run_training``'s ``out_dir``).
        env: the ``scg_jax.Env`` to act in (same observation layout as in training). params: ``EnvParams`` whose
            nominal physics converts the policy's action in [-1, 1] to the physical input.

    Returns:
        ``JaxController`` named after the algorithm; ``act`` returns ``u = env.system.action_to_input(a,
        params.physics)`` (nu,) in N for the mean action ``a``, ``ctrl_state = ()``.
    """
    learner, meta = load_learner(directory, env)
    target = jax.eval_shape(lambda key: learner.policy_params(learner.init(key, params)), jax.random.PRNGKey(0))
    policy_params, _ = load_checkpoint(directory, POLICY_NAME, target)
    policy_params = jax.tree.map(jnp.asarray, policy_params)
    info = {"directory": str(directory), "iterations": meta.get("iterations"), "env_steps": meta.get("env_steps")}
    return policy_controller(env, params, learner, policy_params, info=info)


def policy_controller(env, params, learner, policy_params, info=None) -> JaxController:
    """The deterministic policy of ``learner`` with ``policy_params`` as a stateless ``JaxController``.

    ``act`` returns ``u = policy_action_to_input(env, a, params.physics, learner.config.action_scale)`` (nu,) in N
    for the mean action ``a``; ``ctrl_state = ()``. The controller is named after the learner.
    """
    policy = learner.make_policy(policy_params)
    physics = params.physics
    action_scale = getattr(learner.config, "action_scale", 1.0)

    def act(ctrl_state, obs, step, reference):
        return policy_action_to_input(env, policy(obs, None), physics, action_scale), ctrl_state

    return JaxController(name=learner.name, reset_fn=lambda key, reference: (), act_fn=act, info=dict(info or {}))
