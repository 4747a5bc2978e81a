"""Adversarial PPO, shared by RARL (one adversary) and RAP (a population): a protagonist and ``M`` adversaries,
all Gaussian MLP policies trained with PPO's clipped losses, in one jitted ``update``.

The adversaries act through the env's adversary input (``scg_jax.make(..., adversary={"channel", "scale"})``): an
adversary's action ``b`` in [-1, 1] (the env clips it) is multiplied by ``params.adversary_scale`` and added to the
commanded input ``u`` (``action`` channel, N) or applied as the external force ``f_ext`` on the plant
(``dynamics`` channel, N; for the cart-pole a force on the pole's centre of mass). The game is zero-sum: an
adversary's reward is ``-r`` for the protagonist's reward ``r`` (``adversary_rewards``), and it observes the same
(normalised) observation.

Per-copy assignment: each of the N env copies is driven by one adversary, ``adversary_index`` (N,) in the runner
state, drawn uniformly from ``range(M)`` at the start of every episode (the first reset and each automatic reset),
so an episode is played against one adversary from start to end, and episodes run on across iterations (the
original RAP reset every copy at every update, so its agents never saw the end of an episode; not here).

One iteration:

1. ``rollout_length`` steps of the N copies (``collect_adversarial``): the protagonist samples its action, the
   copy's adversary its input, the env steps and auto-resets, the copies whose episode ended draw a new adversary;
2. GAE for the protagonist on ``r`` with its critic, and for the adversaries on ``-r`` with the critic of the
   adversary that acted at each step (bootstrap at a time limit, none at a termination);
3. PPO epochs for the protagonist and, vmapped over the population, for each adversary on the steps it acted in
   (``masked_ppo_loss``: the PPO loss averaged over those steps only), as the schedule says: ``alternating``
   (``protagonist_iterations`` iterations updating only the protagonist, then ``adversary_iterations`` updating
   only the adversaries, each on fresh rollouts; RARL's loop) or ``joint`` (both from the same rollout every
   iteration; RAP's loop).

The saved policy (``policy_params``) is the protagonist's, with the same structure as PPO's, so the trained
protagonist is evaluated as a controller by the same harness (``scg_algorithms.rl.policy.load_policy``).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import optax

from scg_algorithms.base import option
from scg_algorithms.ppo import losses
from scg_algorithms.rl.collector import CollectorState, Transitions, init_collector
from scg_algorithms.rl.config import check_fields, layer_sizes
from scg_algorithms.rl.counter import Count, add_count, zero_count
from scg_algorithms.rl.envs import EPISODE_METRICS, episode_means, make_train_env, update_episode_stats
from scg_algorithms.rl.networks import MLP, value_network
from scg_algorithms.rl.normalization import RunningStats, normalize, update_stats
from scg_algorithms.rl.training import Learner, raw_key

SCHEDULES = ("alternating", "joint")
ADVERSARY_CHANNELS = ("action", "dynamics")


# --------------------------------------------------------------------------------------------- options
def schedule_option(default: str):
    return option(
        default,
        "alternating: protagonist_iterations iterations updating the protagonist, then adversary_iterations "
        "updating the adversaries (each on fresh rollouts); joint: both from every rollout",
        choices=SCHEDULES,
    )


def protagonist_iterations_option():
    return option(1, "alternating schedule: consecutive iterations updating only the protagonist")


def adversary_iterations_option():
    return option(1, "alternating schedule: consecutive iterations updating only the adversaries")


def adversary_learning_rate_option():
    return option(1e-3, "Adam step size of the adversaries (decayed like the protagonist's with lr_decay)")


def adversary_init_log_std_option():
    return option(-1.0, "initial log standard deviation of the adversaries' Gaussian policies (in [-1, 1] units)")


def adversary_hidden_option():
    return option((64, 64), "hidden layer sizes of each adversary's policy mean and value networks")


def check_robust_fields(config, path: str) -> None:
    """The adversarial fields of a RARL/RAP ``Config`` (the PPO fields are checked by the PPO ``_check``)."""
    check_fields(config, path, positive_fields=("adversary_learning_rate", "num_adversaries"))
    for name in ("protagonist_iterations", "adversary_iterations"):
        if getattr(config, name) < 0:
            raise ValueError(f"{path}.{name}: must be >= 0, got {getattr(config, name)!r}")
    if config.schedule == "alternating" and config.protagonist_iterations + config.adversary_iterations < 1:
        raise ValueError(
            f"{path}.protagonist_iterations: with schedule 'alternating', protagonist_iterations + "
            f"adversary_iterations must be at least 1, got {config.protagonist_iterations} and "
            f"{config.adversary_iterations}"
        )
    object.__setattr__(config, "adversary_hidden", layer_sizes(f"{path}.adversary_hidden", config.adversary_hidden))


def adversary_dim(env, algo: str) -> int:
    """The dimension of ``env``'s adversary channel; ValueError (naming ``env.adversary``) when the env has no
    adversary input, or it is on a channel an adversarial learner does not drive (``observation``), or the
    system's channel is empty."""
    channel = getattr(env, "adversary_channel", None)
    if channel is None:
        raise ValueError(
            f"env.adversary: {algo} trains against an adversary acting through the env's adversary input, but this "
            "env was made without one; add `adversary: {channel: action, scale: 1.0}` (channel action or dynamics) "
            "to the env section"
        )
    if channel not in ADVERSARY_CHANNELS:
        raise ValueError(
            f"env.adversary.channel: {algo}'s adversary acts on the plant; allowed values are "
            f"{', '.join(ADVERSARY_CHANNELS)}, got {channel!r}"
        )
    dim = int(env.channel_dim(channel))
    if dim < 1:
        raise ValueError(
            f"env.adversary.channel: the {env.system.name} has no {channel} channel to disturb (dimension 0); "
            f"allowed values are those of dimension >= 1"
        )
    return dim


