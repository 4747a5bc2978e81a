"""Gymnasium adapters: ``ScgGymEnv`` (one copy), ``ScgVectorEnv`` (N copies in one jitted step), safety wrappers.

After ``import scg_jax`` (with Gymnasium installed) the ids ``scg_jax/CartPole-v0``, ``scg_jax/Quadrotor1D-v0``,
``scg_jax/Quadrotor2D-v0`` and ``scg_jax/Quadrotor3D-v0`` are registered::

    env = gymnasium.make("scg_jax/Quadrotor2D-v0", task="tracking", trajectory={"shape": "figure8"})
    obs, info = env.reset(seed=0)            # info: symbolic_model, x_reference, u_reference, constraints, ...
    obs, reward, terminated, truncated, info = env.step(env.action_space.sample())

    envs = gymnasium.make_vec("scg_jax/CartPole-v0", num_envs=4096)   # ScgVectorEnv: one vmapped step
    envs = SafetyGymnasiumWrapper(env)       # step -> (obs, reward, cost, terminated, truncated, info)

Every id takes the options of ``scg_jax.make`` as keywords, or ``config=`` (a path, YAML text, mapping or
``Config``) with optional ``overrides=["env.key=value", ...]``; keywords given next to a config override it.

Conventions:

- **Actions.** Without a config the adapters default to ``action_mode="normalized"``: ``Box(-1, 1, (nu,))``
  (cart-pole ``F = 10 a`` N, quadrotors ``T = hover (1 + 0.1 a)``). With ``action_mode="physical"`` (or a config
  that says so, as the shipped ones do) the space is ``Box(u_low, u_high)``, the actuator limits of the nominal
  plant. Actions are not clipped here: the plant saturates the input (``info["u_cmd"]`` vs ``info["u"]``). An
  action of the wrong shape raises ``ValueError``.
- **Rewards.** Without a config the adapters default to ``reward_type="exponential"``: ``exp(-c)`` in (0, 1] per
  step, with ``c`` the quadratic cost of ``scg_jax.env``, and episodes that terminate when the state leaves the
  failure bounds. A positive reward makes ending early cost return, so stable-baselines3's PPO with its default
  settings learns on every id (see ``examples/sb3_ppo.py``); with ``reward_type="quadratic"`` (-c) and
  termination, ending early raises the return. A config decides the reward type itself; a keyword overrides both.
- **Observations.** ``float32`` of shape ``(observation_size,)`` in ``Box(-inf, inf)``: the state is unbounded
  for the cart-pole's velocities, an episode ends *outside* the failure bounds, and observation noise is
  unbounded, so no finite box would hold every observation.
- **Episode end.** ``terminated`` (out of bounds, goal with ``done_on_goal``, violation with
  ``done_on_violation``, non-finite state) and ``truncated`` (time limit ``episode_len_sec``, only when not
  terminated) come from the functional env and are never merged. No ``TimeLimit`` wrapper is used.
- **Seeding.** ``reset(seed=s)`` starts the episode from ``jax.random.key(s)``, exactly like
  ``env.reset(jax.random.key(s), params)`` of the functional env. ``reset()`` continues the chain with the key
  ``scg_jax.rollout.next_reset_key(state.key)`` of the current episode (the one
  ``scg_jax.rollout.auto_reset_step`` uses), so a single env reset after every episode replays one copy of an
  auto-resetting batched rollout, and the vector env's autoreset is ``scg_jax.rollout.restart_done``, the one
  ``auto_reset_step`` uses. The vector env's ``reset(seed=s)`` uses
  ``scg_jax.rollout.initial_reset_keys(jax.random.key(s), num_envs)``, the reset keys of
  ``make_rollout``'s ``rollout(jax.random.key(s), params)``, or one ``jax.random.key(s_i)`` per copy for a list
  of seeds; so with ``autoreset_mode=SAME_STEP`` it replays that rollout's episodes.
- **Info.** Every step: ``cost`` (1.0 at a step in violation of a constraint), ``constraint_values``,
  ``constraint_violation``, ``mse`` and the rest of the functional env's info (``quadratic_cost``,
  ``out_of_bounds``, ``goal_reached``, ``nonfinite``, ``step``, ``u_cmd``, ``u``, ``f_ext``) as numpy values in the
  env's dtype. Reset (single env): the extended API of safe-control-gym, see ``ScgGymEnv.reset``.
- **Compilation.** The functional env, its jitted reset and step and its symbolic model are built once per
  distinct set of options and shared by every adapter instance made with the same options (so
  ``check_env``, ``SyncVectorEnv`` and repeated ``gymnasium.make`` calls do not recompile).
"""

