"""The Gymnasium adapters: registration, check_env, seeding, episode ends, the extended reset info, the vector env
against the functional env (both autoreset modes), the safety six-tuple and rendering."""

import functools
import warnings

import gymnasium
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env
from gymnasium.vector import AutoresetMode

import scg_jax
from scg_jax.adapters import GYMNASIUM_IDS
from scg_jax.adapters.gymnasium import (
    SafetyGymnasiumVectorWrapper,
    SafetyGymnasiumWrapper,
    ScgGymEnv,
    ScgVectorEnv,
)
from scg_jax.rollout import initial_reset_keys, next_reset_key

IDS = tuple(GYMNASIUM_IDS.values())
N = 4  # copies in the vector tests (one compilation per batch size)
SHORT = {"episode_len_sec": 1}  # 50 control steps
# check_env warns about unbounded observation boxes; the observations are unbounded (see the module docstring).
ALLOWED_WARNINGS = ("infinity",)


def _check_env_quietly(env, **kwargs):
    """``check_env`` that fails on any warning but the unbounded-observation ones."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        check_env(env, **kwargs)
    unexpected = [str(w.message) for w in caught if not any(a in str(w.message) for a in ALLOWED_WARNINGS)]
    assert not unexpected, unexpected


@functools.cache
def _vmapped(env):
    """Jitted batched reset and step of the functional env, params as an argument (not the adapter's code); one
    compilation per env (the adapters share one ``Env`` per set of options)."""
    reset = jax.jit(jax.vmap(env.reset, in_axes=(0, None)))
    step = jax.jit(jax.vmap(env.step, in_axes=(0, 0, None)))
    next_key = jax.jit(jax.vmap(next_reset_key))
    return reset, step, next_key


# ============================================================================================== registration
@pytest.mark.parametrize("env_id", IDS)
def test_registered_ids(env_id):
    spec = gymnasium.spec(env_id)
    system = next(s for s, i in GYMNASIUM_IDS.items() if i == env_id)
    assert spec.kwargs == {"system": system}
    assert spec.entry_point == "scg_jax.adapters.gymnasium:ScgGymEnv"
    assert spec.vector_entry_point == "scg_jax.adapters.gymnasium:ScgVectorEnv"
    assert spec.max_episode_steps is None  # the env truncates itself: no TimeLimit wrapper
    env = gymnasium.make(env_id, **SHORT)
    assert isinstance(env.unwrapped, ScgGymEnv)
    assert not isinstance(env, gymnasium.wrappers.TimeLimit)
    assert env.unwrapped.functional_env.system.name == system
    assert env.unwrapped.functional_env.action_mode == "normalized"
    assert env.action_space == gymnasium.spaces.Box(-1.0, 1.0, (env.unwrapped.functional_env.nu,), np.float32)
    assert env.unwrapped.metadata["render_fps"] == 50


@pytest.mark.parametrize("env_id", IDS)
def test_check_env(env_id):
    """Gymnasium's ``check_env`` passes, and after it a seeded episode of zero actions (hover thrust, zero force) is
    the functional env's: the same end (step and flags) and the same return to 1e-5."""
    env = gymnasium.make(env_id, **SHORT)
    _check_env_quietly(env.unwrapped, skip_render_check=True)
    fenv, params = env.unwrapped.functional_env, env.unwrapped.params
    reset, step, _ = _vmapped(fenv)
    env.reset(seed=7)
    _, state = reset(jax.random.key(7)[None], params)
    returns, end = [0.0, 0.0], None
    for k in range(1, fenv.num_steps + 1):
        _, reward, terminated, truncated, _ = env.step(np.zeros(fenv.nu, np.float32))
        out = step(state, jnp.zeros((1, fenv.nu)), params)
        state = out.state
        returns[0] += float(reward)
        returns[1] += float(out.reward[0])
        assert (terminated, truncated) == (bool(out.terminated[0]), bool(out.truncated[0]))
        if terminated or truncated:
            end = k
            break
    assert end is not None and 0.0 < returns[0] <= end  # the exponential reward is in (0, 1] per step
    assert returns[0] == pytest.approx(returns[1], rel=1e-5)


def test_check_env_with_constraints_disturbances_randomization():
    env = gymnasium.make(
        "scg_jax/CartPole-v0",
        config="configs/cartpole_stabilization.yaml",
        overrides=["env.episode_len_sec=1"],
        action_mode="normalized",  # the config's is physical; a keyword overrides it
    )
    fenv = env.unwrapped.functional_env
    assert fenv.action_mode == "normalized"
    assert fenv.constraint_specs and fenv.disturbance_specs and fenv.physics_randomization_specs
    _check_env_quietly(env.unwrapped, skip_render_check=True)


def test_make_options_and_config():
    env = gymnasium.make(
        "scg_jax/Quadrotor2D-v0",
        task="tracking",
        trajectory={"shape": "figure8", "scale": 0.4, "offset": [0.1, 1.0]},
        obs_goal_horizon=2,
        **SHORT,
    )
    fenv = env.unwrapped.functional_env
    assert (fenv.task, fenv.trajectory_shape, fenv.num_steps) == ("tracking", "figure8", 50)
    obs, info = env.reset(seed=0)
    assert obs.shape == (18,) and env.observation_space.shape == (18,)
    x_ref, u_ref = fenv.reference(fenv.default_params)
    np.testing.assert_allclose(info["x_reference"], x_ref, atol=1e-5)  # float32 sin/cos, jit vs eager
    np.testing.assert_allclose(info["u_reference"], u_ref, atol=1e-7)
    np.testing.assert_allclose(obs[6:12], x_ref[1], atol=1e-5)  # the next reference point follows the state

    # A config decides every option, action_mode included (the shipped configs are physical); keywords override.
    env = gymnasium.make("scg_jax/CartPole-v0", config="configs/cartpole_stabilization.yaml", episode_len_sec=2)
    assert env.unwrapped.functional_env.num_steps == 100
    assert env.action_space == gymnasium.spaces.Box(-10.0, 10.0, (1,), np.float32)
    env = ScgGymEnv(config="configs/quadrotor_2d_tracking.yaml", overrides=["env.ctrl_freq=25"])
    assert (env.functional_env.system.name, env.functional_env.ctrl_freq) == ("quadrotor_2d", 25)
    env = ScgGymEnv("quadrotor_1d", action_mode="physical")
    low, high = env.functional_env.input_bounds(env.params.physics)
    np.testing.assert_allclose(env.action_space.low, low, rtol=1e-6)
    np.testing.assert_allclose(env.action_space.high, high, rtol=1e-6)

    with pytest.raises(ValueError, match="describes system 'quadrotor_2d'"):
        gymnasium.make("scg_jax/CartPole-v0", config="configs/quadrotor_2d_tracking.yaml")
    with pytest.raises(ValueError, match="env.ctrl_freq"):
        ScgGymEnv(config="configs/cartpole_stabilization.yaml", overrides=["env.ctrl_freq=-1"])
    with pytest.raises(ValueError, match="overrides: only allowed together with config"):
        ScgGymEnv("cartpole", overrides=["env.ctrl_freq=25"])
    with pytest.raises(ValueError, match="ctrl_fq: unknown option"):
        ScgGymEnv("cartpole", ctrl_fq=25)
    with pytest.raises(ValueError, match="render_mode"):
        ScgGymEnv("cartpole", render_mode="human")


# ============================================================================================== single env
def test_seeding_is_deterministic_and_matches_the_functional_env():
    options = {
        "disturbances": {"observation": [{"type": "white_noise", "std": 0.01}]},
        "physics_randomization": {"pole_mass": {"type": "uniform", "low": 0.05, "high": 0.2}},
        **SHORT,
    }
    env_a, env_b = ScgGymEnv("cartpole", **options), ScgGymEnv("cartpole", **options)
    actions = np.random.default_rng(0).uniform(-0.3, 0.3, (20, 1)).astype(np.float32)

    def run(env, seed):
        obs, info = env.reset(seed=seed)
        out = [obs]
        for a in actions:
            out.append(env.step(a)[0])
        return np.stack(out), info

    obs_a, info_a = run(env_a, 3)
    obs_b, info_b = run(env_b, 3)
    np.testing.assert_array_equal(obs_a, obs_b)
    assert info_a["physics"] == info_b["physics"]
    obs_c, info_c = run(env_a, 4)
    assert np.abs(obs_c - obs_a).min() > 0  # every entry differs (noise on every step)
    assert info_c["physics"]["pole_mass"] != info_a["physics"]["pole_mass"]

    # reset(seed=s) is env.reset(key(s)); reset() continues with auto_reset_step's key of the finished episode.
    fenv, params = env_a.functional_env, env_a.params
    obs, info = env_a.reset(seed=3)
    f_obs, f_state = fenv.reset(jax.random.key(3), params)  # eager: the same draws, rounding may differ in 1 ulp
    np.testing.assert_allclose(obs, np.asarray(f_obs), rtol=1e-6, atol=1e-7)
    np.testing.assert_array_equal(info["x0"], np.asarray(f_state.x))
    assert info["physics"]["pole_mass"] == float(f_state.physics.pole_mass)
    assert 0.05 <= info["physics"]["pole_mass"] <= 0.2
    obs, info = env_a.reset()
    f_obs, f_state = fenv.reset(next_reset_key(f_state.key), params)
    np.testing.assert_allclose(obs, np.asarray(f_obs), rtol=1e-6, atol=1e-7)
    out = fenv.step(f_state, jnp.asarray(actions[0]), params)
    np.testing.assert_allclose(env_a.step(actions[0])[0], np.asarray(out.obs), atol=1e-6)


def test_terminated_at_a_crash():
    env = ScgGymEnv("cartpole", episode_len_sec=2)
    env.reset(seed=0)
    push = np.ones(1, np.float32)  # normalized +1: F = +10 N
    crash_step = None
    for k in range(1, 101):
        obs, reward, terminated, truncated, info = env.step(push)
        if terminated or truncated:
            crash_step = k
            break
    assert terminated is True and truncated is False
    assert crash_step is not None and crash_step < 100  # before the time limit
    assert info["out_of_bounds"] and (abs(obs[0]) > 2.4 or abs(obs[2]) > np.pi / 2)
    assert info["u"][0] == pytest.approx(10.0) and info["step"] == crash_step

    # The same crash step in the functional env.
    fenv, params = env.functional_env, env.params
    _, state = fenv.reset(jax.random.key(0), params)
    step = jax.jit(fenv.step)
    functional_crash_step = None
    for j in range(1, 101):
        out = step(state, jnp.ones(1), params)
        state = out.state
        if out.terminated:
            functional_crash_step = j
            break
    assert functional_crash_step == crash_step


def test_truncated_exactly_at_the_time_limit():
    goal = [0.0, 0.0, 1.0, 0.0, 0.0, 0.0]
    env = gymnasium.make("scg_jax/Quadrotor2D-v0", init_state=goal, **SHORT)
    obs, _ = env.reset(seed=0)
    np.testing.assert_array_equal(obs, goal)
    num_steps = env.unwrapped.functional_env.num_steps
    for k in range(1, num_steps + 1):
        obs, reward, terminated, truncated, info = env.step(np.zeros(2, np.float32))  # hover
        assert terminated is False
        assert truncated is (k == num_steps)
        np.testing.assert_allclose(obs, goal, atol=1e-5)
        assert reward == pytest.approx(1.0, abs=1e-7)  # exp(-c) at c = 0: the default exponential reward
    assert info["step"] == num_steps == 50


@pytest.mark.parametrize("system", scg_jax.SYSTEMS)
def test_reset_info_symbolic_model_predicts_the_next_state(system):
    env = ScgGymEnv(system, **SHORT)
    obs, info = env.reset(seed=1)
    fenv = env.functional_env
    T, nx, nu = fenv.num_steps, fenv.nx, fenv.nu
    assert info["x_reference"].shape == (T + 1, nx) and info["u_reference"].shape == (T, nu)
    assert info["ctrl_timestep"] == pytest.approx(0.02) and info["ctrl_freq"] == 50
    assert info["episode_len_sec"] == 1.0
    assert set(info["physics"]) == {f for f in type(env.params.physics).__dataclass_fields__}
    assert info["physical_parameters"] == info["physics"]
    np.testing.assert_array_equal(info["x0"], obs)  # no observation noise, no goal horizon
    model = info["symbolic_model"]
    assert model is env.symbolic_model  # built once per set of options
    u_hover = info["u_reference"][0]
    next_obs, *_ = env.step(np.zeros(nu, np.float32))  # normalized 0 is the reference (hover) input
    predicted = np.asarray(model.fd(info["x0"].astype(float), u_hover)).ravel()
    np.testing.assert_allclose(next_obs, predicted, atol=1e-5)


def test_reset_info_constraints_and_step_info():
    constraints = [
        {"type": "abs_bound", "on": "state", "active_dims": [0], "bound": 0.01},
        {"type": "default", "on": "input"},
    ]
    env = ScgGymEnv("cartpole", constraints=constraints, **SHORT)
    obs, info = env.reset(seed=2)
    assert len(info["constraints"]) == 2 and info["symbolic_constraints"] == info["constraints"]
    fenv, params = env.functional_env, env.params
    _, f_state = fenv.reset(jax.random.key(2), params)
    action = np.array([0.5], np.float32)
    f_out = fenv.step(f_state, jnp.asarray(action), params)

    obs, reward, terminated, truncated, info_step = env.step(action)
    assert obs.dtype == np.float32 and obs.shape == env.observation_space.shape
    assert type(reward) is float and type(terminated) is bool and type(truncated) is bool
    assert {"constraint_values", "constraint_violation", "cost", "mse"} <= set(info_step)
    values = info_step["constraint_values"]
    assert isinstance(values, np.ndarray) and values.dtype == np.float32 and values.shape == (4,)  # 2 + 2 rows
    assert isinstance(info_step["constraint_violation"], np.bool_)
    assert isinstance(info_step["cost"], np.float32) and isinstance(info_step["mse"], np.float32)
    g = np.asarray(info["g"](obs.astype(float), info_step["u_cmd"].astype(float))).ravel()
    np.testing.assert_allclose(values, g, atol=1e-5)
    np.testing.assert_allclose(values, np.asarray(f_out.info["constraint_values"]), atol=1e-6)
    assert info_step["u_cmd"][0] == pytest.approx(5.0)
    assert info_step["mse"] == pytest.approx(float(f_out.info["mse"]), rel=1e-5)
    assert bool(info_step["constraint_violation"]) == bool(np.any(values > 0))
    assert float(info_step["cost"]) == float(info_step["constraint_violation"])
    assert reward == pytest.approx(float(f_out.reward), rel=1e-5)


def test_action_checks():
    env = ScgGymEnv("quadrotor_2d", **SHORT)
    with pytest.raises(gymnasium.error.ResetNeeded):
        env.step(np.zeros(2, np.float32))
    env.reset(seed=0)
    for bad in (np.zeros(1), np.zeros(3), np.zeros((1, 2)), 0.0):
        with pytest.raises(ValueError, match=r"action: expected shape \(2,\)"):
            env.step(bad)
    # Not clipped in the adapter: the plant saturates the input, and both are reported.
    _, _, _, _, info = env.step(np.array([50.0, -50.0], np.float32))
    low, high = env.functional_env.input_bounds(env.params.physics)
    np.testing.assert_allclose(info["u"], [high[0], low[1]], rtol=1e-6)
    assert info["u_cmd"][0] > high[0]
    with pytest.raises(ValueError, match="reset options"):
        env.reset(options={"x0": [0.0] * 6})


# ============================================================================================== vector env
@pytest.fixture(scope="session")
def vector_env_options():
    return {
        "disturbances": {"observation": [{"type": "white_noise", "std": 0.01}]},
        "physics_randomization": {"pole_half_length": {"type": "uniform", "low": 0.4, "high": 0.6}},
        "episode_len_sec": 0.1,  # 5 control steps: every copy truncates at step 5
    }


def test_make_vec_builds_the_vector_env():
    for kwargs in ({}, {"vectorization_mode": "vector_entry_point"}):
        envs = gymnasium.make_vec("scg_jax/CartPole-v0", num_envs=N, **kwargs, **SHORT)
        assert isinstance(envs, ScgVectorEnv) and envs.num_envs == N
        assert envs.metadata["autoreset_mode"] is AutoresetMode.NEXT_STEP
        assert envs.single_observation_space.shape == (4,) and envs.observation_space.shape == (N, 4)
        assert envs.single_action_space.shape == (1,) and envs.action_space.shape == (N, 1)
    envs = gymnasium.make_vec("scg_jax/CartPole-v0", num_envs=N, autoreset_mode="same_step", **SHORT)
    assert envs.metadata["autoreset_mode"] is AutoresetMode.SAME_STEP
    # The sync vectorizer also works with the single env (one process, one copy per env).
    sync = gymnasium.make_vec("scg_jax/CartPole-v0", num_envs=2, vectorization_mode="sync", **SHORT)
    obs, _ = sync.reset(seed=5)
    np.testing.assert_array_equal(obs[1], ScgGymEnv("cartpole", **SHORT).reset(seed=6)[0])  # seeds 5, 6
    envs.reset(seed=0)
    with pytest.raises(ValueError, match=r"actions: expected shape \(4, 1\)"):
        envs.step(np.zeros(N))
    with pytest.raises(ValueError, match="autoreset_mode"):
        ScgVectorEnv(N, "cartpole", autoreset_mode="eventually")


def test_vector_env_matches_the_functional_env(vector_env_options):
    n = N
    envs = ScgVectorEnv(n, "cartpole", **vector_env_options)
    fenv, params = envs.functional_env, envs.params
    reset, step, _ = _vmapped(fenv)
    obs, info = envs.reset(seed=7)
    f_obs, f_state = reset(initial_reset_keys(jax.random.key(7), n), params)
    np.testing.assert_allclose(obs, np.asarray(f_obs), rtol=1e-6, atol=1e-7)
    np.testing.assert_array_equal(info["x0"], np.asarray(f_state.x))
    lengths = info["physics"]["pole_half_length"]
    np.testing.assert_array_equal(lengths, np.asarray(f_state.physics.pole_half_length))
    assert len(np.unique(lengths)) == n and np.all((lengths >= 0.4) & (lengths <= 0.6))  # per-copy plants
    actions = np.random.default_rng(1).uniform(-0.2, 0.2, (4, n, 1)).astype(np.float32)
    for a in actions:  # 4 of the 5 steps of an episode
        obs, reward, terminated, truncated, info = envs.step(a)
        out = step(f_state, jnp.asarray(a), params)
        f_state = out.state
        np.testing.assert_allclose(obs, np.asarray(out.obs), atol=1e-6)
        np.testing.assert_allclose(reward, np.asarray(out.reward), rtol=1e-5, atol=1e-7)
        np.testing.assert_allclose(info["mse"], np.asarray(out.info["mse"]), rtol=1e-5, atol=1e-7)
        assert not terminated.any() and not truncated.any()
        assert obs.dtype == np.float32 and obs.shape == (n, 4) and info["cost"].shape == (n,)
    # Per-copy disturbances: the observation noise differs between copies (and from the true state).
    noise = obs - np.asarray(f_state.x)
    assert np.all(np.abs(noise) > 0) and len(np.unique(noise[:, 0])) == n


def test_vector_autoreset_next_step_and_same_step(vector_env_options):
    """Episodes of 5 steps: the final observation is kept and the new episode starts from auto_reset_step's key."""
    n = N
    next_env = ScgVectorEnv(n, "cartpole", **vector_env_options)
    same_env = ScgVectorEnv(n, "cartpole", autoreset_mode=AutoresetMode.SAME_STEP, **vector_env_options)
    fenv, params = next_env.functional_env, next_env.params
    reset, step, next_key = _vmapped(fenv)
    _, f_state = reset(initial_reset_keys(jax.random.key(0), n), params)
    next_env.reset(seed=0)
    same_env.reset(seed=0)
    a = np.zeros((n, 1), np.float32)
    for k in range(1, 6):
        out = step(f_state, jnp.asarray(a), params)
        f_state = out.state
        o_next, r_next, te_next, tr_next, i_next = next_env.step(a)
        o_same, r_same, te_same, tr_same, i_same = same_env.step(a)
        assert not te_next.any() and not te_same.any()
        assert tr_next.all() == tr_same.all() == (k == 5)
        np.testing.assert_allclose(r_next, r_same, rtol=1e-6)
        np.testing.assert_allclose(o_next, np.asarray(out.obs), atol=1e-6)
    # Step 5 ended every episode. NEXT_STEP returned the final observation as obs; SAME_STEP keeps it in info.
    final_obs = np.asarray(out.obs)
    np.testing.assert_allclose(i_same["final_obs"], final_obs, atol=1e-6)
    assert i_same["_final_obs"].all() and i_same["_final_info"].all()
    np.testing.assert_array_equal(i_same["final_info"]["step"], 5)
    fresh_obs, fresh_state = reset(next_key(f_state.key), params)
    np.testing.assert_allclose(o_same, np.asarray(fresh_obs), atol=1e-6)
    assert np.abs(o_same - final_obs).min() > 0
    # NEXT_STEP: the following step ignores the action and returns the reset observation with reward 0.
    o_next, r_next, te_next, tr_next, i_next = next_env.step(np.ones((n, 1), np.float32))
    np.testing.assert_allclose(o_next, np.asarray(fresh_obs), atol=1e-6)
    np.testing.assert_array_equal(r_next, 0.0)
    assert not te_next.any() and not tr_next.any()
    np.testing.assert_array_equal(i_next["step"], 0)
    np.testing.assert_array_equal(i_next["cost"], 0.0)
    # Both modes then continue the same new episodes.
    out = step(fresh_state, jnp.asarray(a), params)
    o_next = next_env.step(a)[0]
    o_same = same_env.step(a)[0]
    np.testing.assert_allclose(o_next, np.asarray(out.obs), atol=1e-6)
    np.testing.assert_allclose(o_same, np.asarray(out.obs), atol=1e-6)


def test_vector_autoreset_of_some_copies():
    """Copies 0 and 1 are pushed off the track; copies 2 and 3 stay and are never reset."""
    n = N
    envs = ScgVectorEnv(n, "cartpole", autoreset_mode="SAME_STEP", episode_len_sec=2)
    fenv, params = envs.functional_env, envs.params
    reset, step, _ = _vmapped(fenv)
    auto = jax.jit(jax.vmap(lambda s, a: scg_jax.auto_reset_step(fenv, s, a, params)))
    envs.reset(seed=3)
    _, f_state = reset(initial_reset_keys(jax.random.key(3), n), params)
    a = np.array([[1.0], [1.0], [0.0], [0.0]], np.float32)
    crashed = False
    for _ in range(60):
        obs, reward, terminated, truncated, info = envs.step(a)
        out = auto(f_state, jnp.asarray(a))
        f_state = out.state
        np.testing.assert_allclose(obs, np.asarray(out.obs), atol=1e-5)
        np.testing.assert_allclose(info["final_obs"], np.asarray(out.info["final_obs"]), atol=1e-5)
        np.testing.assert_array_equal(terminated, np.asarray(out.terminated))
        np.testing.assert_array_equal(info["_final_obs"], terminated | truncated)
        crashed |= bool(terminated[:2].all())
        assert not terminated[2:].any()
    assert crashed


def test_vector_disabled_autoreset_and_reset_mask(vector_env_options):
    n = N
    envs = ScgVectorEnv(n, "cartpole", autoreset_mode=AutoresetMode.DISABLED, **vector_env_options)
    fenv, params = envs.functional_env, envs.params
    reset, _, next_key = _vmapped(fenv)
    envs.reset(seed=1)
    for _ in range(5):
        obs, _, _, truncated, _ = envs.step(np.zeros((n, 1), np.float32))
    assert truncated.all()
    state_keys = envs.state.key
    mask = np.array([True, False, True, False])
    new_obs, info = envs.reset(options={"reset_mask": mask})
    fresh_obs, _ = reset(next_key(state_keys), params)
    np.testing.assert_allclose(new_obs[mask], np.asarray(fresh_obs)[mask], atol=1e-6)
    np.testing.assert_array_equal(new_obs[~mask], obs[~mask])
    np.testing.assert_array_equal(info["_x0"], mask)
    np.testing.assert_array_equal(np.asarray(envs.state.step), [0, 5, 0, 5])


# ============================================================================================== safety, render
def test_safety_wrapper_six_tuple():
    tight = [{"type": "abs_bound", "on": "input", "bound": 0.1}]  # hover is 0.1323 N per input
    env = SafetyGymnasiumWrapper(gymnasium.make("scg_jax/Quadrotor2D-v0", constraints=tight, **SHORT))
    env.reset(seed=0)
    result = env.step(np.zeros(2, np.float32))
    assert len(result) == 6
    obs, reward, cost, terminated, truncated, info = result
    assert cost == 1.0 and type(cost) is float and bool(info["constraint_violation"])
    np.testing.assert_allclose(info["constraint_values"], [0.1323 - 0.1] * 2 + [-0.1323 - 0.1] * 2, atol=1e-4)
    loose = [{"type": "abs_bound", "on": "input", "bound": 0.2}]
    env = SafetyGymnasiumWrapper(ScgGymEnv("quadrotor_2d", constraints=loose, **SHORT))
    env.reset(seed=0)
    assert env.step(np.zeros(2, np.float32))[2] == 0.0

    envs = SafetyGymnasiumWrapper(gymnasium.make_vec("scg_jax/Quadrotor2D-v0", num_envs=N, constraints=tight, **SHORT))
    assert isinstance(envs, SafetyGymnasiumVectorWrapper)
    envs.reset(seed=0)
    obs, reward, cost, terminated, truncated, info = envs.step(np.zeros((N, 2), np.float32))
    np.testing.assert_array_equal(cost, np.ones(N))
    assert obs.shape == (N, 6)


@pytest.mark.parametrize("env_id", IDS)
def test_render_rgb_array(env_id):
    env = gymnasium.make(env_id, render_mode="rgb_array", **SHORT)
    env.reset(seed=0)
    frame = env.render()
    assert frame.shape == (480, 480, 3) and frame.dtype == np.uint8
    assert frame.std() > 0
    for _ in range(20):
        env.step(env.action_space.high)
    assert np.any(env.render() != frame)  # the scene follows the state
    small = ScgGymEnv(
        env.unwrapped.functional_env.system.name, render_mode="rgb_array", render_width=160, render_height=120, **SHORT
    )
    small.reset(seed=0)
    assert small.render().shape == (120, 160, 3)
    with pytest.warns(UserWarning, match="without a render_mode"):
        assert ScgGymEnv("cartpole", **SHORT).render() is None


def test_check_env_with_rendering():
    """The whole check_env, render checks included, on a tracking task (the reference is drawn too)."""
    env = gymnasium.make("scg_jax/Quadrotor2D-v0", render_mode="rgb_array", task="tracking", **SHORT)
    _check_env_quietly(env.unwrapped)
    envs = gymnasium.make_vec("scg_jax/CartPole-v0", num_envs=N, render_mode="rgb_array", **SHORT)
    envs.reset(seed=0)
    frames = envs.render()
    assert len(frames) == N and all(frame.shape == (480, 480, 3) for frame in frames)
    assert not np.array_equal(frames[0], frames[1])  # each copy is drawn in its own state


@pytest.mark.parametrize("env_id", IDS)
def test_ids_default_to_a_positive_reward_so_ending_early_costs_return(env_id):
    env = gymnasium.make(env_id, **SHORT)
    fenv = env.unwrapped.functional_env
    assert fenv.reward_type == "exponential" and fenv.done_on_out_of_bounds
    env.reset(seed=0)
    _, reward, *_ = env.step(np.zeros(fenv.nu, np.float32))
    assert 0.0 < reward <= 1.0
    quadratic = gymnasium.make(env_id, reward_type="quadratic", **SHORT)
    assert quadratic.unwrapped.functional_env.reward_type == "quadratic"  # a keyword overrides the default


def test_a_config_decides_the_reward_type_itself():
    env = gymnasium.make(
        "scg_jax/CartPole-v0", config="configs/cartpole_stabilization.yaml", overrides=["env.reward_type=quadratic"]
    )
    assert env.unwrapped.functional_env.reward_type == "quadratic"  # not the adapters' exponential default
