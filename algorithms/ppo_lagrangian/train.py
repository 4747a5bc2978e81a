"""PPO-Lagrangian: PPO on a constrained MDP, maximise ``J_r`` subject to ``J_c <= d``.

The learner is ``scg_algorithms.ppo``'s skeleton with a ``Variant``:

- a cost critic ``V_c`` (same shape as the value network, its own Adam and gradient clip so PPO's updates are
  untouched) fitted to the cost returns of ``out.cost`` (1 at a step in violation), with cost GAE
  (``cost_gamma``, ``cost_gae_lambda``);
- once per rollout, before the SGD epochs, the multiplier takes one step towards ``J_c = d``, where ``J_c`` is the
  rollout's fraction of violating steps (``cost_limit_unit: fraction``) or the mean cost of the episodes finished in
  it (``per_episode``; no step when none finished): an Adam step on ``-lambda (J_c - d)`` clipped at 0
  (``lambda_optimizer: adam``, OmniSafe's rule, ``multiplier_adam_update``) or the projected ascent step
  ``lambda <- max(0, lambda + lambda_lr (J_c - d))`` (``sgd``, ``multiplier_update``);
- the actor's advantage is ``(A_r - lambda A_c) / (1 + lambda)`` (``combine_advantages``); with
  ``normalize_advantages`` the reward advantages are standardised per minibatch and the cost advantages centred
  (``cost_advantage: center``, OmniSafe's choice) or standardised (``standardize``).

With ``lambda`` 0 throughout (the limit never reached, ``lagrange_init`` 0) the actor and critic receive exactly
PPO's updates from exactly PPO's random numbers: the parameters equal plain PPO's bit for bit.

Metrics added to PPO's: ``lagrange_multiplier``, ``cost_estimate`` (``J_c`` of the rollout), ``cost_value_loss``.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import optax

from scg_algorithms.base import parse_options
from scg_algorithms.ppo import losses
from scg_algorithms.ppo.train import Variant, make_variant_learner
from scg_algorithms.ppo_lagrangian.config import Config
from scg_algorithms.rl.networks import value_network
from scg_algorithms.rl.training import Learner

NAME = "ppo_lagrangian"
PATH = f"training.{NAME}"


def multiplier_update(multiplier, cost_estimate, cost_limit, lr):
    """``max(0, lambda + lr (J_c - d))``: one projected gradient-ascent step of the Lagrange multiplier; a NaN
    ``cost_estimate`` (no measurement) leaves it unchanged."""
    stepped = jnp.maximum(0.0, multiplier + lr * (cost_estimate - cost_limit))
    return jnp.where(jnp.isnan(cost_estimate), multiplier, stepped)


def multiplier_optimizer(lr: float) -> optax.GradientTransformation:
    """Adam on the multiplier (OmniSafe's ``Lagrange``), for ``multiplier_adam_update``."""
    return optax.adam(lr)


def multiplier_adam_update(multiplier, opt_state, cost_estimate, cost_limit, lr):
    """One Adam step on the loss ``-lambda (J_c - d)`` (gradient ``-(J_c - d)``), then ``lambda`` clipped at 0:
    ``(multiplier, opt_state)``. Adam's steps are about ``lr`` long whatever the size of ``J_c - d``, so a multiplier
    raised by early violations falls as fast once the cost is under the limit (plain ascent falls by at most
    ``lr d`` per step). A NaN ``cost_estimate`` leaves both unchanged."""
    grad = -(cost_estimate - cost_limit)
    updates, stepped_state = multiplier_optimizer(lr).update(jnp.where(jnp.isnan(grad), 0.0, grad), opt_state)
    stepped = jnp.maximum(0.0, multiplier + updates)
    skip = jnp.isnan(cost_estimate)
    opt_state = jax.tree.map(lambda old, new: jnp.where(skip, old, new), opt_state, stepped_state)
    return jnp.where(skip, multiplier, stepped), opt_state


def center_advantages(advantages):
    """``A - mean(A)``: the cost advantages' normalisation with ``cost_advantage: center`` (their scale is kept, so
    a minibatch with few violations gives small cost advantages instead of unit-variance noise)."""
    return advantages - jnp.mean(advantages)


def combine_advantages(reward_advantages, cost_advantages, multiplier):
    """``(A_r - lambda A_c) / (1 + lambda)``: the penalised advantage, scaled so its size does not grow with
    ``lambda``."""
    return (reward_advantages - multiplier * cost_advantages) / (1.0 + multiplier)


def cost_gae(cost, cost_values, next_cost_values, terminated, truncated, config: Config):
    """Cost advantages and cost-value targets, (T, N) each: ``losses.gae`` on the per-step cost (1 at a step in
    violation) with ``cost_gamma`` and ``cost_gae_lambda``.

    With ``termination_cost: absorbing`` a terminated episode is taken to stay where it ended: the step's cost
    continues forever, so the bootstrap at a termination is ``cost_t / (1 - cost_gamma)`` instead of 0 (the trace
    still stops there). Otherwise ending an episode early would end its costs too, and a large multiplier would
    teach the policy to crash. With ``none`` nothing follows a termination.
    """
    if config.termination_cost == "absorbing":
        next_cost_values = jnp.where(terminated, cost / (1.0 - config.cost_gamma), next_cost_values)
        return losses.gae(
            cost, cost_values, next_cost_values, jnp.zeros_like(terminated), terminated | truncated,
            config.cost_gamma, config.cost_gae_lambda,
        )  # fmt: skip
    return losses.gae(
        cost, cost_values, next_cost_values, terminated, truncated, config.cost_gamma, config.cost_gae_lambda
    )


def make_learner(config, env) -> Learner:
    """PPO-Lagrangian as a ``Learner`` for ``run_training``.

    Args:
        config: a ``Config`` or a mapping (the ``training.ppo_lagrangian`` section; ``None`` for defaults).
        env: an ``scg_jax.Env`` (its ``out.cost`` is the constraint signal: without constraints it is always 0).

    Raises:
        ValueError: a bad option, named ``training.ppo_lagrangian.<field>`` (e.g. a cost limit below 0).
    """
    config = parse_options(Config, config, PATH)
    cost_critic = value_network(config.critic_hidden, config.activation)
    cost_optimizer = optax.chain(
        optax.clip_by_global_norm(config.max_grad_norm), optax.adam(config.learning_rate, eps=1e-5)
    )

    def cost_value(critic_params, obs):
        return cost_critic.apply(critic_params, obs)[..., 0]

    def init_aux(key, params):
        critic_params = cost_critic.init(key, jnp.zeros((1, env.observation_size)))
        multiplier = jnp.asarray(config.lagrange_init, jnp.float32)
        return {
            "multiplier": multiplier,
            "multiplier_opt_state": multiplier_optimizer(config.lambda_lr).init(multiplier),
            "cost_critic": critic_params,
            "cost_opt_state": cost_optimizer.init(critic_params),
        }

    def prepare(aux, traj, episode, data, flat):
        if config.cost_limit_unit == "fraction":
            cost_estimate = jnp.mean(traj.cost)
        else:
            cost_estimate = jnp.where(episode["episodes_finished"] > 0, episode["episode_cost"], jnp.nan)
        multiplier_opt_state = aux["multiplier_opt_state"]
        if config.lambda_optimizer == "adam":
            multiplier, multiplier_opt_state = multiplier_adam_update(
                aux["multiplier"], multiplier_opt_state, cost_estimate, config.cost_limit, config.lambda_lr
            )
        else:
            multiplier = multiplier_update(aux["multiplier"], cost_estimate, config.cost_limit, config.lambda_lr)
        cost_values = cost_value(aux["cost_critic"], traj.obs)
        next_cost_values = cost_value(aux["cost_critic"], traj.next_obs)
        cost_advantages, cost_returns = cost_gae(
            traj.cost, cost_values, next_cost_values, traj.terminated, traj.truncated, config
        )
        data = {
            **data,
            "cost_advantages": flat(cost_advantages),
            "cost_returns": flat(cost_returns),
            "cost_value": flat(cost_values),
        }
        metrics = {"lagrange_multiplier": multiplier, "cost_estimate": cost_estimate}
        return {**aux, "multiplier": multiplier, "multiplier_opt_state": multiplier_opt_state}, data, metrics

    def advantages(aux, mb):
        reward_adv, cost_adv = mb["advantages"], mb["cost_advantages"]
        if config.normalize_advantages:
            reward_adv = losses.normalize_advantages(reward_adv)
            if config.cost_advantage == "center":
                cost_adv = center_advantages(cost_adv)
            else:
                cost_adv = losses.normalize_advantages(cost_adv)
        return combine_advantages(reward_adv, cost_adv, aux["multiplier"])

    value_clip = config.value_clip_eps if config.value_clip_eps > 0 else None

    def cost_loss(critic_params, mb):
        return losses.value_loss(cost_value(critic_params, mb["obs"]), mb["cost_value"], mb["cost_returns"], value_clip)

    cost_grad = jax.value_and_grad(cost_loss)

    def aux_step(aux, mb):
        loss, grads = cost_grad(aux["cost_critic"], mb)
        updates, opt_state = cost_optimizer.update(grads, aux["cost_opt_state"], aux["cost_critic"])
        critic_params = optax.apply_updates(aux["cost_critic"], updates)
        return {**aux, "cost_critic": critic_params, "cost_opt_state": opt_state}, {"cost_value_loss": loss}

    variant = Variant(init_aux=init_aux, prepare=prepare, advantages=advantages, aux_step=aux_step)
    return make_variant_learner(NAME, config, env, variant)