# --------------------------------------------------------------------------------------------- pure pieces
def adversary_rewards(reward):
    """The adversaries' reward for the protagonist's reward ``reward`` (any shape): ``-reward`` (zero-sum)."""
    return -reward


def assign_adversaries(key, index, done, num_adversaries: int):
    """The adversary of each copy for its next step: a fresh uniform draw from ``range(num_adversaries)`` where
    the copy's episode ended (``done``), the old ``index`` elsewhere. index, done: (N,); returns (N,) int32."""
    fresh = jax.random.randint(key, index.shape, 0, num_adversaries, dtype=jnp.int32)
    return jnp.where(done, fresh, index)


def masked_ppo_loss(
    mean,
    log_std,
    values,
    actions,
    old_log_prob,
    old_values,
    advantages,
    returns,
    weight,
    *,
    clip_eps: float,
    vf_coef: float,
    ent_coef: float,
    normalize: bool,
):
    """``losses.ppo_loss`` over the samples with ``weight`` 1 only (``weight`` (B,) of 0/1): every mean is a
    weighted mean, and advantages are normalised with the weighted mean and std. With all weights 1 it equals
    ``losses.ppo_loss`` (unclipped value loss). No sample (all weights 0): zero loss and gradient.

    Returns:
        ``(loss, info)`` with ``policy_loss``, ``value_loss``, ``entropy``, ``clip_fraction``, ``approx_kl``.
    """
    count = jnp.maximum(jnp.sum(weight), 1.0)
    wmean = lambda x: jnp.sum(weight * x) / count  # noqa: E731
    if normalize:
        centre = wmean(advantages)
        std = jnp.sqrt(wmean(jnp.square(advantages - centre)))
        advantages = (advantages - centre) / (std + 1e-8)
    log_prob = losses.gaussian_log_prob(mean, log_std, actions)
    log_ratio = log_prob - old_log_prob
    ratio = jnp.exp(log_ratio)
    surrogate = jnp.minimum(ratio * advantages, jnp.clip(ratio, 1.0 - clip_eps, 1.0 + clip_eps) * advantages)
    policy_loss = -wmean(surrogate)
    v_loss = 0.5 * wmean(jnp.square(values - returns))
    entropy = losses.gaussian_entropy(log_std)
    any_sample = (jnp.sum(weight) > 0).astype(mean.dtype)
    loss = policy_loss + vf_coef * v_loss - any_sample * ent_coef * entropy
    info = {
        "policy_loss": policy_loss,
        "value_loss": v_loss,
        "entropy": entropy,
        "clip_fraction": wmean((jnp.abs(ratio - 1.0) > clip_eps).astype(ratio.dtype)),
        "approx_kl": wmean((ratio - 1.0) - log_ratio),
    }
    return loss, info


