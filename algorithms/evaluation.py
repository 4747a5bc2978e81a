"""The one evaluation harness: every method, learned or not, is run and scored the same way.

``evaluate(env, params, controller, key, num_episodes)`` runs ``num_episodes`` copies of the env (one episode each,
no auto-reset) in closed loop with the controller and scores each copy's episode with ``scg_jax.metrics``:

- JAX controllers (``controller.is_jax``): reset, control and step of all copies are one ``jax.jit``-ed
  ``vmap`` of a ``lax.scan`` over the episode.
- Host controllers (CasADi/IPOPT): the copies step together through a jitted, vmapped ``env.step`` while the
  controller is called once per copy per step, on the host; a copy whose episode ended is no longer asked.

Copy ``i`` uses ``split(key, num_episodes)[i]``, itself split into the env's reset key and the controller's key, in
both paths, so a JAX and a host controller see the same initial states and disturbances for the same key.

Compute time per step (``compute_time_per_step_s``) is the controller's time per copy and control step:

- host controllers: the median wall time of one ``act`` call;
- JAX controllers: the controller alone is replayed, jitted and vmapped, over the observations recorded in the
  rollout (the same computation, since a controller is deterministic given its observations), and the wall time
  of that replay after compilation is divided by ``num_steps * num_episodes``: amortised over the batch, which is
  how a batched controller is used. ``compute_time_per_batch_step_s`` is the same time divided by ``num_steps``.
"""

from __future__ import annotations

import functools
import time
from collections.abc import Mapping
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from scg_algorithms.base import Reference
from scg_algorithms.progress import Task, as_progress, running
from scg_algorithms.safety_filters.base import check_system, filter_record, intervention_metrics, is_filtered
from scg_jax import metrics as metrics_lib
from scg_jax.caching import CompileCache
from scg_jax.tracing import batched_like

# The keys of the JSON the CLI writes, in the paper's order: summary name -> metrics.summarize name.
SUMMARY_KEYS = {
    "rmse": "rmse_mean",
    "rmse_std": "rmse_std",
    "worst_case_rmse_at_0.5": "worst_case_rmse_at_0.5",
    "failure_rate": "failure_rate",
    "constraint_violation_steps": "violation_steps_mean",
    "constraint_violation_steps_std": "violation_steps_std",
    "return": "return_mean",
    "return_std": "return_std",
    "length": "length_mean",
    "length_std": "length_std",
    "crash_rate": "crash_rate",
}

_INFO_KEYS = ("u_cmd", "u", "mse", "out_of_bounds", "nonfinite", "constraint_values")


class Evaluation(NamedTuple):
    """What ``evaluate`` returns; all numpy.

    Attributes:
        controller: the controller's name.
        summary: plain floats: ``rmse`` (mean over episodes of the per-episode RMSE of the ``mse_weight``-weighted
            tracking error, m with the default weights), ``rmse_std``, ``worst_case_rmse_at_0.5`` (CVaR at 0.5),
            ``failure_rate`` (episodes with any constraint violation or a crash), ``constraint_violation_steps``
            (mean steps in violation per episode) and its ``_std``, ``return``, ``return_std``, ``length``,
            ``length_std`` (control steps), ``crash_rate``, ``compute_time_per_step_s``,
            ``compute_time_per_batch_step_s`` (JAX controllers; ``None`` for host ones), ``num_episodes``; for a
            safety-filtered controller (``scg_algorithms.safety_filters.filtered``) also ``intervention_fraction``
            (steps where the filter changed the input by more than 1e-4 N / steps), ``mean_correction`` (mean
            change of the applied input, ``|u - clip(u_uncertified)|``, over steps, N), ``infeasible_fraction``
            (steps whose filter problem failed) and what was applied on them, ``infeasible_<kind>_fraction``
            (``scg_algorithms.safety_filters.base.intervention_metrics``).
        per_episode: ``scg_jax.metrics.episode_metrics`` of each episode, (num_episodes,) arrays.
        trajectory: ``x`` (T + 1, N, nx) states from reset to the last step, ``x_ref`` (T + 1, N, nx), ``obs``
            (T, N, obs), ``u_cmd`` and ``u`` (T, N, nu) commanded and applied inputs (N), ``reward``, ``cost``,
            ``terminated``, ``truncated``, ``mse``, ``out_of_bounds``, ``nonfinite`` (T, N) and
            ``constraint_values`` (T, N, rows); a filtered controller adds ``filter_correction`` (T, N, nu),
            ``filter_feasible``, ``filter_slack`` and ``filter_applied`` (T, N). Rows after a copy's episode ended
            are the plant running on (JAX controllers) or repeat the last input (host controllers); the metrics
            ignore them.
        timing: ``run_s`` (wall time of the closed loop, compile excluded for JAX controllers), ``compile_s``.
    """

    controller: str
    summary: dict
    per_episode: dict
    trajectory: dict
    timing: dict