from __future__ import annotations

import dataclasses
import functools
import json
import threading
from collections.abc import Iterable

import gymnasium
import jax
import jax.numpy as jnp
import numpy as np
from gymnasium import spaces
from gymnasium.utils import seeding
from gymnasium.vector import AutoresetMode, VectorEnv, VectorWrapper
from gymnasium.vector.utils import batch_space

from scg_jax.caching import CompileCache
from scg_jax.config import Config, EnvConfig, load_config, make_from_config
from scg_jax.env import Env, EnvParams, EnvState, make
from scg_jax.rollout import initial_reset_keys, next_reset_key, restart_done, select_where

DEFAULT_ACTION_MODE = "normalized"
# A positive per-step reward, so that termination (falling over, leaving the bounds) costs the return of the
# steps not taken: with the quadratic reward -c, ending an episode early *raises* the return, and standard RL
# libraries with their default settings learn to crash (the paper's RL runs use the exponential reward too).
DEFAULT_REWARD_TYPE = "exponential"
RENDER_MODES = ("rgb_array",)
_MAX_SEED = 2**31 - 1


# ============================================================================================== options
def _resolve_options(system, task, config, overrides, make_options) -> tuple[str, str, dict, Config | None]:
    """``(system, task, options, config)`` for ``scg_jax.make`` from the adapter's constructor arguments."""
    if isinstance(overrides, str):
        raise TypeError(f"overrides: expected a list of 'dotted.key=value' strings, got the string {overrides!r}")
    if config is None:
        if overrides:
            raise ValueError("overrides: only allowed together with config=; pass make's options as keywords instead")
        if system is None:
            raise ValueError("system: required (cartpole, quadrotor_1d, quadrotor_2d or quadrotor_3d) unless config=")
        options = {"action_mode": DEFAULT_ACTION_MODE, "reward_type": DEFAULT_REWARD_TYPE, **make_options}
        return system, "stabilization" if task is None else task, options, None
    if isinstance(config, EnvConfig):
        config = Config(env=config)
    cfg = load_config(config, list(overrides or ()))
    if task is not None or make_options:
        data = cfg.to_dict()
        data["env"].update(make_options)
        if task is not None:
            data["env"]["task"] = task
        cfg = load_config(data)
    if system is not None and cfg.env.system != system:
        raise ValueError(
            f"config: describes system {cfg.env.system!r} but this env is for {system!r}; use the id of "
            f"{cfg.env.system!r} or leave the system out"
        )
    return cfg.env.system, cfg.env.task, cfg.env.make_options(), cfg


def _plain_array(value):
    """``json.dumps``'s ``default``: arrays and numpy scalars as lists and numbers; anything else is not plain data."""
    if isinstance(value, np.ndarray | np.generic | jax.Array):
        return np.asarray(value).tolist()
    raise TypeError(f"not plain data: {type(value).__name__}")


# ============================================================================================== packing
def _is_key(leaf) -> bool:
    return jax.dtypes.issubdtype(leaf.dtype, jax.dtypes.prng_key)