def update_flags(iteration, config):
    """``(protagonist_updates, adversary_updates)`` (bool scalars) at 0-based ``iteration`` under
    ``config.schedule``: joint, both; alternating, the protagonist in the first ``protagonist_iterations`` of each
    cycle of ``protagonist_iterations + adversary_iterations`` iterations, the adversaries in the rest."""
    if config.schedule == "joint":
        true = jnp.asarray(True)
        return true, true
    cycle = config.protagonist_iterations + config.adversary_iterations
    protagonist = (iteration % cycle) < config.protagonist_iterations
    return protagonist, jnp.logical_not(protagonist)


def update_counts(config) -> tuple[int, int]:
    """Iterations in the budget that update the protagonist and the adversaries (for the step-size decay)."""
    flags = [
        (i % max(config.protagonist_iterations + config.adversary_iterations, 1)) < config.protagonist_iterations
        for i in range(config.num_iterations)
    ]
    if config.schedule == "joint":
        return config.num_iterations, config.num_iterations
    return sum(flags), config.num_iterations - sum(flags)


# --------------------------------------------------------------------------------------------- state
class Agent(NamedTuple):
    """One PPO agent: ``params`` ``{"actor", "critic", "log_std"}`` and its optax state (adversaries: every leaf
    stacked on a leading population axis M)."""

    params: Any
    opt_state: Any


class RunnerState(NamedTuple):
    """Everything a RARL/RAP run carries between iterations (one pytree, checkpointed whole).

    Attributes:
        protagonist: ``Agent``. adversaries: ``Agent`` with leaves (M, ...). adversary_index: (N,) int32, the
        adversary of each copy for its next step. collector: ``CollectorState`` (env states, observations,
        episode sums, observation normaliser). key: raw PRNG key. env_steps: ``Count``. iteration: int32,
        iterations done (the alternating schedule's clock).
    """

    protagonist: Agent
    adversaries: Agent
    adversary_index: Any
    collector: CollectorState
    key: Any
    env_steps: Count
    iteration: Any

    @property
    def obs_stats(self) -> RunningStats:
        return self.collector.obs_stats