@functools.partial(jax.jit, static_argnums=1)  # one program per count, not one per operation and count
def _copy_keys(key, num_episodes: int):
    keys = jax.random.split(key, num_episodes)
    both = jax.vmap(jax.random.split)(keys)
    return both[:, 0], both[:, 1]


def _params_axis(batched_params: bool):
    return 0 if batched_params else None


def _check(env, params, controller, num_episodes) -> int:
    for name in ("name", "is_jax", "reset", "act"):
        if not hasattr(controller, name):
            raise TypeError(f"controller: missing {name!r}; see scg_algorithms.base.Controller")
    if isinstance(num_episodes, bool) or int(num_episodes) != num_episodes or num_episodes < 1:
        raise ValueError(f"num_episodes: must be a positive integer, got {num_episodes!r}")
    return int(num_episodes)


# --------------------------------------------------------------------------------------------- JAX path
def _closed_loop_fn(env, controller):
    """One copy's episode: ``(env_key, ctrl_key, params) -> records`` (leaves (T, ...)) and extras."""

    def one_copy(env_key, ctrl_key, params):
        obs, state = env.reset(env_key, params)
        reference = Reference(*env.reference(params))
        ctrl_state = controller.reset(ctrl_key, reference)

        def body(carry, _):
            obs, state, ctrl_state = carry
            u, ctrl_state = controller.act(ctrl_state, obs, state.step, reference)
            out = env.step(state, env.input_to_action(u, params), params)
            record = {
                "obs": obs,
                "x": state.x,
                "reward": out.reward,
                "cost": out.cost,
                "terminated": out.terminated,
                "truncated": out.truncated,
                **{name: out.info[name] for name in _INFO_KEYS},
            }
            if is_filtered(controller):  # a safety filter's report of this step, for the intervention metrics
                record.update(filter_record(ctrl_state))
            return (out.obs, out.state, ctrl_state), record

        carry = batched_like((obs, state, ctrl_state), env_key)  # vmap traces the body once (scg_jax.tracing)
        (_, final_state, _), records = jax.lax.scan(body, carry, None, length=env.num_steps)
        return records, final_state.x, reference.x_ref

    return one_copy


def _replay_fn(env, controller):
    """The controller alone over recorded observations of one copy (for timing)."""

    def replay(ctrl_key, obs_seq, params):
        reference = Reference(*env.reference(params))
        ctrl_state = controller.reset(ctrl_key, reference)

        def body(ctrl_state, inputs):
            obs, step = inputs
            u, ctrl_state = controller.act(ctrl_state, obs, step, reference)
            return ctrl_state, u

        steps = jnp.arange(obs_seq.shape[0], dtype=jnp.int32)
        _, u = jax.lax.scan(body, batched_like(ctrl_state, ctrl_key), (obs_seq, steps))
        return u

    return replay


# Compiled closed loops and replays, so evaluating the same env and controller again (new key, new params of the
# same shapes) does not compile again; an entry goes with its env or controller (scg_jax.caching's policy).
_COMPILED = CompileCache(maxsize=32)


def _compiled(kind: str, env, controller, axis, args) -> tuple[Any, float]:
    """``(executable, compile seconds)``; 0 s when it was compiled before for the same shapes."""
    # The layout is part of the executable: a sharded evaluation compiles apart from the single-device one.
    signature = jax.tree.map(lambda a: (jnp.shape(a), jnp.result_type(a), str(getattr(a, "sharding", None))), args)
    compile_s = 0.0

    def build():
        nonlocal compile_s
        start = time.perf_counter()
        loop_or_replay = _closed_loop_fn if kind == "loop" else _replay_fn
        executable = jax.jit(jax.vmap(loop_or_replay(env, controller), in_axes=(0, 0, axis))).lower(*args).compile()
        compile_s = time.perf_counter() - start
        return executable

    key = (kind, axis, str(jax.tree.structure(args)), str(signature))
    return _COMPILED.get(key, build, owners=(env, controller)), compile_s