class _Packer:
    """A pytree of small arrays as one flat array per dtype, so a jitted call has few arguments and results.

    A call of the single env is bound by dispatch (a few microseconds per argument and result leaf), not by
    arithmetic, so its state and outputs cross the jit boundary packed. ``pack`` and ``unpack`` run inside
    ``jit``; ``to_host`` rebuilds the tree as numpy values (0-d leaves as numpy scalars). PRNG key leaves are
    stored as their key data.
    """

    def __init__(self, shapes):
        impls = {}

        def key_data(tree):
            leaves = jax.tree.leaves(tree)
            for i, leaf in enumerate(leaves):
                if _is_key(leaf):
                    impls[i] = jax.random.key_impl(leaf)
            return [jax.random.key_data(leaf) if _is_key(leaf) else leaf for leaf in leaves]

        self.treedef = jax.tree.structure(shapes)
        leaves = jax.eval_shape(key_data, shapes)
        self.impls = [impls.get(i) for i in range(len(leaves))]
        self.dtypes = sorted({np.dtype(leaf.dtype) for leaf in leaves}, key=str)
        self.groups = [[i for i, leaf in enumerate(leaves) if np.dtype(leaf.dtype) == d] for d in self.dtypes]
        self.layout = [None] * len(leaves)
        for g, indices in enumerate(self.groups):
            offset = 0
            for i in indices:
                size = int(np.prod(leaves[i].shape, dtype=int))
                self.layout[i] = (g, offset, size, tuple(leaves[i].shape))
                offset += size

    def pack(self, tree) -> tuple:
        leaves = [jax.random.key_data(leaf) if _is_key(leaf) else leaf for leaf in jax.tree.leaves(tree)]
        return tuple(jnp.concatenate([jnp.ravel(leaves[i]) for i in indices]) for indices in self.groups)

    def _leaves(self, arrays):
        for (g, offset, size, shape), impl in zip(self.layout, self.impls, strict=True):
            yield arrays[g][offset : offset + size].reshape(shape), impl

    def unpack(self, packed):
        leaves = [
            leaf if impl is None else jax.random.wrap_key_data(leaf, impl=impl) for leaf, impl in self._leaves(packed)
        ]
        return jax.tree.unflatten(self.treedef, leaves)

    def to_host(self, packed):
        """The tree as numpy values (no key leaves allowed); 0-d leaves become numpy scalars."""
        arrays = [np.asarray(p) for p in packed]
        leaves = [leaf[()] if leaf.ndim == 0 else leaf.copy() for leaf, _ in self._leaves(arrays)]
        return jax.tree.unflatten(self.treedef, leaves)


def _physics_dict(physics) -> dict:
    return {field.name: getattr(physics, field.name) for field in dataclasses.fields(physics)}


