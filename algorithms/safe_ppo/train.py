"""Safety-layer PPO (Dalal et al. 2018): PPO acting through the safety layer's projection of its mean.

The learner is ``scg_algorithms.ppo``'s skeleton with a ``Variant``: ``init`` pretrains the constraint models
(``layer.pretrain``, random actions, seconds) and freezes them; every action is then sampled from
``N(project(mu(obs)), sigma)`` and its log-probability is taken under the projected mean (the projection is part
of the policy, and the PPO ratio differentiates through it). Exploration noise can still violate a constraint,
as in the original. The deterministic policy saved for evaluation is ``clip(project(mu(obs)), -1, 1)``; it carries
the frozen layer (``policy_params["layer"]``), so ``scg-jax eval --controller DIR`` runs it like any controller.

Metrics added to PPO's: ``constraint_model_mse`` (held-out MSE of the pretrained models),
``constraint_model_baseline_mse``, ``constraint_model_train_mse``, ``pretrain_env_steps`` (random-action steps spent
on pretraining, not counted in ``env_steps``).
"""

from __future__ import annotations

import jax.numpy as jnp

from scg_algorithms.base import parse_options
from scg_algorithms.ppo.train import Variant, make_variant_learner
from scg_algorithms.rl.envs import make_train_env
from scg_algorithms.rl.training import Learner, raw_key
from scg_algorithms.safe_ppo import layer as layer_lib
from scg_algorithms.safe_ppo.config import Config

NAME = "safe_ppo"
PATH = f"training.{NAME}"


def _slack(config: Config, num_rows: int):
    slack = config.constraint_slack
    if len(slack) not in (1, num_rows):
        raise ValueError(
            f"{PATH}.constraint_slack: expected 1 value or {num_rows} (one per state-constraint row of the env), "
            f"got {len(slack)}"
        )
    return jnp.broadcast_to(jnp.asarray(slack, jnp.float32), (num_rows,))


def make_learner(config, env, params=None) -> Learner:
    """Safety-layer PPO as a ``Learner`` for ``run_training``.

    Args:
        config: a ``Config`` or a mapping (the ``training.safe_ppo`` section; ``None`` for defaults). env: an
            ``scg_jax.Env`` with at least one linear state constraint. params: ``EnvParams`` to check the rows
            against now (default ``env.default_params``); the rows used are those of the ``params`` given to
            ``init``.

    Raises:
        ValueError: a bad option (named ``training.safe_ppo.<field>``) or an env without state constraints
            (named ``env.constraints``).
    """
    config = parse_options(Config, config, PATH)
    check_params = env.default_params if params is None else params
    A, _ = layer_lib.state_constraint_rows(env, check_params)
    slack = _slack(config, A.shape[0])
    if env.observation_size < env.system.nx:
        raise ValueError(f"env: the safety layer reads the state from the observation, which has fewer than nx = "
                         f"{env.system.nx} entries")  # fmt: skip
    train_env = make_train_env(env, config.num_envs, config.action_scale)
    _, apply = layer_lib.make_constraint_model(config.constraint_hidden_dim, train_env.action_size)

    def init_aux(key, params):
        rows = layer_lib.state_constraint_rows(env, params)
        layer, stats = layer_lib.pretrain(config, train_env, raw_key(key), params, rows)
        return {"layer": layer, "stats": stats}

    def context(layer, raw_obs):
        return {"g": apply(layer["model"], raw_obs), "c": layer_lib.constraint_values(layer, raw_obs)}

    def project(ctx, mean):
        return layer_lib.project_mean(mean, ctx["g"], ctx["c"], slack)

    def prepare(aux, traj, episode, data, flat):
        return aux, data, dict(aux["stats"])

    variant = Variant(
        init_aux=init_aux, context=context, project=project, prepare=prepare, policy_aux=lambda aux: aux["layer"]
    )
    return make_variant_learner(NAME, config, env, variant)