def _evaluate_jax(env, params, controller, key, num_episodes, batched_params, measure_time, mesh=None):
    env_keys, ctrl_keys = _copy_keys(key, num_episodes)
    axis = _params_axis(batched_params)
    if mesh is not None:  # copies laid out over the mesh's devices (and hosts); jit partitions the closed loop
        from scg_jax import sharding

        sharding.check_divisible(num_episodes, mesh, "num_episodes")
        env_keys, ctrl_keys = sharding.shard_batch((env_keys, ctrl_keys), mesh)
        params = sharding.shard_batch(params, mesh) if batched_params else sharding.replicate(params, mesh)
    compiled, compile_s = _compiled("loop", env, controller, axis, (env_keys, ctrl_keys, params))
    start = time.perf_counter()
    records, x_final, x_ref = jax.block_until_ready(compiled(env_keys, ctrl_keys, params))
    run_s = time.perf_counter() - start
    if mesh is not None:  # every process gets every copy's records (a collective over the processes)
        obs_on_devices = records["obs"]
        records, x_final, x_ref = sharding.to_host((records, x_final, x_ref))

    timing = {"compile_s": compile_s, "run_s": run_s}
    per_step = per_batch_step = None
    if measure_time:
        obs = records["obs"] if mesh is None else obs_on_devices
        replay_compiled, _ = _compiled("replay", env, controller, axis, (ctrl_keys, obs, params))
        jax.block_until_ready(replay_compiled(ctrl_keys, obs, params))
        start = time.perf_counter()
        jax.block_until_ready(replay_compiled(ctrl_keys, obs, params))
        replay_s = time.perf_counter() - start
        per_batch_step = replay_s / env.num_steps
        per_step = per_batch_step / num_episodes
        timing["controller_replay_s"] = replay_s

    # vmap puts the copy axis first; the metrics and plots are time-major like scg_jax.Trajectory.
    trajectory = {name: np.swapaxes(np.asarray(value), 0, 1) for name, value in records.items()}
    x = np.concatenate([trajectory["x"], np.asarray(x_final)[None]], axis=0)
    trajectory["x"] = x
    trajectory["x_ref"] = np.swapaxes(np.asarray(x_ref), 0, 1)
    return trajectory, timing, per_step, per_batch_step


# --------------------------------------------------------------------------------------------- host path
_HOST_FUNCTIONS = CompileCache(maxsize=16)


def _host_functions(env, batched_params: bool):
    """Jitted, vmapped ``reset``, ``step`` (from the physical input) and ``reference`` of ``env``, made once."""
    return _HOST_FUNCTIONS.get(batched_params, lambda: _make_host_functions(env, batched_params), owners=(env,))


def _make_host_functions(env, batched_params: bool):
    axis = _params_axis(batched_params)

    def step_one(state, u, params):
        out = env.step(state, env.input_to_action(u, params), params)
        info = {name: out.info[name] for name in _INFO_KEYS}
        return out.obs, out.state, out.reward, out.cost, out.terminated, out.truncated, info

    return (
        jax.jit(jax.vmap(env.reset, in_axes=(0, axis))),
        jax.jit(jax.vmap(step_one, in_axes=(0, 0, axis))),
        jax.jit(jax.vmap(env.reference, in_axes=(axis,)) if batched_params else env.reference),
    )