# ============================================================================================== compiled
class _Compiled:
    """One functional env, its default params and its jitted single and batched functions.

    Shared by every adapter instance made with the same options (see ``_compiled``). ``params`` are closed over
    (fewer arguments to flatten per call: the single env is bound by dispatch, not by arithmetic).
    """

    def __init__(self, env: Env, params: EnvParams):
        self.env = env
        self.params = params
        self.dtype = np.dtype(params.goal.dtype)
        state_shape = jax.eval_shape(lambda: env.reset(jax.random.key(0), params)[1])
        action_shape = jax.ShapeDtypeStruct((env.nu,), self.dtype)
        self.state_packer = _Packer(state_shape)
        self.step_packer = _Packer(jax.eval_shape(self._step_outputs, state_shape, action_shape)[1])
        # The single env: packed state in, packed state and packed outputs out.
        self.reset = jax.jit(self._packed_reset)
        self.step = jax.jit(self._packed_step)
        self.unpack_state = jax.jit(self.state_packer.unpack)
        self.next_reset_key = jax.jit(lambda packed: next_reset_key(self.state_packer.unpack(packed).key))
        self.vector_reset = jax.jit(jax.vmap(self._reset))
        self.vector_reset_masked = jax.jit(self._vector_reset_masked)
        self.vector_steps = {mode: jax.jit(functools.partial(self._vector_step, mode)) for mode in AutoresetMode}
        self.vector_next_reset_key = jax.jit(jax.vmap(next_reset_key))
        self._lock = threading.Lock()
        self._model = None

    def symbolic_model(self):
        """The CasADi model of the nominal params, built once (the first call costs 0.1-0.3 s)."""
        with self._lock:
            if self._model is None:
                self._model = self.env.symbolic_model(self.params)
            return self._model

    # --------------------------------------------------------------------------------------- single
    def _reset(self, key):
        obs, state = self.env.reset(key, self.params)
        host = {"obs": obs.astype(jnp.float32), "x0": state.x, "physics": _physics_dict(state.physics)}
        return state, host

    def _step_outputs(self, state, action):
        out = self.env.step(state, action, self.params)
        info = {**out.info, "cost": out.cost}
        return out.state, (out.obs.astype(jnp.float32), out.reward, out.terminated, out.truncated, info)

    def _packed_reset(self, key):
        state, host = self._reset(key)
        return self.state_packer.pack(state), host

    def _packed_step(self, packed_state, action):
        state, host = self._step_outputs(self.state_packer.unpack(packed_state), action)
        return self.state_packer.pack(state), self.step_packer.pack(host)

    # --------------------------------------------------------------------------------------- batched
    def _vector_reset_masked(self, keys, mask, state):
        fresh, host = jax.vmap(self._reset)(keys)
        return select_where(mask, fresh, state), host

    def _vector_step(self, mode: AutoresetMode, state, prev_done, action):
        """One batched step; finished copies restart by ``scg_jax.rollout.restart_done`` (the suite's one
        auto-reset), per ``mode``:

        - NEXT_STEP: copies done at the previous step start a new episode instead of stepping (reward 0,
          terminated and truncated False, info zeros);
        - SAME_STEP: a finished copy restarts in the same call (as ``auto_reset_step``); the observation of the
          finished step is ``info["final_obs"]``; reward, flags and info describe the finished step;
        - DISABLED: no automatic reset; reset finished copies with ``reset(options={"reset_mask": done})``.
        """
        out = jax.vmap(self.env.step, in_axes=(0, 0, None))(state, action, self.params)
        obs, next_state, reward, terminated, truncated = out.obs, out.state, out.reward, out.terminated, out.truncated
        info = {**out.info, "cost": out.cost}
        if mode != AutoresetMode.DISABLED:
            reset = jax.vmap(self.env.reset, in_axes=(0, None))
            # The key is the same before and after the step (EnvState.key is the episode's key).
            done = prev_done if mode == AutoresetMode.NEXT_STEP else terminated | truncated
            obs, next_state = restart_done(done, state.key, (obs, next_state), lambda k: reset(k, self.params), True)
        if mode == AutoresetMode.NEXT_STEP:
            keep = ~prev_done
            terminated, truncated = terminated & keep, truncated & keep
            reward = jnp.where(keep, reward, jnp.zeros_like(reward))
            info = jax.tree.map(lambda v: select_where(keep, v, jnp.zeros_like(v)), info)
        elif mode == AutoresetMode.SAME_STEP:
            info["final_obs"] = out.obs.astype(jnp.float32)
        return next_state, terminated | truncated, (obs.astype(jnp.float32), reward, terminated, truncated, info)


# Adapter instances made with the same options share one _Compiled (the env and its jitted functions).
_CACHE = CompileCache(maxsize=16)


def _compiled(system: str, task: str, options: dict, config: Config | None = None) -> _Compiled:
    """The ``_Compiled`` of these options, from the cache (built on a miss)."""

    def build():
        if config is not None:  # make_from_config prefixes make's errors with the dotted config path
            env, params = make_from_config(config)
        else:
            env = make(system, task, **options)
            params = env.default_params
        return _Compiled(env, params)

    try:
        # The default float dtype (jax_enable_x64) decides the params' dtype, so it is part of the key; one spelling
        # per value (tuples and arrays as lists, sorted keys).
        key = json.dumps([system, task, options, str(jnp.zeros(()).dtype)], sort_keys=True, default=_plain_array)
    except TypeError:  # options that are not plain data: build without caching
        return build()
    return _CACHE.get(key, build)


def _build(system, task, config, overrides, make_options) -> _Compiled:
    system, task, options, cfg = _resolve_options(system, task, config, overrides, make_options)
    return _compiled(system, task, options, cfg)


def _spaces(compiled: _Compiled) -> tuple[spaces.Box, spaces.Box]:
    env = compiled.env
    if env.action_mode == "normalized":
        action_space = spaces.Box(-1.0, 1.0, (env.nu,), np.float32)
    else:
        low, high = env.input_bounds(compiled.params.physics)
        action_space = spaces.Box(np.asarray(low, np.float32), np.asarray(high, np.float32), (env.nu,), np.float32)
    observation_space = spaces.Box(-np.inf, np.inf, (env.observation_size,), np.float32)
    return observation_space, action_space