def collect_adversarial(train_env, params, state: CollectorState, index, act, key, num_steps: int, num_adversaries,
                        *, update_normalizer: bool = True, info_keys: tuple[str, ...] = ()):  # fmt: skip
    """``scg_algorithms.rl.collector.collect`` with a per-copy adversary assignment carried through the scan.

    Args:
        act: ``act(obs (N, obs_size), index (N,), key) -> ActOutput`` with the adversary's input in
            ``adversary``. index: (N,) int32, each copy's adversary. num_adversaries: M (new draws at episode
            starts). Others as ``collect``.

    Returns:
        ``(state, index, transitions, episode)``: ``transitions.extras["adversary_index"]`` (T, N) is the
        adversary that acted at each step.
    """

    def step(carry, step_key):
        env_state, obs, episode_stats, index = carry
        key_act, key_assign = jax.random.split(step_key)
        out_act = act(obs, index, key_act)
        out = train_env.step(env_state, out_act.action, params, adversary=out_act.adversary)
        episode_stats, finished = update_episode_stats(episode_stats, out)
        transition = Transitions(
            obs=obs,
            action=out_act.action,
            reward=out.reward,
            cost=out.cost,
            terminated=out.terminated,
            truncated=out.truncated,
            next_obs=out.final_obs,
            info={name: out.info[name] for name in info_keys},
            extras={**out_act.extras, "adversary_index": index},
            adversary=out_act.adversary,
        )
        index = assign_adversaries(key_assign, index, finished.done, num_adversaries)
        return (out.state, out.obs.astype(obs.dtype), episode_stats, index), (transition, finished)

    carry = (state.env_state, state.obs, state.episode_stats, index)
    (env_state, obs, episode_stats, index), (transitions, finished) = jax.lax.scan(
        step, carry, jax.random.split(key, num_steps)
    )
    obs_stats = update_stats(state.obs_stats, transitions.obs) if update_normalizer else state.obs_stats
    episode = episode_means(finished, state.last_episode)
    new_state = CollectorState(
        env_state=env_state,
        obs=obs,
        episode_stats=episode_stats,
        last_episode={name: episode[name] for name in EPISODE_METRICS},
        obs_stats=obs_stats,
    )
    return new_state, index, transitions, episode


def _optimizer(learning_rate: float, config, num_updating_iterations: int):
    if config.lr_decay:
        steps = max(1, num_updating_iterations * config.num_epochs * config.num_minibatches)
        learning_rate = optax.linear_schedule(learning_rate, 0.0, transition_steps=steps)
    return optax.chain(optax.clip_by_global_norm(config.max_grad_norm), optax.adam(learning_rate, eps=1e-5))


class Functions(NamedTuple):
    """What ``make_functions`` builds: the Learner's pieces plus ``rollout`` (for tests) and the networks."""

    init: Any
    update: Any
    rollout: Any
    policy_params: Any
    make_policy: Any
    train_env: Any
    adversary_actor: Any