def _evaluate_host(env, params, controller, key, num_episodes, batched_params, progress):
    env_keys, ctrl_keys = _copy_keys(key, num_episodes)
    reset, step, reference_fn = _host_functions(env, batched_params)

    start = time.perf_counter()
    obs, state = reset(env_keys, params)
    if batched_params:
        x_ref_all, u_ref_all = (np.asarray(a, dtype=np.float64) for a in reference_fn(params))
    else:
        x_ref_one, u_ref_one = (np.asarray(a, dtype=np.float64) for a in reference_fn(params))
        x_ref_all = np.broadcast_to(x_ref_one, (num_episodes, *x_ref_one.shape))
        u_ref_all = np.broadcast_to(u_ref_one, (num_episodes, *u_ref_one.shape))
    references = [Reference(x_ref_all[i], u_ref_all[i]) for i in range(num_episodes)]
    ctrl_keys_np = list(ctrl_keys)
    ctrl_states = [controller.reset(ctrl_keys_np[i], references[i]) for i in range(num_episodes)]

    num_steps = env.num_steps
    records: dict[str, list] = {name: [] for name in ("obs", "x", "reward", "cost", "terminated", "truncated")}
    records.update({name: [] for name in _INFO_KEYS})
    with_filter = is_filtered(controller)
    if with_filter:
        filter_last = [filter_record(state_i) for state_i in ctrl_states]
    done = np.zeros(num_episodes, dtype=bool)
    u_last = np.zeros((num_episodes, env.nu))
    act_times: list[float] = []

    with running(progress, Task(f"evaluating {controller.name} on {num_episodes} episodes", num_steps, 0, "step")):
        for k in range(num_steps):
            obs_np = np.asarray(obs, dtype=np.float64)
            x_np = np.asarray(state.x)
            for i in range(num_episodes):
                if done[i]:
                    continue
                tick = time.perf_counter()
                u_i, ctrl_states[i] = controller.act(ctrl_states[i], obs_np[i], k, references[i])
                act_times.append(time.perf_counter() - tick)
                u_i = np.asarray(u_i, dtype=np.float64).reshape(env.nu)
                if not np.all(np.isfinite(u_i)):
                    raise FloatingPointError(f"controller {controller.name!r} returned a non-finite input {u_i}")
                u_last[i] = u_i
                if with_filter:
                    filter_last[i] = filter_record(ctrl_states[i])
            if with_filter:
                for name in filter_last[0]:
                    records.setdefault(name, []).append(np.stack([np.asarray(f[name]) for f in filter_last]))
            obs_next, state, reward, cost, terminated, truncated, info = step(state, jnp.asarray(u_last), params)
            for name, value in (
                ("obs", obs_np),
                ("x", x_np),
                ("reward", reward),
                ("cost", cost),
                ("terminated", terminated),
                ("truncated", truncated),
            ):
                records[name].append(np.asarray(value))
            for name in _INFO_KEYS:
                records[name].append(np.asarray(info[name]))
            obs = obs_next
            done |= np.asarray(terminated) | np.asarray(truncated)
            progress.update(k + 1, {"episodes_done": int(done.sum())})
            if done.all():
                break
    run_s = time.perf_counter() - start

    trajectory = {name: np.stack(values) for name, values in records.items()}
    trajectory["x"] = np.concatenate([trajectory["x"], np.asarray(state.x)[None]], axis=0)
    trajectory["x_ref"] = np.swapaxes(x_ref_all, 0, 1)
    per_step = float(np.median(act_times)) if act_times else None
    timing = {"compile_s": 0.0, "run_s": run_s, "controller_calls": len(act_times)}
    if act_times:
        timing["controller_mean_s"] = float(np.mean(act_times))
        timing["controller_p95_s"] = float(np.percentile(act_times, 95))
        timing["controller_max_s"] = float(np.max(act_times))
    return trajectory, timing, per_step, None


# --------------------------------------------------------------------------------------------- public
def evaluate(
    env,
    params,
    controller,
    key,
    num_episodes: int,
    *,
    batched_params: bool = False,
    measure_time: bool = True,
    progress=None,
    mesh=None,
) -> Evaluation:
    """Run ``num_episodes`` episodes of ``env`` under ``controller`` and score them.

    Args:
        env: an ``scg_jax.Env``. params: the true plant's ``EnvParams`` (what is simulated; the controller was built
            from its own prior). controller: an ``scg_algorithms.base.Controller``. key: a JAX PRNG key.
        num_episodes: number of episodes, run as parallel copies (one episode per copy).
        batched_params: ``params`` has a leading axis of size ``num_episodes`` (a sweep).
        measure_time: time JAX controllers alone (one extra replay); host controllers are always timed.
        progress: a ``scg_algorithms.progress.Progress``: the task ``"evaluating NAME on N episodes"``, counting
            control steps for a host controller (whose loop runs in Python), uncounted for a JAX one (compiling and
            one jitted call). None: silent.
        mesh: ``scg_jax.sharding.make_mesh(devices)``: JAX controllers' copies are laid out over its devices and
            processes (``num_episodes`` must divide evenly; every process gets all copies' results); host
            controllers ignore it. ``None``: one device.

    Returns:
        ``Evaluation`` (see its docstring for the definitions).
    """
    num_episodes = _check(env, params, controller, num_episodes)
    progress = as_progress(progress)
    if is_filtered(controller):
        check_system(controller.safety_filter, env)
    if controller.is_jax:
        with running(progress, Task(f"evaluating {controller.name} on {num_episodes} episodes")):
            trajectory, timing, per_step, per_batch_step = _evaluate_jax(
                env, params, controller, key, num_episodes, batched_params, measure_time, mesh
            )
    else:
        trajectory, timing, per_step, per_batch_step = _evaluate_host(
            env, params, controller, key, num_episodes, batched_params, progress
        )
    return _score(controller.name, trajectory, timing, per_step, per_batch_step, num_episodes)