def _check_render_mode(render_mode):
    if render_mode is not None and render_mode not in RENDER_MODES:
        raise ValueError(f"render_mode: unknown value {render_mode!r}; allowed values are None, rgb_array")


def _render(compiled: _Compiled, x, physics, width: int, height: int):
    from scg_jax.render import render_frame

    params = compiled.params.replace(physics=physics)  # the episode's plant (e.g. a randomised pole length)
    x_ref = compiled.symbolic_model().x_ref if compiled.env.task == "tracking" else None  # goal drawn anyway
    return render_frame(compiled.env, np.asarray(x), params, x_ref=x_ref, width=width, height=height)


# ============================================================================================== single env
class ScgGymEnv(gymnasium.Env):
    """One scg-jax environment behind the Gymnasium ``Env`` API (numpy in and out, one jitted call per step).

    Args:
        system: ``cartpole``, ``quadrotor_1d``, ``quadrotor_2d`` or ``quadrotor_3d`` (set by the registered id;
            may be left out with ``config``, must match it otherwise).
        task: ``stabilization`` (default) or ``tracking``.
        render_mode: ``None`` or ``"rgb_array"``.
        config: a config path, YAML text, mapping, ``Config`` or ``EnvConfig`` (see ``scg_jax.load_config``);
            it decides every option, ``action_mode`` included.
        overrides: ``"env.key=value"`` strings applied to ``config``.
        render_width, render_height: frame size of ``render()``, pixels.
        **make_options: options of ``scg_jax.make``; ``action_mode`` defaults to ``"normalized"`` and
            ``reward_type`` to ``"exponential"`` here (``make``'s defaults are physical and quadratic).

    Attributes:
        functional_env: the ``scg_jax.Env``. params: its ``EnvParams`` (fixed per instance).
        state: the current ``EnvState`` (JAX arrays; ``None`` before the first reset).
    """

    metadata = {"render_modes": list(RENDER_MODES), "render_fps": 50}

    def __init__(
        self,
        system: str | None = None,
        task: str | None = None,
        render_mode: str | None = None,
        config=None,
        overrides: Iterable[str] = (),
        render_width: int = 480,
        render_height: int = 480,
        **make_options,
    ):
        _check_render_mode(render_mode)
        self._compiled = _build(system, task, config, overrides, make_options)
        self.functional_env = self._compiled.env
        self.params = self._compiled.params
        self.render_mode = render_mode
        self.render_size = (int(render_width), int(render_height))
        self.metadata = {**type(self).metadata, "render_fps": self.functional_env.ctrl_freq}
        self.observation_space, self.action_space = _spaces(self._compiled)
        self._packed_state = None

    @property
    def state(self) -> EnvState | None:
        """The current ``EnvState`` (JAX arrays), ``None`` before the first reset."""
        return None if self._packed_state is None else self._compiled.unpack_state(self._packed_state)

    @property
    def symbolic_model(self):
        """The CasADi ``SymbolicModel`` of the nominal params (built once per set of options)."""
        return self._compiled.symbolic_model()

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        """Start an episode.

        Args:
            seed: a non-negative integer: the episode starts from ``jax.random.key(seed)``. ``None``: continue
                from the current episode's key (or, on the very first reset, from a random seed).
            options: must be empty (there are no reset options).

        Returns:
            ``(obs, info)``; ``info`` holds what the extended API of safe-control-gym promises:
            ``symbolic_model`` (CasADi model of the *nominal* plant; randomised parameters are in ``physics``),
            ``x_reference`` (num_steps + 1, nx) and ``u_reference`` (num_steps, nu), ``constraints`` (one CasADi
            function ``g_i(x, u)`` per constraint, ``g <= 0`` satisfied) and ``g`` (all rows), ``physics`` (the
            plant's parameters drawn for this episode, floats), ``x0`` (the true initial state, before observation
            noise), ``ctrl_timestep`` (s), ``ctrl_freq`` (Hz), ``episode_len_sec`` (s); and the safe-control-gym
            names ``physical_parameters`` (= ``physics``) and ``symbolic_constraints`` (= ``constraints``).
        """
        if options:
            raise ValueError(f"options: unknown reset options {sorted(options)}; there are none")
        super().reset(seed=seed)
        if seed is not None:
            key = jax.random.key(seed)
        elif self._packed_state is not None:
            key = self._compiled.next_reset_key(self._packed_state)
        else:
            key = jax.random.key(int(self.np_random.integers(_MAX_SEED)))
        self._packed_state, host = self._compiled.reset(key)
        host = jax.tree.map(np.array, host)
        model = self._compiled.symbolic_model()
        physics = {name: float(value) for name, value in host["physics"].items()}
        env = self.functional_env
        info = {
            "symbolic_model": model,
            "x_reference": model.x_ref.copy(),
            "u_reference": model.u_ref.copy(),
            "constraints": model.constraints,
            "g": model.g,
            "physics": physics,
            "x0": host["x0"],
            "ctrl_timestep": env.dt,
            "ctrl_freq": env.ctrl_freq,
            "episode_len_sec": env.episode_len_sec,
            "physical_parameters": dict(physics),
            "symbolic_constraints": model.constraints,
        }
        return host["obs"], info

    def step(self, action):
        """Advance one control step with ``action`` of shape ``action_space.shape`` (not clipped here).

        Returns:
            ``(obs float32, reward float, terminated bool, truncated bool, info)``; ``info`` as in the module
            docstring (numpy values; ``cost`` 1.0 at a step in violation).
        """
        if self._packed_state is None:
            raise gymnasium.error.ResetNeeded("step: call reset before step")
        action = np.asarray(action, dtype=self._compiled.dtype)
        if action.shape != self.action_space.shape:
            raise ValueError(
                f"action: expected shape {self.action_space.shape} (nu = {self.functional_env.nu}), got {action.shape}"
            )
        self._packed_state, packed = self._compiled.step(self._packed_state, action)
        obs, reward, terminated, truncated, info = self._compiled.step_packer.to_host(packed)
        return obs, float(reward), bool(terminated), bool(truncated), info

    def render(self):
        """The current state as an ``(height, width, 3)`` uint8 frame (``render_mode="rgb_array"``), else None."""
        if self.render_mode is None:
            gymnasium.logger.warn("render: called without a render_mode; make the env with render_mode='rgb_array'")
            return None
        state = self.state
        if state is None:
            raise gymnasium.error.ResetNeeded("render: call reset before render")
        width, height = self.render_size
        return _render(self._compiled, state.x, state.physics, width, height)