def make_functions(config, env, num_adversaries: int, algo: str) -> Functions:
    """init, update, rollout, policy_params and make_policy of an adversarial PPO run with M = ``num_adversaries``.

    Raises:
        ValueError: ``env.adversary`` missing or on an unsupported channel (``adversary_dim``).
    """
    adv_dim = adversary_dim(env, algo)
    train_env = make_train_env(env, config.num_envs, config.action_scale)
    actor = MLP((*config.actor_hidden, train_env.action_size), config.activation, final_scale=0.01)
    critic = value_network(config.critic_hidden, config.activation)
    adv_actor = MLP((*config.adversary_hidden, adv_dim), config.activation, final_scale=0.01)
    adv_critic = value_network(config.adversary_hidden, config.activation)
    n_protagonist, n_adversary = update_counts(config)
    protagonist_opt = _optimizer(config.learning_rate, config, n_protagonist)
    adversary_opt = _optimizer(config.adversary_learning_rate, config, n_adversary)
    batch = config.batch_size
    minibatch = batch // config.num_minibatches
    value_clip = config.value_clip_eps if config.value_clip_eps > 0 else None
    M = int(num_adversaries)

    def observe(stats, obs):
        return normalize(stats, obs, config.obs_clip) if config.normalize_observations else obs

    def init(key, params) -> RunnerState:
        key = raw_key(key)
        key, key_actor, key_critic, key_adv, key_env, key_index = jax.random.split(key, 6)
        dummy = jnp.zeros((1, train_env.obs_size))
        protagonist = {
            "actor": actor.init(key_actor, dummy),
            "critic": critic.init(key_critic, dummy),
            "log_std": jnp.full((train_env.action_size,), config.init_log_std, jnp.float32),
        }

        def one_adversary(k):
            k_actor, k_critic = jax.random.split(k)
            return {
                "actor": adv_actor.init(k_actor, dummy),
                "critic": adv_critic.init(k_critic, dummy),
                "log_std": jnp.full((adv_dim,), config.adversary_init_log_std, jnp.float32),
            }

        adversaries = jax.vmap(one_adversary)(jax.random.split(key_adv, M))
        return RunnerState(
            protagonist=Agent(protagonist, protagonist_opt.init(protagonist)),
            adversaries=Agent(adversaries, jax.vmap(adversary_opt.init)(adversaries)),
            adversary_index=jax.random.randint(key_index, (config.num_envs,), 0, M, dtype=jnp.int32),
            collector=init_collector(train_env, key_env, params),
            key=key,
            env_steps=zero_count(),
            iteration=jnp.zeros((), jnp.int32),
        )

    def rollout(runner: RunnerState, params, key, info_keys: tuple[str, ...] = ()):
        """The rollout of one iteration: ``(collector, adversary_index, transitions, episode)``; the transitions'
        ``obs`` and ``next_obs`` raw, extras ``log_prob``, ``adversary_log_prob``, ``adversary_index``."""
        net, adv = runner.protagonist.params, runner.adversaries.params
        stats = runner.collector.obs_stats
        std = jnp.exp(net["log_std"])

        def act(raw_obs, index, step_key):
            from scg_algorithms.rl.collector import ActOutput

            key_p, key_a = jax.random.split(step_key)
            obs = observe(stats, raw_obs)
            mean = actor.apply(net["actor"], obs)
            action = mean + std * jax.random.normal(key_p, mean.shape, mean.dtype)
            # Every adversary's mean on every copy, then each copy's own: M is small, a gather is cheaper than a
            # per-copy parameter gather of the whole network.
            all_means = jax.vmap(adv_actor.apply, in_axes=(0, None))(adv["actor"], obs)  # (M, N, d)
            adv_mean = jnp.take_along_axis(all_means, index[None, :, None], axis=0)[0]
            adv_log_std = adv["log_std"][index]  # (N, d)
            adv_action = adv_mean + jnp.exp(adv_log_std) * jax.random.normal(key_a, adv_mean.shape, adv_mean.dtype)
            extras = {
                "log_prob": losses.gaussian_log_prob(mean, net["log_std"], action),
                "adversary_log_prob": losses.gaussian_log_prob(adv_mean, adv_log_std, adv_action),
            }
            return ActOutput(action, extras, adv_action)

        return collect_adversarial(
            train_env,
            params,
            runner.collector,
            runner.adversary_index,
            act,
            key,
            config.rollout_length,
            M,
            update_normalizer=config.normalize_observations,
            info_keys=info_keys,
        )

    def protagonist_loss(net_params, mb):
        mean = actor.apply(net_params["actor"], mb["obs"])
        values = critic.apply(net_params["critic"], mb["obs"])[..., 0]
        advantages = mb["advantages"]
        if config.normalize_advantages:
            advantages = losses.normalize_advantages(advantages)
        return losses.ppo_loss(
            mean, net_params["log_std"], values, mb["action"], mb["log_prob"], mb["value"], advantages,
            mb["returns"], clip_eps=config.clip_eps, value_clip_eps=value_clip, vf_coef=config.vf_coef,
            ent_coef=config.ent_coef,
        )  # fmt: skip

    def adversary_loss(net_params, mb, member):
        mean = adv_actor.apply(net_params["actor"], mb["obs"])
        values = adv_critic.apply(net_params["critic"], mb["obs"])[..., 0]
        weight = (mb["index"] == member).astype(mean.dtype)
        return masked_ppo_loss(
            mean, net_params["log_std"], values, mb["action"], mb["log_prob"], mb["value"], mb["advantages"],
            mb["returns"], weight, clip_eps=config.clip_eps, vf_coef=config.vf_coef, ent_coef=config.ent_coef,
            normalize=config.normalize_advantages,
        )  # fmt: skip

    def ppo_epochs(loss_fn, optimizer, agent: Agent, data, key):
        grad_fn = jax.value_and_grad(loss_fn, has_aux=True)

        def sgd_step(carry, mb):
            net_params, opt_state = carry
            (loss, info), grads = grad_fn(net_params, mb)
            updates, opt_state = optimizer.update(grads, opt_state, net_params)
            return (optax.apply_updates(net_params, updates), opt_state), {**info, "loss": loss}

        def epoch(carry, epoch_key):
            permutation = jax.random.permutation(epoch_key, batch)
            shuffled = jax.tree.map(
                lambda x: jnp.reshape(x[permutation], (config.num_minibatches, minibatch, *x.shape[1:])), data
            )
            return jax.lax.scan(sgd_step, carry, shuffled)

        (net_params, opt_state), infos = jax.lax.scan(
            epoch, (agent.params, agent.opt_state), jax.random.split(key, config.num_epochs)
        )
        return Agent(net_params, opt_state), jax.tree.map(jnp.mean, infos)

    def update(runner: RunnerState, params) -> tuple[RunnerState, dict]:
        key, key_rollout, key_p, key_a = jax.random.split(runner.key, 4)
        collector, index, traj, episode = rollout(runner, params, key_rollout)
        stats = runner.collector.obs_stats
        obs, next_obs = observe(stats, traj.obs), observe(stats, traj.next_obs)
        net, adv = runner.protagonist.params, runner.adversaries.params
        reward = traj.reward * config.reward_scale
        acting = traj.extras["adversary_index"]  # (T, N)

        value = critic.apply(net["critic"], obs)[..., 0]
        next_value = critic.apply(net["critic"], next_obs)[..., 0]
        advantages, returns = losses.gae(
            reward, value, next_value, traj.terminated, traj.truncated, config.gamma, config.gae_lambda
        )

        def acting_value(x):  # the critic of the adversary that acted at each step, (T, N)
            all_values = jax.vmap(adv_critic.apply, in_axes=(0, None))(adv["critic"], x)[..., 0]  # (M, T, N)
            return jnp.take_along_axis(all_values, acting[None], axis=0)[0]

        adv_value, adv_next_value = acting_value(obs), acting_value(next_obs)
        adv_advantages, adv_returns = losses.gae(
            adversary_rewards(reward), adv_value, adv_next_value, traj.terminated, traj.truncated, config.gamma,
            config.gae_lambda,
        )  # fmt: skip

        flat = lambda x: jnp.reshape(x, (batch, *x.shape[2:]))  # noqa: E731
        protagonist_data = {
            "obs": flat(obs), "action": flat(traj.action), "log_prob": flat(traj.extras["log_prob"]),
            "value": flat(value), "advantages": flat(advantages), "returns": flat(returns),
        }  # fmt: skip
        adversary_data = {
            "obs": flat(obs), "action": flat(traj.adversary), "log_prob": flat(traj.extras["adversary_log_prob"]),
            "value": flat(adv_value), "advantages": flat(adv_advantages), "returns": flat(adv_returns),
            "index": flat(acting),
        }  # fmt: skip

        update_protagonist, update_adversaries = update_flags(runner.iteration, config)

        def train_protagonist(agent):
            return ppo_epochs(protagonist_loss, protagonist_opt, agent, protagonist_data, key_p)

        def train_adversaries(agents):
            def one(agent, member):
                loss_fn = lambda p, mb: adversary_loss(p, mb, member)  # noqa: E731
                return ppo_epochs(loss_fn, adversary_opt, agent, adversary_data, key_a)

            return jax.vmap(one)(agents, jnp.arange(M))

        def skip(agent, shapes):
            return agent, jax.tree.map(lambda s: jnp.full(s.shape, jnp.nan, s.dtype), shapes)

        p_shapes = jax.eval_shape(train_protagonist, runner.protagonist)[1]
        a_shapes = jax.eval_shape(train_adversaries, runner.adversaries)[1]
        protagonist, p_info = jax.lax.cond(
            update_protagonist, train_protagonist, lambda a: skip(a, p_shapes), runner.protagonist
        )
        adversaries, a_info = jax.lax.cond(
            update_adversaries, train_adversaries, lambda a: skip(a, a_shapes), runner.adversaries
        )
        env_steps = add_count(runner.env_steps, batch)
        dt = 1.0 / env.ctrl_freq
        metrics = {
            "env_steps": env_steps,
            **episode,
            **p_info,
            **{f"adversary_{name}": jnp.mean(value) for name, value in a_info.items()},
            "protagonist_updated": update_protagonist.astype(jnp.float32),
            "adversaries_updated": update_adversaries.astype(jnp.float32),
            "policy_std": jnp.mean(jnp.exp(protagonist.params["log_std"])),
            "adversary_std": jnp.mean(jnp.exp(adversaries.params["log_std"])),
            "adversary_abs_input": jnp.mean(jnp.abs(jnp.clip(traj.adversary, -1.0, 1.0))),
            "mean_reward": jnp.mean(traj.reward),
            # The constrained-MDP view of the rollout: share of steps in violation (cost 1) per simulated second.
            "violation_fraction": jnp.mean(traj.cost.astype(jnp.float32)),
            "simulated_seconds_per_iteration": jnp.asarray(batch * dt, jnp.float32),
        }
        new_runner = RunnerState(
            protagonist=protagonist,
            adversaries=adversaries,
            adversary_index=index,
            collector=collector,
            key=key,
            env_steps=env_steps,
            iteration=runner.iteration + 1,
        )
        return new_runner, metrics

    def policy_params(runner: RunnerState) -> dict:
        """The protagonist's policy, PPO's structure: ``{"actor", "log_std", "obs_stats"}``."""
        return {
            "actor": runner.protagonist.params["actor"],
            "log_std": runner.protagonist.params["log_std"],
            "obs_stats": runner.collector.obs_stats,
        }

    def make_policy(policy_params: Mapping):
        """The protagonist: ``policy(obs, key=None) -> a`` in [-1, 1] (``clip(mu)``, or a clipped sample)."""

        def policy(obs, key=None):
            mean = actor.apply(policy_params["actor"], observe(policy_params["obs_stats"], obs))
            if key is None:
                return jnp.clip(mean, -1.0, 1.0)
            noise = jax.random.normal(raw_key(key), mean.shape, mean.dtype)
            return jnp.clip(mean + jnp.exp(policy_params["log_std"]) * noise, -1.0, 1.0)

        return policy

    return Functions(init, update, rollout, policy_params, make_policy, train_env, adv_actor)