def _score(name, trajectory, timing, per_step, per_batch_step, num_episodes) -> Evaluation:
    per_episode = metrics_lib.episode_metrics(
        trajectory["reward"],
        trajectory["terminated"],
        trajectory["truncated"],
        trajectory["mse"],
        trajectory["out_of_bounds"],
        trajectory["nonfinite"],
        trajectory["cost"],
    )
    raw = metrics_lib.summarize(per_episode)
    summary: dict[str, Any] = {name: raw[source] for name, source in SUMMARY_KEYS.items()}
    summary["compute_time_per_step_s"] = per_step
    summary["compute_time_per_batch_step_s"] = per_batch_step
    summary["num_episodes"] = num_episodes
    if "filter_correction" in trajectory:  # a filtered controller: how often and how much the filter intervened
        summary.update(
            intervention_metrics(
                trajectory["filter_correction"],
                trajectory["filter_feasible"],
                per_episode["length"],
                trajectory.get("filter_applied"),
            )
        )
    return Evaluation(name, summary, per_episode, trajectory, timing)


def make_evaluator(env, build_controller, num_episodes: int, *, batched_params: bool = False, mesh=None):
    """An evaluation whose controller is rebuilt from traced values, for evaluating a learner as it trains.

    ``evaluate`` compiles once per controller object; a learner's policy changes every iteration, so here the
    controller is built inside the compiled function from ``controller_params`` (e.g. network weights), and a new
    policy is evaluated without compiling again.

    Args:
        env: the environment. build_controller: ``build_controller(controller_params) -> JaxController``, traced.
        num_episodes: copies, one episode each. batched_params: ``params`` has a leading copy axis.
        mesh: ``scg_jax.sharding.make_mesh(devices)``: the copies are laid out over its devices (and processes:
            then every process calls ``evaluate_fn`` with the same arguments, a collective, and gets every copy's
            results), ``controller_params`` replicated; ``num_episodes`` must divide evenly. ``None``: one device.

    Returns:
        ``evaluate_fn(controller_params, key, params) -> Evaluation`` (no compute-time measurement), with the same
        keys per copy as ``evaluate``.
    """
    num_episodes = int(num_episodes)
    axis = _params_axis(batched_params)
    if mesh is not None:
        from scg_jax import sharding

        sharding.check_divisible(num_episodes, mesh, "num_episodes")

    def run(controller_params, env_keys, ctrl_keys, params):
        controller = build_controller(controller_params)
        loop = jax.vmap(_closed_loop_fn(env, controller), in_axes=(0, 0, axis))
        return loop(env_keys, ctrl_keys, params)

    run_jit = jax.jit(run)

    def evaluate_fn(controller_params, key, params) -> Evaluation:
        env_keys, ctrl_keys = _copy_keys(key, num_episodes)
        if mesh is not None:  # as in evaluate: the copies split over the devices, the rest held whole on each
            env_keys, ctrl_keys = sharding.shard_batch((env_keys, ctrl_keys), mesh)
            params = sharding.shard_batch(params, mesh) if batched_params else sharding.replicate(params, mesh)
            controller_params = sharding.replicate(controller_params, mesh)
        start = time.perf_counter()
        records, x_final, x_ref = jax.block_until_ready(run_jit(controller_params, env_keys, ctrl_keys, params))
        timing = {"run_s": time.perf_counter() - start}
        if mesh is not None:  # every process gets every copy's records (a collective over the processes)
            records, x_final, x_ref = sharding.to_host((records, x_final, x_ref))
        trajectory = {name: np.swapaxes(np.asarray(value), 0, 1) for name, value in records.items()}
        trajectory["x"] = np.concatenate([trajectory["x"], np.asarray(x_final)[None]], axis=0)
        trajectory["x_ref"] = np.swapaxes(np.asarray(x_ref), 0, 1)
        name = build_controller.__name__ if hasattr(build_controller, "__name__") else "controller"
        return _score(name, trajectory, timing, None, None, num_episodes)

    return evaluate_fn


def evaluation_record(evaluation: Evaluation, extra: Mapping | None = None) -> dict:
    """The JSON record of an evaluation: the summary keys at the top level (``rmse``, ``rmse_std``,
    ``worst_case_rmse_at_0.5``, ``failure_rate``, ``constraint_violation_steps``, ``return``, ``length``, ...),
    then ``controller``, ``timing``, ``per_episode`` lists and ``extra``."""
    record = dict(evaluation.summary)
    record["controller"] = evaluation.controller
    record["timing"] = dict(evaluation.timing)
    record["per_episode"] = {name: np.asarray(v).tolist() for name, v in evaluation.per_episode.items()}
    if extra:
        record.update(extra)
    return record