# ============================================================================================== vector env
def _autoreset_mode(value) -> AutoresetMode:
    if isinstance(value, AutoresetMode):
        return value
    if isinstance(value, str):
        for mode in AutoresetMode:
            if value in (mode.value, mode.name, mode.name.lower()):
                return mode
    allowed = ", ".join(f"AutoresetMode.{mode.name}" for mode in AutoresetMode)
    raise ValueError(f"autoreset_mode: unknown value {value!r}; allowed values are {allowed} (or their names)")


class ScgVectorEnv(VectorEnv):
    """``num_envs`` copies of one scg-jax environment stepped by one jitted, vmapped call (Gymnasium 1.x API).

    ``gymnasium.make_vec(id, num_envs=N, ...)`` builds it (``vector_entry_point``); every copy has its own key,
    so initial states, randomised physical parameters and disturbances differ between copies.

    Args:
        num_envs: number of copies N.
        autoreset_mode: ``AutoresetMode.NEXT_STEP`` (default, as Gymnasium's own vector envs): after a step
            where a copy terminated or was truncated, its next ``step`` ignores the action and returns the first
            observation of a new episode with reward 0, ``terminated = truncated = False`` and zero info.
            ``SAME_STEP``: the copy restarts in the same call; ``obs`` is the new episode's first observation,
            ``info["final_obs"]`` (with mask ``info["_final_obs"]``) the observation of the finished step, and
            reward, flags and the rest of ``info`` describe the finished step (``info["final_info"]`` is the same
            step info, masked by ``info["_final_info"]``); this is ``scg_jax.rollout.auto_reset_step``.
            ``DISABLED``: no reset; call ``reset(options={"reset_mask": done})``. Names such as ``"same_step"``
            are accepted. The mode is in ``metadata["autoreset_mode"]``.
        the rest: as ``ScgGymEnv``.

    Observations are ``float32 (N, observation_size)``; rewards ``(N,)`` in the env's dtype; flags ``(N,)``
    bool; ``info`` a dict of ``(N, ...)`` numpy arrays (``cost``, ``constraint_values``, ``constraint_violation``,
    ``mse``, ...). The reset info holds ``x0`` (N, nx) and ``physics`` (``{name: (N,)}``) of the copies that were
    reset, with masks ``_x0`` and ``_physics``; the shared items of the single env's reset info are attributes:
    ``symbolic_model``, ``x_reference``, ``u_reference``.
    """

    metadata = {"render_modes": list(RENDER_MODES), "render_fps": 50, "autoreset_mode": AutoresetMode.NEXT_STEP}

    def __init__(
        self,
        num_envs: int = 1,
        system: str | None = None,
        task: str | None = None,
        render_mode: str | None = None,
        config=None,
        overrides: Iterable[str] = (),
        autoreset_mode: AutoresetMode | str = AutoresetMode.NEXT_STEP,
        render_width: int = 480,
        render_height: int = 480,
        **make_options,
    ):
        if isinstance(num_envs, bool) or not float(num_envs).is_integer() or num_envs < 1:
            raise ValueError(f"num_envs: must be a positive integer, got {num_envs!r}")
        _check_render_mode(render_mode)
        self.autoreset_mode = _autoreset_mode(autoreset_mode)
        self._compiled = _build(system, task, config, overrides, make_options)
        self.functional_env = self._compiled.env
        self.params = self._compiled.params
        self.num_envs = int(num_envs)
        self.render_mode = render_mode
        self.render_size = (int(render_width), int(render_height))
        self.metadata = {
            **type(self).metadata,
            "render_fps": self.functional_env.ctrl_freq,
            "autoreset_mode": self.autoreset_mode,
        }
        self.single_observation_space, self.single_action_space = _spaces(self._compiled)
        self.observation_space = batch_space(self.single_observation_space, self.num_envs)
        self.action_space = batch_space(self.single_action_space, self.num_envs)
        self._step_fn = self._compiled.vector_steps[self.autoreset_mode]
        self.state: EnvState | None = None
        self._done = None
        self._obs = None

    # --------------------------------------------------------------------------------------- shared data
    @property
    def symbolic_model(self):
        """The CasADi ``SymbolicModel`` of the nominal params."""
        return self._compiled.symbolic_model()

    @property
    def x_reference(self) -> np.ndarray:
        return self._compiled.symbolic_model().x_ref.copy()

    @property
    def u_reference(self) -> np.ndarray:
        return self._compiled.symbolic_model().u_ref.copy()

    # --------------------------------------------------------------------------------------- API
    def _reset_keys(self, seed):
        n = self.num_envs
        if seed is None:
            if self.state is not None:
                return self._compiled.vector_next_reset_key(self.state.key)
            self._np_random, self._np_random_seed = seeding.np_random()
            return jax.random.split(jax.random.key(int(self._np_random.integers(_MAX_SEED))), n)
        if isinstance(seed, int | np.integer) and not isinstance(seed, bool):
            self._np_random, self._np_random_seed = seeding.np_random(int(seed))
            return initial_reset_keys(jax.random.key(int(seed)), n)
        seeds = list(seed)
        if len(seeds) != n or not all(isinstance(s, int | np.integer) and s >= 0 for s in seeds):
            raise ValueError(f"seed: expected None, a non-negative integer or {n} non-negative integers, got {seed!r}")
        return jnp.stack([jax.random.key(int(s)) for s in seeds])

    def reset(self, *, seed: int | list[int] | None = None, options: dict | None = None):
        """Reset every copy, or those in ``options["reset_mask"]`` ((N,) bool).

        ``seed``: an integer (copy i starts from ``scg_jax.rollout.initial_reset_keys(jax.random.key(seed), N)[i]``,
        as copy i of ``make_rollout``'s ``rollout(jax.random.key(seed), params)``), a list of N integers (copy i
        from ``jax.random.key(seed[i])``) or ``None`` (continue each copy's key chain).
        """
        options = dict(options or {})
        mask = options.pop("reset_mask", None)
        if options:
            raise ValueError(f"options: unknown reset options {sorted(options)}; allowed is reset_mask")
        if mask is not None:
            mask = np.asarray(mask)
            if mask.shape != (self.num_envs,) or mask.dtype != np.bool_:
                raise ValueError(f"options['reset_mask']: expected a ({self.num_envs},) bool array, got {mask!r}")
            if self.state is None:
                raise gymnasium.error.ResetNeeded("reset: the first reset must reset every copy (no reset_mask)")
        keys = self._reset_keys(seed)
        if mask is None:
            self.state, host = self._compiled.vector_reset(keys)
            mask = np.ones(self.num_envs, bool)
        else:
            self.state, host = self._compiled.vector_reset_masked(keys, mask, self.state)
        host = jax.tree.map(np.array, host)
        obs = host["obs"] if self._obs is None else np.where(mask[:, None], host["obs"], self._obs)
        self._obs = obs
        done = np.zeros(self.num_envs, bool) if self._done is None else np.asarray(self._done) & ~mask
        self._done = jnp.asarray(done)
        info = {"x0": host["x0"], "_x0": mask.copy(), "physics": host["physics"], "_physics": mask.copy()}
        return obs.copy(), info

    def step(self, actions):
        """Step every copy with ``actions`` (N, nu); autoreset per ``metadata["autoreset_mode"]``."""
        if self.state is None:
            raise gymnasium.error.ResetNeeded("step: call reset before step")
        actions = np.asarray(actions, dtype=self._compiled.dtype)
        if actions.shape != self.action_space.shape:
            raise ValueError(f"actions: expected shape {self.action_space.shape} (num_envs, nu), got {actions.shape}")
        self.state, self._done, host = self._step_fn(self.state, self._done, actions)
        obs, reward, terminated, truncated, info = jax.tree.map(np.array, host)
        if self.autoreset_mode == AutoresetMode.SAME_STEP:
            done = terminated | truncated
            final_info = {key: value for key, value in info.items() if key != "final_obs"}
            info.update(_final_obs=done, final_info=final_info, _final_info=done.copy())
        self._obs = obs
        return obs.copy(), reward, terminated, truncated, info

    def render(self):
        """One ``(height, width, 3)`` uint8 frame per copy (``render_mode="rgb_array"``), else None."""
        if self.render_mode is None:
            gymnasium.logger.warn("render: called without a render_mode; make the env with render_mode='rgb_array'")
            return None
        if self.state is None:
            raise gymnasium.error.ResetNeeded("render: call reset before render")
        xs = np.asarray(self.state.x)
        physics = jax.tree.map(np.asarray, self.state.physics)
        width, height = self.render_size
        return tuple(
            _render(self._compiled, xs[i], jax.tree.map(lambda v, i=i: v[i], physics), width, height)
            for i in range(self.num_envs)
        )