def make_adversarial_learner(name: str, config, env, num_adversaries: int) -> Learner:
    """A ``Learner`` for ``run_training`` (see the module docstring)."""
    fns = make_functions(config, env, num_adversaries, name)
    return Learner(
        name=name,
        config=config,
        init=fns.init,
        update=fns.update,
        num_iterations=config.num_iterations,
        steps_per_iteration=config.batch_size,
        policy_params=fns.policy_params,
        make_policy=fns.make_policy,
    )


def make_protagonist_learner(name: str, config, env) -> Learner:
    """The protagonist alone, for loading a saved policy on any env (with or without an adversary input): PPO's
    learner on the PPO fields of ``config`` (same networks, so the same ``policy_params`` and ``make_policy``),
    named ``name``. Not for training (it has no adversary)."""
    import dataclasses

    from scg_algorithms.ppo import Config as PPOConfig
    from scg_algorithms.ppo import make_learner as make_ppo_learner

    fields = {f.name for f in dataclasses.fields(PPOConfig)}
    ppo_config = PPOConfig(**{k: v for k, v in dataclasses.asdict(config).items() if k in fields})
    return make_ppo_learner(ppo_config, env)._replace(name=name, config=config)


def make_train(make_learner, config, env):
    """The whole run as one pure function ``train(key, params) -> (runner_state, metrics)`` (jit it, vmap it over
    keys for seeds), like ``scg_algorithms.ppo.make_train``."""
    learner = make_learner(config, env)

    def train(key, params):
        runner = learner.init(key, params)
        return jax.lax.scan(lambda state, _: learner.update(state, params), runner, None, learner.num_iterations)

    return train
