"""The functional environment: ``make`` decides static structure, ``reset``/``step`` are pure functions.

``env = make(system, task, **options)`` holds only what is fixed for every parallel copy (system, task,
trajectory shape and plane, frequencies, episode length, integrator, action mode, reward type, observation
layout). Everything that may differ between copies lives in ``EnvParams`` (sweep it with ``jax.vmap``) or in
``EnvState`` (the PRNG key travels there, so a rollout is fully determined by the reset key and the params).

Step semantics (control step ``k -> k + 1``):

1. ``u_cmd`` is the action (``action_mode="physical"``) or its conversion (``"normalized"``);
2. the action-channel disturbances (and an action adversary) are added to ``u_cmd``, and the applied input is
   that sum clipped to the plant's actuator limits (saturation is physics; ``info["u_cmd"]`` and ``info["u"]``
   report both);
3. the plant integrates ``dynamics`` with the episode's physical parameters ``state.physics`` and the
   dynamics-channel force ``f_ext`` (held) over ``physics_freq / ctrl_freq`` substeps;
4. the reward compares ``x_{k+1}`` with ``x_ref[k+1]`` and ``u`` with ``u_ref[k]``, the same indices for every
   system, so the rewards of an episode sum to ``-J`` of the paper less its constant ``x_0`` term;
5. constraints are evaluated at ``(x_{k+1}, u_cmd)``; the observation of ``x_{k+1}`` gets the
   observation-channel disturbances (and an observation adversary's input).

A non-finite state after integration (e.g. from a NaN action) ends the episode, keeps ``x_k`` and still gives a
finite reward and cost (see ``Env.step``). ``params.replace(...)`` is unchecked; ``Env.with_physics`` and
``Env.validate`` check values as ``make`` does.

Rewards (``reward_type``), with ``c = 1/2 e^T Q e + 1/2 du^T R du``, ``e = x_{k+1} - x_ref[k+1]``,
``du = u - u_ref[k]``:

- ``"quadratic"``: ``-c``;
- ``"exponential"``: ``exp(-c)``, in (0, 1];
- ``"upright"`` (cart-pole only): ``1`` when ``x_{k+1}`` is inside the failure bounds, else ``0`` (the classic
  cart-pole reward; the return is the number of upright steps).

``cost`` is the constrained-MDP cost: 1 at a step where any constraint row is violated, else 0, so an
episode's cost is its number of steps in violation. ``violation_penalty`` (>= 0) is *subtracted* from the reward
at such steps, and ``done_on_violation`` ends the episode there.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from scg_jax import constraints as constraints_lib
from scg_jax import disturbances as disturbances_lib
from scg_jax import randomization, trajectories
from scg_jax import validation as V
from scg_jax._pytree import pytree_dataclass
from scg_jax.backends import jax_backend
from scg_jax.env_config import _OPTION_DEFAULTS, DEFAULT_TASK, DistributionConfig, EnvConfig
from scg_jax.integrators import make_discrete_dynamics
from scg_jax.systems import System, get_system
from scg_jax.validation import FieldError

TRAJECTORY_KEYS = ("shape", "num_cycles", "plane", "offset", "scale")
CHANNEL_INDEX = {channel: i for i, channel in enumerate(disturbances_lib.CHANNELS)}
TRAJECTORY_KEYS = ("shape", "num_cycles", "plane", "offset", "scale")


@pytree_dataclass
class TrajectoryParams:
    """Traced trajectory settings (the shape and plane are static, on the env).

    Attributes:
        scale: s, m (negative flips the shape).
        offset: (2,) in-plane offset, m.
        num_cycles: cycles per episode; the period is ``episode_len_sec / num_cycles``.
    """

    scale: Any
    offset: Any
    num_cycles: Any


@pytree_dataclass
class EnvParams:
    """Everything that may differ between parallel copies; batch any leaf and ``jax.vmap`` over it.

    Attributes:
        physics: the system's ``Params``: the nominal plant, copied into ``EnvState.physics`` at reset.
        Q: (nx, nx) state cost weight. R: (nu, nu) input cost weight.
        goal: (nx,) stabilization goal state.
        goal_tolerance: Euclidean distance to ``goal`` under which ``info["goal_reached"]`` is true.
        init_state: ``DistributionParams`` of the initial state (nx,).
        physics_randomization: ``{field: DistributionParams}`` of the randomised physical parameters.
        state_low, state_high: (nx,) failure bounds; leaving them sets ``info["out_of_bounds"]``.
        trajectory: ``TrajectoryParams`` (used by the tracking task).
        mse_weight: (nx,) weights of the squared tracking error reported as ``info["mse"]``.
        constraints: tuple of ``LinearConstraintParams`` / ``QuadraticConstraintParams``, in option order.
        violation_penalty: subtracted from the reward at a step in violation (>= 0).
        disturbances: ``{channel: tuple of DisturbanceParams}``.
        adversary_scale: (dim,) of the adversary's channel: the adversary input in [-1, 1] is multiplied by it.
    """

    physics: Any
    Q: Any
    R: Any
    goal: Any
    goal_tolerance: Any
    init_state: Any
    physics_randomization: dict
    state_low: Any
    state_high: Any
    trajectory: TrajectoryParams
    mse_weight: Any
    constraints: tuple
    violation_penalty: Any
    disturbances: dict
    adversary_scale: Any


@pytree_dataclass
class EnvState:
    """The state of one copy.

    Attributes:
        x: (nx,) physical state.
        step: control-step counter (int32), 0 after reset.
        key: the episode's PRNG key; the random disturbances of step k (and the observation noise of the state it
            reaches) are drawn from ``fold_in(key, k)``.
        physics: the plant's physical parameters in this episode (randomised ones as drawn).
        disturbances: ``{channel: tuple of DisturbanceState}``, the per-episode draws (periodic phases, impulse
            starts).
    """

    x: Any
    step: Any
    key: Any
    physics: Any
    disturbances: dict


class StepOutput(NamedTuple):
    """What ``Env.step`` returns; ``info`` is a dict of arrays (see ``Env.step``)."""

    obs: Any
    state: EnvState
    reward: Any
    cost: Any
    terminated: Any
    truncated: Any
    info: dict


@dataclasses.dataclass(frozen=True, eq=False)
class Env:
    """A functional environment; build it with ``scg_jax.make``. Hashable by identity, so it can be static."""

    system: System
    task: str
    ctrl_freq: int
    physics_freq: int
    episode_len_sec: float
    integrator: str
    action_mode: str
    reward_type: str
    obs_goal_horizon: int
    done_on_out_of_bounds: bool
    done_on_goal: bool
    trajectory_shape: str | None
    trajectory_plane: str | None
    done_on_violation: bool
    init_state_spec: randomization.DistributionSpec
    physics_randomization_specs: dict
    constraint_specs: tuple
    disturbance_specs: dict
    adversary_channel: str | None
    _default_params_numpy: dict

    # ----------------------------------------------------------------------------------------- structure
    @property
    def dt(self) -> float:
        """Control period, s."""
        return 1.0 / self.ctrl_freq

    @property
    def substeps(self) -> int:
        """Physics steps per control step."""
        return self.physics_freq // self.ctrl_freq

    @property
    def num_steps(self) -> int:
        """Control steps per episode (the reference holds ``num_steps + 1`` points)."""
        return round(self.episode_len_sec * self.ctrl_freq)

    @property
    def nx(self) -> int:
        return self.system.nx

    @property
    def nu(self) -> int:
        return self.system.nu

    @property
    def observation_size(self) -> int:
        """``nx * (1 + obs_goal_horizon)``: the state followed by the next H reference states."""
        return self.nx * (1 + self.obs_goal_horizon)

    @property
    def action_size(self) -> int:
        return self.nu

    @property
    def default_params(self) -> EnvParams:
        """Fresh ``EnvParams`` from the options given to ``make`` (arrays in the current default float dtype)."""
        d = self._default_params_numpy
        dtype = jnp.zeros(()).dtype
        as_array = lambda value: jnp.asarray(value, dtype=dtype)  # noqa: E731
        return EnvParams(
            physics=jax.tree.map(as_array, d["physics"]),
            Q=as_array(d["Q"]),
            R=as_array(d["R"]),
            goal=as_array(d["goal"]),
            goal_tolerance=as_array(d["goal_tolerance"]),
            init_state=randomization.DistributionParams(**jax.tree.map(as_array, d["init_state"])),
            physics_randomization={
                name: randomization.DistributionParams(**jax.tree.map(as_array, values))
                for name, values in d["physics_randomization"].items()
            },
            state_low=as_array(self.system.state_low),
            state_high=as_array(self.system.state_high),
            trajectory=TrajectoryParams(
                scale=as_array(d["trajectory"]["scale"]),
                offset=as_array(d["trajectory"]["offset"]),
                num_cycles=as_array(d["trajectory"]["num_cycles"]),
            ),
            mse_weight=as_array(d["mse_weight"]),
            constraints=tuple(
                constraints_lib.params_from_numpy(spec, values, as_array)
                for spec, values in zip(self.constraint_specs, d["constraints"], strict=True)
            ),
            violation_penalty=as_array(d["violation_penalty"]),
            disturbances={
                channel: tuple(
                    disturbances_lib.DisturbanceParams(
                        **{
                            k: (jnp.asarray(v) if k in ("start_step", "duration") else as_array(v))
                            for k, v in values.items()
                        }
                    )
                    for values in entries
                )
                for channel, entries in d["disturbances"].items()
            },
            adversary_scale=as_array(d["adversary_scale"]),
        )

    def with_physics(self, params: EnvParams, **fields) -> EnvParams:
        """``params`` with the named physical parameters replaced, checked as ``make`` checks them.

        ``params.replace(physics=params.physics.replace(...))`` is the raw, unchecked path (it must stay
        traceable); this is the checked one: unknown names and non-physical values (a negative mass, a minimum
        thrust above the maximum, ...) raise a ``ValueError`` naming the field. Values may be scalars or arrays
        (a sweep over copies); they must be concrete (call it outside ``jit``).

        Example: ``params = env.with_physics(env.default_params, pole_half_length=0.6)``.
        """
        allowed = [f.name for f in dataclasses.fields(params.physics)]
        V.check_keys(fields, "physics", allowed, what="parameter", where=f"of {self.system.name}")
        # Checked at the precision given (messages quote the values as written), then stored in the env's dtype.
        self.system.validate_params(params.physics.replace(**{k: np.asarray(v, float) for k, v in fields.items()}))
        dtype = jnp.zeros(()).dtype
        physics = params.physics.replace(**{name: jnp.asarray(value, dtype) for name, value in fields.items()})
        return self.validate(params.replace(physics=physics))

    def validate(self, params: EnvParams) -> EnvParams:
        """Check ``params`` (made by ``default_params`` and changed with raw ``replace``) and return it.

        Checks, each failing with a ``ValueError`` that names the field: the pytree structure and every leaf's
        trailing shape against ``default_params`` (extra leading axes are allowed: a batched sweep), physical
        parameters (``System.validate_params``, as ``make``), ``Q`` and ``R`` symmetric positive semidefinite,
        finite ``goal``, ``state_low`` <= ``state_high``, ``goal_tolerance`` > 0, ``mse_weight`` >= 0,
        ``violation_penalty`` >= 0, ``trajectory.num_cycles`` > 0 and a finite ``adversary_scale``. Values must be
        concrete (outside ``jit``). Raw ``params.replace(...)`` is never checked.
        """
        reference = self.default_params
        if jax.tree.structure(params) != jax.tree.structure(reference):
            raise ValueError(
                f"params: structure differs from env.default_params of this {self.system.name} env; build params "
                "from env.default_params and change values with replace or with_physics"
            )
        for (path, leaf), ref in zip(
            jax.tree_util.tree_leaves_with_path(params), jax.tree.leaves(reference), strict=True
        ):
            name = jax.tree_util.keystr(path).lstrip(".")
            if isinstance(leaf, jax.core.Tracer):
                raise ValueError(f"params.{name}: validate needs concrete values; call it outside jit")
            shape, ref_shape = jnp.shape(leaf), jnp.shape(ref)
            if shape[len(shape) - len(ref_shape) :] != ref_shape or len(shape) < len(ref_shape):
                raise ValueError(
                    f"params.{name}: expected shape {ref_shape} (with optional leading batch axes), got {shape}"
                )
        self.system.validate_params(params.physics)

        def check(name, ok, requirement, value):
            if not bool(np.all(ok)):
                raise ValueError(f"params.{name}: must be {requirement}, got {np.asarray(value).tolist()!r}")

        for name in ("Q", "R"):
            matrix = np.asarray(getattr(params, name), dtype=float)
            symmetric = np.allclose(matrix, np.swapaxes(matrix, -1, -2))
            check(
                name,
                symmetric and np.linalg.eigvalsh(matrix).min() >= -1e-12,
                "symmetric positive semidefinite",
                matrix,
            )
        goal = np.asarray(params.goal)
        check("goal", np.isfinite(goal), "finite", goal)
        low, high = np.asarray(params.state_low), np.asarray(params.state_high)
        check("state_low", low <= high, "<= state_high", low)
        tolerance = np.asarray(params.goal_tolerance)
        check("goal_tolerance", tolerance > 0, "positive", tolerance)
        weight = np.asarray(params.mse_weight)
        check("mse_weight", np.isfinite(weight) & (weight >= 0), "finite and non-negative", weight)
        penalty = np.asarray(params.violation_penalty)
        check("violation_penalty", np.isfinite(penalty) & (penalty >= 0), "finite and non-negative", penalty)
        cycles = np.asarray(params.trajectory.num_cycles)
        check("trajectory.num_cycles", np.isfinite(cycles) & (cycles > 0), "positive", cycles)
        scale = np.asarray(params.adversary_scale)
        check("adversary_scale", np.isfinite(scale), "finite", scale)
        return params

    def channel_dim(self, channel: str) -> int:
        """Dimension of a disturbance channel: nu (action), nx (observation), f_ext_dim (dynamics)."""
        return {"action": self.nu, "observation": self.nx, "dynamics": self.system.f_ext_dim}[channel]

    # ----------------------------------------------------------------------------------------- physics
    def discrete_dynamics(self):
        """``step(x, u, params, xp, f_ext=None) -> x_next`` over one control period (the plant's integrator)."""
        return make_discrete_dynamics(
            self.system.dynamics, self.integrator, self.dt, self.substeps, self.system.velocity_mask
        )

    def integrate(self, x, u, physics, f_ext=None):
        """Advance the plant one control period with input ``u`` (N) held; JAX arrays (nx,) -> (nx,)."""
        return self.discrete_dynamics()(x, u, physics, jax_backend, f_ext)

    def input_bounds(self, physics):
        """Actuator limits ``(u_low, u_high)``, each (nu,), of a plant with parameters ``physics``."""
        low, high = self.system.input_bounds(physics)
        return jnp.asarray(low), jnp.asarray(high)

    def action_to_input(self, action, params: EnvParams):
        """Physical input (nu,) for an action (nu,) in this env's ``action_mode``."""
        if self.action_mode == "normalized":
            return self.system.action_to_input(action, params.physics)
        return action

    def input_to_action(self, u, params: EnvParams):
        """Inverse of ``action_to_input``."""
        if self.action_mode == "normalized":
            return self.system.input_to_action(u, params.physics)
        return u

    # ----------------------------------------------------------------------------------------- reference
    def reference_at(self, step, params: EnvParams):
        """Reference ``(x_ref (nx,), u_ref (nu,))`` at control step ``step`` (clamped to ``[0, num_steps]``)."""
        u_ref = jnp.asarray(self.system.equilibrium_input(params.physics), dtype=params.goal.dtype)
        if self.task == "stabilization":
            return params.goal, u_ref
        k = jnp.clip(step, 0, self.num_steps)
        traj = params.trajectory
        period = self.episode_len_sec / traj.num_cycles
        position, velocity = trajectories.world_reference(
            self.trajectory_shape, self.trajectory_plane, k * self.dt, period, traj.scale, traj.offset
        )
        x_ref = jnp.zeros(self.nx, dtype=position.dtype)
        for axis, pos_index, vel_index in self.system.tracking_axes:
            x_ref = x_ref.at[pos_index].set(position[axis]).at[vel_index].set(velocity[axis])
        return x_ref, u_ref

    def reference(self, params: EnvParams):
        """The whole episode's reference: ``x_ref (num_steps + 1, nx)`` and ``u_ref (num_steps, nu)``."""
        x_ref, _ = jax.vmap(lambda k: self.reference_at(k, params))(jnp.arange(self.num_steps + 1))
        _, u_ref = jax.vmap(lambda k: self.reference_at(k, params))(jnp.arange(self.num_steps))
        return x_ref, u_ref

    # ----------------------------------------------------------------------------------------- reset / step
    def observe(self, state: EnvState, params: EnvParams):
        """Noise-free observation (observation_size,): ``x`` then ``x_ref`` at steps ``k+1 .. k+H``."""
        if self.obs_goal_horizon == 0:
            return state.x
        steps = state.step + 1 + jnp.arange(self.obs_goal_horizon)
        goals, _ = jax.vmap(lambda k: self.reference_at(k, params))(steps)
        return jnp.concatenate([state.x, goals.reshape(-1)])

    @property
    def has_step_noise(self) -> bool:
        """Whether any disturbance draws random numbers at every step (white noise or uniform)."""
        return any(
            spec.type in disturbances_lib.RANDOM_TYPES for specs in self.disturbance_specs.values() for spec in specs
        )

    def _step_noise(self, key, params: EnvParams) -> dict:
        """Standard samples of every per-step random disturbance from ``key`` (one draw for all channels)."""
        if not self.has_step_noise:
            return {}
        return disturbances_lib.draw_standard_noise(self.disturbance_specs, key, params.goal.dtype)

    def _disturb(self, channel: str, state: EnvState, params: EnvParams, noise: dict, step):
        return disturbances_lib.channel_value(
            channel,
            self.disturbance_specs.get(channel, ()),
            params.disturbances.get(channel, ()),
            state.disturbances.get(channel, ()),
            noise,
            step,
            self.dt,
            self.channel_dim(channel),
            params.goal.dtype,
        )

    def _noisy_observation(self, state: EnvState, params: EnvParams, noise: dict, adversary=None):
        """``observe`` plus the observation-channel disturbances and the observation adversary's ``adversary``
        (nx,), both on the state part only (the appended reference points are exact)."""
        obs = self.observe(state, params)
        if self.disturbance_specs.get("observation"):
            obs = obs.at[: self.nx].add(self._disturb("observation", state, params, noise, state.step))
        if adversary is not None:
            obs = obs.at[: self.nx].add(adversary)
        return obs

    def reset(self, key, params: EnvParams):
        """Start an episode: draw the initial state, the plant's randomised parameters and the per-episode
        disturbance draws. Returns ``(obs, state)``."""
        key, key_init, key_physics, key_disturbances, key_obs = jax.random.split(key, 5)
        x0 = randomization.draw(self.init_state_spec, params.init_state, key_init)
        physics = params.physics
        physics_keys = jax.random.split(key_physics, max(len(self.physics_randomization_specs), 1))
        for field_key, (name, spec) in zip(
            physics_keys, sorted(self.physics_randomization_specs.items()), strict=False
        ):
            drawn = randomization.draw(
                spec, params.physics_randomization[name], field_key, nominal=getattr(params.physics, name)
            )
            physics = physics.replace(**{name: drawn})
        draws = {}
        for channel, specs in self.disturbance_specs.items():
            channel_keys = jax.random.split(jax.random.fold_in(key_disturbances, CHANNEL_INDEX[channel]), len(specs))
            draws[channel] = tuple(
                disturbances_lib.initial_state(spec, p, k, self.num_steps)
                for spec, p, k in zip(specs, params.disturbances[channel], channel_keys, strict=True)
            )
        state = EnvState(x=x0, step=jnp.zeros((), jnp.int32), key=key, physics=physics, disturbances=draws)
        return self._noisy_observation(state, params, self._step_noise(key_obs, params)), state

    def step(self, state: EnvState, action, params: EnvParams, adversary=None) -> StepOutput:
        """Advance one control step.

        Args:
            state: ``EnvState`` of one copy. action: (nu,) in this env's ``action_mode`` (an array or a list; the
                shape is checked at trace time, so under ``jax.vmap`` it is the shape of one copy's action).
            params: ``EnvParams``.
            adversary: optional input (dim of the adversary channel,) in [-1, 1] (clipped to that range, by
                definition of the adversary's action space), times ``params.adversary_scale``; only for envs
                made with ``adversary``. It is added to that channel at this step: ``action`` to the commanded
                input ``u_cmd`` before saturation (N), ``dynamics`` to the external force ``f_ext`` (N),
                ``observation`` to the state part of the returned ``obs`` (of ``x_{k+1}``; the true state is
                unaffected).

        Returns:
            ``StepOutput`` with ``info`` holding ``mse`` (weighted squared tracking error of ``x_{k+1}``),
            ``quadratic_cost`` (``c`` above), ``out_of_bounds``, ``goal_reached``, ``nonfinite`` (the
            integration produced a non-finite state: the episode ends and the last finite state is kept),
            ``step`` (k + 1), ``u_cmd`` and ``u`` (commanded and applied input, N), ``f_ext`` (the external
            force, N), ``constraint_values`` (all rows ``g``, in option order), ``constraint_violation`` (any
            row violated).

            A non-finite action (NaN, or an infinite action where no saturation catches it) never gives a
            non-finite reward or cost: the state is kept (``nonfinite`` and ``terminated`` are true), the input
            term of ``c`` charges each non-finite entry of ``u`` as the admissible input farthest from
            ``u_ref`` (``max(|u_low - u_ref|, |u_high - u_ref|)`` per entry, the worst admissible cost), and a
            constraint row whose value is not finite counts as violated (``NaN <= 0`` is false), so ``cost``
            is 1 when the env has constraints.

        Raises:
            ValueError: at trace time, when ``action`` is not of shape (nu,) or ``adversary`` not of the
                adversary channel's shape, naming ``nu``; or when ``adversary`` is given to an env made without.
        """
        if adversary is not None and self.adversary_channel is None:
            raise ValueError(
                "adversary: this env was made without an adversary channel; pass "
                "adversary={'channel': ..., 'scale': ...} to make"
            )
        action = self._checked_action(action)
        # One draw per step, from fold_in(episode key, k), serves the action and dynamics disturbances of step k
        # and the observation noise of the state it reaches: PRNG calls dominate the cost of these small systems.
        noise = self._step_noise(jax.random.fold_in(state.key, state.step), params) if self.has_step_noise else {}
        extra = {channel: 0.0 for channel in disturbances_lib.CHANNELS}
        extra["observation"] = None
        if adversary is not None:
            extra[self.adversary_channel] = params.adversary_scale * jnp.clip(
                self._checked_adversary(adversary), -1.0, 1.0
            )

        u_cmd = self.action_to_input(action, params)
        u_low, u_high = self.input_bounds(state.physics)
        u_disturbed = u_cmd + self._disturb("action", state, params, noise, state.step) + extra["action"]
        u = jnp.clip(u_disturbed, u_low, u_high)
        f_ext = self._disturb("dynamics", state, params, noise, state.step) + extra["dynamics"]
        x_next = self.integrate(state.x, u, state.physics, f_ext)
        finite = jnp.all(jnp.isfinite(x_next))
        x_next = jnp.where(finite, x_next, state.x)
        step = state.step + 1

        x_ref, _ = self.reference_at(step, params)
        _, u_ref = self.reference_at(state.step, params)
        error = x_next - x_ref
        # A non-finite input entry is charged as the worst admissible one, so the reward stays finite and its
        # input term is never better than that of an admissible action.
        worst_du = jnp.maximum(jnp.abs(u_low - u_ref), jnp.abs(u_high - u_ref))
        du = jnp.where(jnp.isfinite(u), u - u_ref, worst_du)
        quadratic_cost = 0.5 * error @ params.Q @ error + 0.5 * du @ params.R @ du
        out_of_bounds = jnp.any((x_next < params.state_low) | (x_next > params.state_high))
        goal_reached = (
            jnp.linalg.norm(x_next - params.goal) < params.goal_tolerance
            if self.task == "stabilization"
            else jnp.zeros((), bool)
        )
        if self.constraint_specs:
            constraint_values = constraints_lib.evaluate_all(
                self.constraint_specs, params.constraints, x_next, u_cmd, jax_backend
            )
            rows = constraints_lib.violated(self.constraint_specs, params.constraints, constraint_values)
            # g <= 0 is satisfied; a NaN row (e.g. from a NaN action) is not, so it counts as violated.
            violation = jnp.any(rows | ~jnp.isfinite(constraint_values))
        else:
            constraint_values = jnp.zeros(0, x_next.dtype)
            violation = jnp.zeros((), bool)
        cost = violation.astype(x_next.dtype)

        terminated = ~finite
        if self.done_on_out_of_bounds:
            terminated = terminated | out_of_bounds
        if self.done_on_goal:
            terminated = terminated | goal_reached
        if self.done_on_violation:
            terminated = terminated | violation
        truncated = (step >= self.num_steps) & ~terminated

        if self.reward_type == "quadratic":
            reward = -quadratic_cost
        elif self.reward_type == "exponential":
            reward = jnp.exp(-quadratic_cost)
        else:
            reward = jnp.where(out_of_bounds, 0.0, 1.0).astype(x_next.dtype)
        reward = reward - params.violation_penalty * cost

        next_state = state.replace(x=x_next, step=step)
        info = {
            "mse": jnp.sum(params.mse_weight * error**2),
            "quadratic_cost": quadratic_cost,
            "out_of_bounds": out_of_bounds,
            "goal_reached": goal_reached,
            "nonfinite": ~finite,
            "step": step,
            "u_cmd": u_cmd,
            "u": u,
            "f_ext": f_ext,
            "constraint_values": constraint_values,
            "constraint_violation": violation,
        }
        return StepOutput(
            obs=self._noisy_observation(next_state, params, noise, adversary=extra["observation"]),
            state=next_state,
            reward=reward,
            cost=cost,
            terminated=terminated,
            truncated=truncated,
            info=info,
        )

    def _checked_action(self, action):
        """``action`` as an array of shape (nu,); shapes are static, so this check costs nothing inside ``jit``."""
        shape = np.shape(action)
        if shape != (self.nu,):
            raise ValueError(
                f"action: expected shape ({self.nu},) (nu = {self.nu}: {', '.join(self.system.input_names)} of "
                f"{self.system.name}), got shape {shape}; under jax.vmap this is the shape of one copy's action"
            )
        return jnp.asarray(action)

    def _checked_adversary(self, adversary):
        dim = self.channel_dim(self.adversary_channel)
        shape = np.shape(adversary)
        if shape != (dim,):
            raise ValueError(
                f"adversary: expected shape ({dim},) for the {self.adversary_channel!r} channel, got shape {shape}"
            )
        return jnp.asarray(adversary)

    # ----------------------------------------------------------------------------------------- symbolic
    def symbolic_model(self, params: EnvParams, discretization: str = "env"):
        """The CasADi mirror of this env for the (prior) parameters in ``params``; see ``scg_jax.symbolic``."""
        from scg_jax.symbolic import build_symbolic_model

        return build_symbolic_model(self, params, discretization)


def prior_params(env: Env, params: EnvParams, scale: float = 1.5, fields=None) -> EnvParams:
    """Params for a controller's prior model: the chosen physical parameters of ``params`` times ``scale``.

    Args:
        env: the environment. params: the true (nominal) ``EnvParams``. scale: factor, e.g. 1.5 for 150%.
        fields: names of ``params.physics`` fields to scale; default ``env.system.inertial_fields`` (cart-pole:
            cart mass, pole mass, pole half-length; quadrotors: mass and the moments of inertia in use).

    Returns:
        ``EnvParams`` equal to ``params`` except for the scaled physical parameters; pass it to
        ``env.symbolic_model`` so the model mismatch is explicit.
    """
    names = env.system.inertial_fields if fields is None else tuple(fields)
    allowed = [f.name for f in dataclasses.fields(params.physics)]
    for name in names:
        if name not in allowed:
            raise ValueError(
                f"fields: unknown parameter {name!r} of {env.system.name}; allowed are {', '.join(allowed)}"
            )
    if not (np.isfinite(scale) and scale > 0):
        raise ValueError(f"scale: must be a positive number, got {scale!r}")
    scaled = {name: getattr(params.physics, name) * scale for name in names}
    return params.replace(physics=params.physics.replace(**scaled))


def make(system, task: str = DEFAULT_TASK, **options) -> Env:
    """Build an environment.

    Args:
        system: ``"cartpole"``, ``"quadrotor_1d"``, ``"quadrotor_2d"`` or ``"quadrotor_3d"``; or a whole
            ``scg_jax.EnvConfig`` (then no other argument).
        task: ``"stabilization"`` or ``"tracking"``.
        **options:
            ctrl_freq (Hz, default 50), physics_freq (Hz, a multiple of ctrl_freq, default 1000),
            episode_len_sec (s, default 5; episode_len_sec * ctrl_freq must be an integer),
            integrator (``euler``, ``semi_implicit_euler``, ``rk4``; default rk4),
            action_mode (``physical`` (default) or ``normalized``), reward_type (``quadratic`` (default),
            ``exponential``, ``upright``), obs_goal_horizon (H >= 0 reference points appended to the
            observation), done_on_out_of_bounds (default True), done_on_goal (stabilization, default False),
            trajectory (tracking: dict with ``shape`` (circle, sinusoid, figure8, square; default circle),
            ``num_cycles`` (default 1), ``plane``, ``offset`` (2,), ``scale``; defaults per system),
            physics (dict of ``Params`` fields to override), Q (nx,) or (nx, nx), R (nu,) or (nu, nu),
            goal (nx,), goal_tolerance, mse_weight (nx,),
            init_state (a fixed (nx,) state or a distribution, see ``scg_jax.randomization``; default the
            system's uniform range), physics_randomization (``{field: distribution}``, drawn at every reset),
            constraints (list of constraint mappings, see ``scg_jax.constraints``), done_on_violation
            (default False), violation_penalty (>= 0, subtracted from the reward at a violating step),
            disturbances (``{channel: [disturbance mappings]}``, see ``scg_jax.disturbances``), adversary
            (``{"channel": action|observation|dynamics, "scale": number or (dim,)}``).

    The options are read into a typed ``EnvConfig`` (its fields are these options), which checks names, types and
    structure; ``make`` then checks what depends on the system and on several options together.

    Raises:
        scg_jax.validation.FieldError (a ValueError): ``"<option path>: <what is wrong>; <what is allowed>"``,
            e.g. ``ctrl_freq: expected an integer, got '50'`` or ``constraints[1].bound: must be >= 0, got -1``.
    """
    if isinstance(system, EnvConfig):
        if options or task != DEFAULT_TASK:
            raise TypeError("make: pass either an EnvConfig alone or a system name with options, not both")
        return _make(system)
    V.check_keys(options, "", _OPTION_DEFAULTS, what="option")
    return _make(EnvConfig.from_dict({"system": system, "task": task, **options}, ""))


def _make(cfg) -> Env:
    """``make`` of a checked ``EnvConfig``: the checks that need the system or several options; field paths are
    relative to the config's ``env`` section.

    Each part below checks its options and returns ``(static, values)``: fields of the ``Env`` (structure) and
    entries of its default ``EnvParams`` (numbers, as numpy).
    """
    spec = get_system(cfg.system)
    # The options the env keeps as they were given.
    given = ("integrator", "action_mode", "reward_type", "done_on_out_of_bounds", "done_on_goal", "done_on_violation")
    static = {"system": spec, "task": cfg.task, **_timing(cfg), "obs_goal_horizon": _task_options(cfg, spec)}
    static.update({name: getattr(cfg, name) for name in given})
    physics = _physics(cfg, spec)
    num_steps = round(static["episode_len_sec"] * static["ctrl_freq"])
    channel_dims = {"action": spec.nu, "observation": spec.nx, "dynamics": spec.f_ext_dim}
    values = {"physics": physics}
    for part_static, part_values in (
        _trajectory(cfg, spec),
        _randomization(cfg, spec),
        _constraints(cfg, spec, physics),
        _disturbances(cfg, channel_dims, num_steps),
        _adversary(cfg, channel_dims),
        ({}, _costs_and_goal(cfg, spec)),
    ):
        static.update(part_static)
        values.update(part_values)
    return Env(**static, _default_params_numpy=values)


def _timing(cfg) -> dict:
    """``ctrl_freq`` (Hz), ``physics_freq`` (Hz, a multiple of it) and ``episode_len_sec`` (s, whole control
    periods)."""
    ctrl_freq = V.integer(cfg.ctrl_freq, "ctrl_freq", minimum=1)
    physics_freq = V.integer(cfg.physics_freq, "physics_freq", minimum=1)
    if physics_freq % ctrl_freq:
        raise FieldError(
            "physics_freq",
            f"must be a multiple of ctrl_freq ({ctrl_freq} Hz), got {physics_freq} Hz; allowed values are "
            f"{ctrl_freq}, {2 * ctrl_freq}, {3 * ctrl_freq}, ...",
        )
    episode_len_sec = cfg.episode_len_sec
    steps = episode_len_sec * ctrl_freq
    if episode_len_sec <= 0 or not math.isclose(steps, round(steps), abs_tol=1e-9):
        raise FieldError(
            "episode_len_sec",
            f"must be positive and a whole number of control periods (1/{ctrl_freq} s), got {episode_len_sec!r}",
        )
    return {"ctrl_freq": ctrl_freq, "physics_freq": physics_freq, "episode_len_sec": episode_len_sec}


def _task_options(cfg, spec: System) -> int:
    """Check the options allowed only for some systems or tasks; return ``obs_goal_horizon`` (>= 0)."""
    if cfg.reward_type == "upright" and spec.name != "cartpole":
        raise FieldError(
            "reward_type", f"'upright' is only for cartpole; allowed values for {spec.name} are quadratic, exponential"
        )
    horizon = V.integer(cfg.obs_goal_horizon, "obs_goal_horizon", minimum=0)
    if cfg.done_on_goal and cfg.task != "stabilization":
        raise FieldError("done_on_goal", "only allowed with task 'stabilization'")
    return horizon


def _physics(cfg, spec: System):
    """The system's nominal ``Params`` with the ``physics`` overrides, checked."""
    overrides = dict(cfg.physics or {})
    V.check_keys(overrides, "physics", _physics_fields(spec), what="parameter", where=f"of {spec.name}")
    physics = spec.params_cls(**overrides)
    spec.validate_params(physics)
    return physics


def _physics_fields(spec: System) -> list[str]:
    return [f.name for f in dataclasses.fields(spec.params_cls)]


def _trajectory(cfg, spec: System) -> tuple[dict, dict]:
    """The trajectory's shape and plane, and its values; stabilization keeps the system's default values, unused,
    so that params have one structure per system."""
    if cfg.task != "tracking":
        if cfg.trajectory is not None:
            raise FieldError("trajectory", "only allowed with task 'tracking'")
        values = {"scale": spec.default_scale, "offset": np.asarray(spec.default_offset), "num_cycles": 1.0}
        return {"trajectory_shape": None, "trajectory_plane": None}, {"trajectory": values}
    given = cfg.trajectory

    def pick(name, default):  # a key left out of the trajectory section takes the system's default
        value = None if given is None else getattr(given, name)
        return default if value is None else value

    static = {"trajectory_shape": pick("shape", "circle"), "trajectory_plane": pick("plane", spec.default_plane)}
    values = {
        "scale": pick("scale", spec.default_scale),
        "offset": V.vector(pick("offset", spec.default_offset), "trajectory.offset", 2),
        "num_cycles": V.positive(pick("num_cycles", 1.0), "trajectory.num_cycles"),
    }
    return static, {"trajectory": values}


def _randomization(cfg, spec: System) -> tuple[dict, dict]:
    """The distributions of the initial state (default: the system's uniform range) and of the randomised physical
    parameters."""
    init = cfg.init_state
    if init is None:
        init = DistributionConfig(type="uniform", low=spec.init_low.tolist(), high=spec.init_high.tolist())
    init_spec, init_values = randomization.parse_distribution(
        "init_state", init, (spec.nx,), positive=False, allow_relative=False
    )
    randomized = cfg.physics_randomization or {}
    V.check_keys(randomized, "physics_randomization", _physics_fields(spec), what="parameter", where=f"of {spec.name}")
    physics_specs, physics_values = {}, {}
    for name, raw in randomized.items():
        physics_specs[name], physics_values[name] = randomization.parse_distribution(
            f"physics_randomization.{name}", raw, (), positive=True, allow_relative=True
        )
    static = {"init_state_spec": init_spec, "physics_randomization_specs": physics_specs}
    return static, {"init_state": init_values, "physics_randomization": physics_values}


def _constraints(cfg, spec: System, physics) -> tuple[dict, dict]:
    """The constraints in option order and the violation penalty."""
    state_bounds = (spec.state_low, spec.state_high)
    input_bounds = tuple(np.asarray(b, dtype=float) for b in spec.input_bounds(physics))
    parsed = [
        constraints_lib.parse_constraint(f"constraints[{i}]", c, spec, state_bounds, input_bounds)
        for i, c in enumerate(cfg.constraints or ())
    ]
    penalty = cfg.violation_penalty
    if not penalty >= 0:
        raise FieldError("violation_penalty", f"must be >= 0 (it is subtracted from the reward), got {penalty:g}")
    static = {"constraint_specs": tuple(p[0] for p in parsed)}
    return static, {"constraints": [p[1] for p in parsed], "violation_penalty": penalty}


def _disturbances(cfg, channel_dims: dict, num_steps: int) -> tuple[dict, dict]:
    """The disturbances of the channels that have any."""
    specs, values = {}, {}
    for channel, entries in (cfg.disturbances or {}).items():
        if not entries:
            continue
        items = [
            disturbances_lib.parse_disturbance(
                f"disturbances.{channel}[{i}]", d, channel, channel_dims[channel], num_steps
            )
            for i, d in enumerate(entries)
        ]
        specs[channel] = tuple(item[0] for item in items)
        values[channel] = [item[1] for item in items]
    return {"disturbance_specs": specs}, {"disturbances": values}


def _adversary(cfg, channel_dims: dict) -> tuple[dict, dict]:
    """The adversary input's channel and scale (dim,); no channel and an empty scale without an adversary."""
    if cfg.adversary is None:
        return {"adversary_channel": None}, {"adversary_scale": np.zeros(0)}
    channel = cfg.adversary.channel
    scale = 1.0 if cfg.adversary.scale is None else cfg.adversary.scale
    return {"adversary_channel": channel}, {
        "adversary_scale": V.vector(scale, "adversary.scale", channel_dims[channel], broadcast=True)
    }


def _costs_and_goal(cfg, spec: System) -> dict:
    """The cost weights, the goal and its tolerance, and the weights of the reported tracking error."""
    nx, nu = spec.nx, spec.nu
    return {
        "Q": V.weight_matrix(spec.q_diag if cfg.Q is None else cfg.Q, "Q", nx),
        "R": V.weight_matrix(spec.r_diag if cfg.R is None else cfg.R, "R", nu),
        "goal": V.vector(spec.goal if cfg.goal is None else cfg.goal, "goal", nx),
        "goal_tolerance": V.positive(cfg.goal_tolerance, "goal_tolerance"),
        "mse_weight": V.vector(spec.mse_weight if cfg.mse_weight is None else cfg.mse_weight, "mse_weight", nx),
    }