# ============================================================================================== safety
class SafetyGymnasiumWrapper(gymnasium.Wrapper):
    """``step`` returns the safety-gymnasium six-tuple ``(obs, reward, cost, terminated, truncated, info)``.

    ``cost`` is ``info["cost"]`` as a float: 1.0 at a step where a constraint is violated, else 0.0 (so an
    episode's cost is its number of steps in violation). Given a ``VectorEnv`` it returns a
    ``SafetyGymnasiumVectorWrapper`` instead (costs ``(N,)``).
    """

    def __new__(cls, env, *args, **kwargs):
        if isinstance(env, VectorEnv):
            return SafetyGymnasiumVectorWrapper(env)
        return super().__new__(cls)

    def step(self, action):
        obs, reward, terminated, truncated, info = self.env.step(action)
        return obs, reward, float(info["cost"]), terminated, truncated, info


class SafetyGymnasiumVectorWrapper(VectorWrapper):
    """The vector form of ``SafetyGymnasiumWrapper``: ``cost`` is ``info["cost"]`` (N,)."""

    def step(self, actions):
        obs, reward, terminated, truncated, info = self.env.step(actions)
        return obs, reward, np.asarray(info["cost"]), terminated, truncated, info


__all__ = [
    "DEFAULT_ACTION_MODE",
    "DEFAULT_REWARD_TYPE",
    "SafetyGymnasiumVectorWrapper",
    "SafetyGymnasiumWrapper",
    "ScgGymEnv",
    "ScgVectorEnv",
]
