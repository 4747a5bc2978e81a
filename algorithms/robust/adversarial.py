"""The adversarial game of RARL and RAP: a protagonist and ``M`` adversaries, every one a PPO agent
(``scg_algorithms.ppo.agent``), in one jitted ``update``. RARL (``scg_algorithms.robust.rarl``) and RAP
(``scg_algorithms.robust.rap``) are this one game with other defaults: one adversary and alternating updates, or a
population updated jointly.

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

1. ``rollout_length`` steps of the N copies (the learners' collector with the assignment as its per-copy labels):
   the protagonist samples its action, the copy's adversary its input, the env steps and auto-resets, the copies
   whose episode ended draw a new adversary;
2. GAE for the protagonist on ``r`` with its critic, and for the adversaries on ``-r`` with the critic of the
   adversary that acted at each step (bootstrap at a time limit, none at a termination);
3. PPO's epochs (``ppo.agent.ppo_epochs``) for the protagonist and, vmapped over the population, for each adversary
   on the steps it acted in (PPO's loss with 0/1 per-sample weights), as the schedule says: ``alternating``
   (``protagonist_iterations`` iterations updating only the protagonist, then ``adversary_iterations`` updating
   only the adversaries, each on fresh rollouts; RARL's loop) or ``joint`` (both from the same rollout every
   iteration; RAP's loop).

The saved policy (``policy_params``) is the protagonist's, with the same structure as PPO's, so the trained
protagonist is evaluated as a controller by the same harness (``scg_algorithms.rl.policy.load_policy``).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

from scg_algorithms.base import option, parse_options
from scg_algorithms.ppo import agent as agent_lib
from scg_algorithms.ppo import losses
from scg_algorithms.ppo import make_learner as make_ppo_learner
from scg_algorithms.ppo.agent import Agent, Networks
from scg_algorithms.ppo.config import Config as PPOConfig
from scg_algorithms.rl import learner as learner_lib
from scg_algorithms.rl.collector import ActOutput, Collected, CollectorState, CopyLabels, collect, init_collector
from scg_algorithms.rl.config import hidden_sizes_option
from scg_algorithms.rl.counter import Count, add_count, zero_count
from scg_algorithms.rl.envs import TrainEnv, make_train_env
from scg_algorithms.rl.normalization import RunningStats
from scg_algorithms.rl.training import Learner, raw_key

__all__ = [
    "Agent",
    "Config",
    "Game",
    "RunnerState",
    "adversary_dim",
    "adversary_rewards",
    "assign_adversaries",
    "init",
    "learner_functions",
    "make_game",
    "rollout",
    "update",
    "update_counts",
    "update_flags",
]

SCHEDULES = ("alternating", "joint")
ADVERSARY_CHANNELS = ("action", "dynamics")


# --------------------------------------------------------------------------------------------- options
@dataclasses.dataclass(frozen=True)
class Config(PPOConfig):
    """The game's options: PPO's (the protagonist's, and the adversaries' unless named here) and the adversaries'.
    The defaults are RAP's; RARL's ``Config`` differs only in its defaults (``scg_algorithms.base.with_defaults``)."""

    num_adversaries: int = option(
        2, "adversaries in the population (each copy draws one per episode)", check="positive"
    )
    schedule: str = option(
        "joint",
        "alternating: protagonist_iterations iterations updating the protagonist, then adversary_iterations "
        "updating the adversaries (each on fresh rollouts); joint: both from every rollout",
        choices=SCHEDULES,
    )
    protagonist_iterations: int = option(
        1, "alternating schedule: consecutive iterations updating only the protagonist", check="non_negative"
    )
    adversary_iterations: int = option(
        1, "alternating schedule: consecutive iterations updating only the adversaries", check="non_negative"
    )
    adversary_learning_rate: float = option(
        1e-3, "Adam step size of the adversaries (decayed like the protagonist's with lr_decay)", check="positive"
    )
    adversary_init_log_std: float = option(
        -1.0, "initial log standard deviation of the adversaries' Gaussian policies (in [-1, 1] units)"
    )
    adversary_hidden: tuple = hidden_sizes_option(
        (64, 64), "hidden layer sizes of each adversary's policy mean and value networks"
    )

    def _check(self, path: str) -> None:
        super()._check(path)
        if self.schedule == "alternating" and self.protagonist_iterations + self.adversary_iterations < 1:
            raise ValueError(
                f"{path}.protagonist_iterations: with schedule 'alternating', protagonist_iterations + "
                f"adversary_iterations must be at least 1, got {self.protagonist_iterations} and "
                f"{self.adversary_iterations}"
            )


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
    if config.schedule == "joint":
        return config.num_iterations, config.num_iterations
    cycle = config.protagonist_iterations + config.adversary_iterations
    protagonist = sum((i % cycle) < config.protagonist_iterations for i in range(config.num_iterations))
    return protagonist, config.num_iterations - protagonist


# --------------------------------------------------------------------------------------------- state
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


class Game(NamedTuple):
    """The static pieces of a game (``make_game``): its checked ``config``, the N copies, both kinds of agent's
    networks and optimisers (the adversaries' decay over the iterations that update them), the control period
    ``dt`` (s)."""

    config: Config
    train_env: TrainEnv
    protagonist: Networks
    adversary: Networks
    protagonist_optimizer: Any
    adversary_optimizer: Any
    dt: float


def make_game(config: Config, env, algo: str) -> Game:
    """The game of ``config`` (checked) on ``env``.

    Raises:
        ValueError: ``env.adversary`` missing or on an unsupported channel (``adversary_dim``).
    """
    adv_dim = adversary_dim(env, algo)
    train_env = make_train_env(env, config.num_envs, config.action_scale)
    protagonist = agent_lib.make_networks(
        config.actor_hidden, config.critic_hidden, config.activation, train_env.action_size
    )
    adversary = agent_lib.make_networks(config.adversary_hidden, config.adversary_hidden, config.activation, adv_dim)
    n_protagonist, n_adversary = update_counts(config)
    return Game(
        config=config,
        train_env=train_env,
        protagonist=protagonist,
        adversary=adversary,
        protagonist_optimizer=agent_lib.make_optimizer(config, config.learning_rate, n_protagonist),
        adversary_optimizer=agent_lib.make_optimizer(config, config.adversary_learning_rate, n_adversary),
        dt=1.0 / env.ctrl_freq,
    )


# --------------------------------------------------------------------------------------------- one iteration
def init(game: Game, key, params) -> RunnerState:
    """Fresh agents, a uniform first assignment and reset copies, all from ``key``."""
    config, obs_size = game.config, game.train_env.obs_size
    key = raw_key(key)
    key, key_actor, key_critic, key_adv, key_env, key_index = jax.random.split(key, 6)
    protagonist = agent_lib.init_params(game.protagonist, key_actor, key_critic, obs_size, config.init_log_std)

    def one_adversary(k):
        k_actor, k_critic = jax.random.split(k)
        return agent_lib.init_params(game.adversary, k_actor, k_critic, obs_size, config.adversary_init_log_std)

    adversaries = jax.vmap(one_adversary)(jax.random.split(key_adv, config.num_adversaries))
    index = jax.random.randint(key_index, (config.num_envs,), 0, config.num_adversaries, dtype=jnp.int32)
    return RunnerState(
        protagonist=Agent(protagonist, game.protagonist_optimizer.init(protagonist)),
        adversaries=Agent(adversaries, jax.vmap(game.adversary_optimizer.init)(adversaries)),
        adversary_index=index,
        collector=init_collector(game.train_env, key_env, params),
        key=key,
        env_steps=zero_count(),
        iteration=jnp.zeros((), jnp.int32),
    )


def rollout(game: Game, runner: RunnerState, params, key, info_keys: tuple[str, ...] = ()) -> Collected:
    """The rollout of one iteration (the collector with the adversary assignment as its labels): transitions with
    raw ``obs`` and ``next_obs``, extras ``log_prob``, ``adversary_log_prob`` and ``label`` (the adversary that
    acted), and the assignment after the last step as ``labels``."""
    config, protagonist, adversary = game.config, game.protagonist, game.adversary
    net, adv = runner.protagonist.params, runner.adversaries.params
    stats = runner.collector.obs_stats

    def act(raw_obs, step_key, index):
        key_p, key_a = jax.random.split(step_key)
        obs = agent_lib.observe(config, stats, raw_obs)
        mean = protagonist.mean(net, obs)
        action = agent_lib.sample_action(key_p, mean, net["log_std"])
        # Every adversary's mean on every copy, then each copy's own: M is small, a gather is cheaper than a
        # per-copy parameter gather of the whole network.
        all_means = jax.vmap(adversary.mean, in_axes=(0, None))(adv, obs)  # (M, N, d)
        adv_mean = jnp.take_along_axis(all_means, index[None, :, None], axis=0)[0]
        adv_log_std = adv["log_std"][index]  # (N, d)
        adv_action = agent_lib.sample_action(key_a, adv_mean, adv_log_std)
        extras = {
            "log_prob": losses.gaussian_log_prob(mean, net["log_std"], action),
            "adversary_log_prob": losses.gaussian_log_prob(adv_mean, adv_log_std, adv_action),
        }
        return ActOutput(action, extras, adv_action)

    def redraw(redraw_key, index, done):
        return assign_adversaries(redraw_key, index, done, config.num_adversaries)

    return collect(
        game.train_env, params, runner.collector, act, key, config.rollout_length,
        update_normalizer=config.normalize_observations, info_keys=info_keys,
        labels=CopyLabels(runner.adversary_index, redraw),
    )  # fmt: skip


def _batches(game: Game, runner: RunnerState, traj) -> tuple[dict, dict]:
    """The protagonist's and the adversaries' GAE batches of a rollout (``agent.gae_batch``); the adversaries'
    carries ``acting``, the adversary of each step."""
    config = game.config
    stats = runner.collector.obs_stats
    obs, next_obs = agent_lib.observe(config, stats, traj.obs), agent_lib.observe(config, stats, traj.next_obs)
    net, adv = runner.protagonist.params, runner.adversaries.params
    reward = traj.reward * config.reward_scale
    acting = traj.extras["label"]  # (T, N)
    protagonist_data = agent_lib.gae_batch(
        config, reward, game.protagonist.value(net, obs), game.protagonist.value(net, next_obs), traj.terminated,
        traj.truncated, obs=obs, action=traj.action, log_prob=traj.extras["log_prob"],
    )  # fmt: skip

    def acting_value(x):  # the critic of the adversary that acted at each step, (T, N)
        all_values = jax.vmap(game.adversary.value, in_axes=(0, None))(adv, x)  # (M, T, N)
        return jnp.take_along_axis(all_values, acting[None], axis=0)[0]

    adversary_data = agent_lib.gae_batch(
        config, adversary_rewards(reward), acting_value(obs), acting_value(next_obs), traj.terminated,
        traj.truncated, obs=obs, action=traj.adversary, log_prob=traj.extras["adversary_log_prob"], acting=acting,
    )  # fmt: skip
    return protagonist_data, adversary_data


def _protagonist_loss(game: Game, params, aux, mb):
    networks = game.protagonist
    return agent_lib.minibatch_loss(
        game.config, networks.mean(params, mb["obs"]), params["log_std"], networks.value(params, mb["obs"]), mb
    )


def _adversary_loss(game: Game, member, params, aux, mb):
    """PPO's loss of adversary ``member`` on the steps it acted in (weight 1 there, 0 elsewhere)."""
    networks = game.adversary
    mean = networks.mean(params, mb["obs"])
    weight = (mb["acting"] == member).astype(mean.dtype)
    values = networks.value(params, mb["obs"])
    return agent_lib.minibatch_loss(game.config, mean, params["log_std"], values, mb, weight=weight)


def _train_if(flag, train: Callable, agent: Agent):
    """``train(agent) -> (agent, info)`` where ``flag`` holds; elsewhere the agent unchanged and NaN info."""
    shapes = jax.eval_shape(train, agent)[1]

    def skip(agent):
        return agent, jax.tree.map(lambda s: jnp.full(s.shape, jnp.nan, s.dtype), shapes)

    return jax.lax.cond(flag, train, skip, agent)


def update(game: Game, runner: RunnerState, params, iteration) -> tuple[RunnerState, dict]:
    """One iteration (see the module docstring); ``iteration`` (0-based, int32) is the schedule's clock."""
    config = game.config
    key, key_rollout, key_p, key_a = jax.random.split(runner.key, 4)
    collected = rollout(game, runner, params, key_rollout)
    traj = collected.transitions
    protagonist_data, adversary_data = _batches(game, runner, traj)
    update_protagonist, update_adversaries = update_flags(iteration, config)

    def train_protagonist(agent):
        loss = lambda p, aux, mb: _protagonist_loss(game, p, aux, mb)  # noqa: E731
        agent, _, info = agent_lib.ppo_epochs(loss, game.protagonist_optimizer, agent, protagonist_data, key_p, config)
        return agent, info

    def train_adversaries(agents):
        def one(agent, member):
            loss = lambda p, aux, mb: _adversary_loss(game, member, p, aux, mb)  # noqa: E731
            agent, _, info = agent_lib.ppo_epochs(loss, game.adversary_optimizer, agent, adversary_data, key_a, config)
            return agent, info

        return jax.vmap(one)(agents, jnp.arange(config.num_adversaries))

    protagonist, p_info = _train_if(update_protagonist, train_protagonist, runner.protagonist)
    adversaries, a_info = _train_if(update_adversaries, train_adversaries, runner.adversaries)
    env_steps = add_count(runner.env_steps, config.batch_size)
    metrics = {
        "env_steps": env_steps,
        **collected.episode,
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
        "simulated_seconds_per_iteration": jnp.asarray(config.batch_size * game.dt, jnp.float32),
    }
    new_runner = RunnerState(
        protagonist=protagonist,
        adversaries=adversaries,
        adversary_index=collected.labels,
        collector=collected.state,
        key=key,
        env_steps=env_steps,
        iteration=runner.iteration + 1,
    )
    return new_runner, metrics


# --------------------------------------------------------------------------------------------- learners
def _learner(name: str, config_cls, config, env) -> tuple[Learner, Callable]:
    """The game named ``name`` as a ``Learner`` and its ``update_at`` (``rl.learner.make_train``)."""
    config = parse_options(config_cls, config, f"training.{name}")
    game = make_game(config, env, name)

    def policy_mean(saved, obs, raw_obs):
        return game.protagonist.mean(saved, obs)

    learner = Learner(
        name=name,
        config=config,
        init=lambda key, params: init(game, key, params),
        update=lambda runner, params: update(game, runner, params, runner.iteration),
        num_iterations=config.num_iterations,
        steps_per_iteration=config.batch_size,
        policy_params=lambda runner: agent_lib.saved_policy(runner.protagonist.params, runner.collector.obs_stats),
        make_policy=lambda policy_params: agent_lib.make_policy(config, policy_mean, policy_params),
    )
    return learner, lambda runner, params, i: update(game, runner, params, i)


def learner_functions(name: str, config_cls) -> tuple[Callable, Callable, Callable]:
    """``make_learner``, ``make_policy_learner`` and ``make_train`` of the game named ``name`` whose options are
    ``config_cls`` (``Config`` or one ``with_defaults`` of it), each ``f(config, env)``:

    - ``make_learner(config, env) -> Learner`` for ``run_training``; ``config`` a ``config_cls``, a mapping (the
      ``training.<name>`` section) or ``None`` for the defaults; ``env`` made with an adversary input on the
      ``action`` or ``dynamics`` channel. Raises ValueError naming a bad option (``training.<name>.<field>``) or
      ``env.adversary``.
    - ``make_policy_learner(config, env) -> Learner``: the protagonist alone, for loading a saved policy on any env
      (with or without an adversary input): PPO's learner on the PPO fields of ``config`` (same networks, so the
      same ``policy_params`` and ``make_policy``), named ``name``. Not for training (it has no adversary).
    - ``make_train(config, env)``: the whole run as one pure function ``train(key, params) -> (runner_state,
      metrics)`` (``scg_algorithms.rl.learner.make_train``; jit it, vmap it over keys for seeds).
    """

    def make_learner(config, env) -> Learner:
        return _learner(name, config_cls, config, env)[0]

    def make_policy_learner(config, env) -> Learner:
        config = parse_options(config_cls, config, f"training.{name}")
        fields = {field.name for field in dataclasses.fields(PPOConfig)}
        ppo_config = PPOConfig(**{key: getattr(config, key) for key in fields})
        return make_ppo_learner(ppo_config, env)._replace(name=name, config=config)

    def make_train(config, env) -> Callable:
        return learner_lib.make_train(*_learner(name, config_cls, config, env))

    return make_learner, make_policy_learner, make_train
