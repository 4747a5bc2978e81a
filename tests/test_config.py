"""Configuration files: typed loading, overrides, dotted-path errors, YAML round trips and ``make_from_config``."""

import dataclasses
import importlib
import inspect
import io
import math
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import yaml

import scg_jax
from scg_algorithms import CONTROLLERS
from scg_algorithms.base import parse_options
from scg_algorithms.rl.policy import algorithm_module
from scg_algorithms.safety_filters import FILTERS
from scg_jax import constraints as constraints_lib
from scg_jax import disturbances as disturbances_lib
from scg_jax import randomization
from scg_jax.config import (
    SAFETY_FILTER_NAMES,
    Config,
    ConfigError,
    EnvConfig,
    dump_config,
    load_config,
    make_from_config,
)
from scg_jax.constraints import ConstraintSpec
from scg_jax.disturbances import DisturbanceSpec
from scg_jax.env import TRAJECTORY_KEYS
from scg_jax.env_config import (
    _OPTION_DEFAULTS,
    TASKS,
    AdversaryConfig,
    ConstraintConfig,
    DistributionConfig,
    DisturbanceConfig,
    TrajectoryConfig,
)
from scg_jax.randomization import DistributionSpec

CONFIG_DIR = Path(__file__).resolve().parents[1] / "configs"
CONFIG_FILES = sorted(CONFIG_DIR.glob("*.yaml"))
CONFIG_IDS = [path.stem for path in CONFIG_FILES]


def _cartpole(**env):
    return {"env": {"system": "cartpole", **env}}


def _tracking(**env):
    return {"env": {"system": "cartpole", "task": "tracking", **env}}


# --------------------------------------------------------------------------------------------- the files
def test_configs_cover_every_system_and_task_and_the_paper_settings():
    names = {path.name for path in CONFIG_FILES}
    expected = {f"{system}_{task}.yaml" for system in scg_jax.SYSTEMS for task in TASKS}
    expected |= {"paper_cartpole_lqr_mpc.yaml", "paper_quadrotor_2d.yaml"}
    assert expected <= names


@pytest.mark.parametrize("path", CONFIG_FILES, ids=CONFIG_IDS)
def test_config_file_makes_the_env_it_describes_and_steps(path):
    cfg = load_config(path)
    env, params = make_from_config(cfg)
    e = cfg.env

    assert (env.system.name, env.task) == (e.system, e.task)
    assert (env.ctrl_freq, env.physics_freq, env.episode_len_sec) == (e.ctrl_freq, e.physics_freq, e.episode_len_sec)
    assert env.num_steps == round(e.episode_len_sec * e.ctrl_freq)
    assert env.substeps * e.ctrl_freq == e.physics_freq
    assert (env.integrator, env.action_mode, env.reward_type) == (e.integrator, e.action_mode, e.reward_type)
    assert env.observation_size == env.nx * (1 + e.obs_goal_horizon)
    if e.Q is not None:
        np.testing.assert_allclose(np.asarray(params.Q), np.diag(e.Q), rtol=1e-6)
    if e.R is not None:
        np.testing.assert_allclose(np.asarray(params.R), np.diag(e.R), rtol=1e-6)
    if e.goal is not None:
        np.testing.assert_allclose(np.asarray(params.goal), e.goal, rtol=1e-6)
    if e.task == "tracking":
        assert env.trajectory_shape == e.trajectory.shape and env.trajectory_plane == e.trajectory.plane
        np.testing.assert_allclose(float(params.trajectory.scale), e.trajectory.scale, rtol=1e-6)
        np.testing.assert_allclose(np.asarray(params.trajectory.offset), e.trajectory.offset, rtol=1e-6)
    assert isinstance(e.init_state, DistributionConfig) and e.init_state.type == "uniform"
    np.testing.assert_allclose(np.asarray(params.init_state.low), e.init_state.low, rtol=1e-6)
    np.testing.assert_allclose(np.asarray(params.init_state.high), e.init_state.high, rtol=1e-6)
    assert [(s.type, s.on) for s in env.constraint_specs] == [(c.type, c.on) for c in e.constraints]
    assert set(env.physics_randomization_specs) == set(e.physics_randomization or {})
    assert {ch: [s.type for s in specs] for ch, specs in env.disturbance_specs.items()} == {
        ch: [d.type for d in entries] for ch, entries in (e.disturbances or {}).items()
    }

    obs0, state = env.reset(jax.random.key(0), params)
    assert np.all(np.asarray(state.x) >= np.asarray(params.init_state.low) - 1e-7)
    assert np.all(np.asarray(state.x) <= np.asarray(params.init_state.high) + 1e-7)
    u_eq = jnp.asarray(env.system.equilibrium_input(params.physics), dtype=obs0.dtype)
    out = env.step(state, u_eq, params)
    assert obs0.shape == out.obs.shape == (env.observation_size,)
    assert int(out.state.step) == 1 and np.all(np.isfinite(np.asarray(out.obs)))
    assert out.info["constraint_values"].shape == (sum(s.num_rows for s in env.constraint_specs),)
    np.testing.assert_allclose(np.asarray(out.info["u"]), np.asarray(u_eq), rtol=1e-6)  # hover is within limits
    assert float(out.cost) in (0.0, 1.0)
    c = float(out.info["quadratic_cost"])
    shaped = {"quadratic": -c, "exponential": math.exp(-c)}[env.reward_type]
    assert float(out.reward) == pytest.approx(shaped - float(params.violation_penalty) * float(out.cost), rel=1e-6)


@pytest.mark.parametrize("path", CONFIG_FILES, ids=CONFIG_IDS)
def test_config_file_round_trips_through_yaml(path, tmp_path):
    cfg = load_config(path)
    text = dump_config(cfg)
    assert load_config(text) == cfg
    assert load_config(io.StringIO(text)) == cfg
    assert dump_config(load_config(text)) == text
    assert yaml.safe_load(text) == cfg.to_dict()  # plain YAML any reader understands
    dump_config(cfg, tmp_path / "out.yaml")
    assert load_config(tmp_path / "out.yaml") == cfg
    assert load_config(str(tmp_path / "out.yaml")) == cfg


def test_paper_settings():
    env, _ = make_from_config(load_config(CONFIG_DIR / "paper_cartpole_lqr_mpc.yaml"))
    assert (env.system.name, env.task, env.ctrl_freq, env.physics_freq) == ("cartpole", "stabilization", 15, 750)
    assert env.dt == pytest.approx(1 / 15) and env.substeps == 50 and env.num_steps == 90
    env, params = make_from_config(load_config(CONFIG_DIR / "paper_quadrotor_2d.yaml"))
    assert (env.system.name, env.task, env.ctrl_freq, env.physics_freq) == ("quadrotor_2d", "tracking", 50, 1000)
    assert env.dt == pytest.approx(1 / 50) and env.substeps == 20 and env.num_steps == 300
    assert env.trajectory_shape == "figure8" and float(params.trajectory.scale) == pytest.approx(0.75)


# --------------------------------------------------------------------------------------------- defaults
def test_env_config_fields_and_defaults_are_makes():
    assert EnvConfig.option_names() == tuple(_OPTION_DEFAULTS)
    fields = {f.name: f for f in dataclasses.fields(EnvConfig)}
    for name, default in _OPTION_DEFAULTS.items():
        assert fields[name].default == default, name
    assert fields["task"].default == inspect.signature(scg_jax.make).parameters["task"].default
    assert fields["system"].default is dataclasses.MISSING


def test_section_keys_are_the_keys_make_accepts():
    assert set(TrajectoryConfig.keys()) == set(TRAJECTORY_KEYS)
    assert set(ConstraintConfig.keys()) == set(constraints_lib._COMMON_KEYS).union(*constraints_lib._KEYS.values())
    assert set(DisturbanceConfig.keys()) == {"type", "mask"}.union(*disturbances_lib._KEYS.values())
    assert set(DistributionConfig.keys()) == {"type", "relative"}.union(*randomization._KEYS.values())
    assert set(AdversaryConfig.keys()) == {"channel", "scale"}
    assert Config.keys() == ("env", "controllers", "training", "safety_filters", "devices")


@pytest.mark.parametrize("system", tuple(scg_jax.SYSTEMS))
def test_minimal_config_gives_makes_default_env(system):
    cfg = load_config({"env": {"system": system}})
    assert cfg.env.make_options() == {k: v for k, v in _OPTION_DEFAULTS.items() if v is not None}
    env, params = make_from_config(cfg)
    reference = scg_jax.make(system)
    for name in ("task", "ctrl_freq", "physics_freq", "episode_len_sec", "integrator", "action_mode"):
        assert getattr(env, name) == getattr(reference, name)
    leaves = jax.tree.leaves(jax.tree.map(lambda a, b: bool(jnp.array_equal(a, b)), params, reference.default_params))
    assert leaves and all(leaves)


def test_dump_leaves_out_none_and_is_plain_data():
    cfg = load_config(_cartpole(ctrl_freq=25, physics_freq=500))
    data = cfg.to_dict()
    assert set(data) == {"env"}
    assert "Q" not in data["env"] and "trajectory" not in data["env"]
    assert data["env"]["ctrl_freq"] == 25 and data["env"]["task"] == "stabilization"
    assert yaml.safe_load(yaml.safe_dump(data)) == data


# --------------------------------------------------------------------------------------------- overrides
def test_overrides_change_the_env():
    base = CONFIG_DIR / "cartpole_stabilization.yaml"
    cfg = load_config(base, overrides=["env.ctrl_freq=15", "env.physics_freq=750"])
    env, _ = make_from_config(cfg)
    assert env.dt == 1 / 15 and env.num_steps == round(5.0 * 15) == 75 and env.substeps == 50
    assert load_config(base).env.ctrl_freq == 50  # the file is unchanged

    with pytest.raises(ConfigError) as err:  # 1000 Hz is not a multiple of 15 Hz: make says so, with the path
        make_from_config(load_config(base, overrides=["env.ctrl_freq=15"]))
    assert err.value.path == "env.physics_freq"
    assert "allowed values are 15, 30, 45" in str(err.value)

    cfg = load_config(CONFIG_DIR / "cartpole_tracking.yaml", overrides=["env.trajectory.shape=figure8"])
    env, params = make_from_config(cfg)
    assert env.trajectory_shape == "figure8" and float(params.trajectory.scale) == 1.0  # other keys kept

    cfg = load_config(base, overrides=["env.disturbances.action=[{type: white_noise, std: 0.1}]"])
    env, params = make_from_config(cfg)
    assert env.disturbance_specs["action"] == (DisturbanceSpec("white_noise", "action", 1, False),)
    np.testing.assert_allclose(np.asarray(params.disturbances["action"][0].std), [0.1], rtol=1e-6)
    assert env.disturbance_specs["observation"][0].type == "white_noise"  # the file's channel is kept

    cfg = load_config(base, overrides=["env.physics.pole_mass=0.2", "env.violation_penalty=1e-3"])
    env, params = make_from_config(cfg)
    assert float(params.physics.pole_mass) == pytest.approx(0.2) and float(params.physics.cart_mass) == 1.0
    assert cfg.env.violation_penalty == 0.001  # YAML 1.2 numbers: 1e-3 is a float


def test_override_into_a_list_entry():
    source = _cartpole(constraints=[{"type": "abs_bound", "on": "input", "bound": 2.0}, {"type": "default"}])
    cfg = load_config(source, overrides=["env.constraints[0].bound=0.5"])
    assert cfg.env.constraints[0] == ConstraintConfig(type="abs_bound", on="input", bound=0.5)
    _, params = make_from_config(cfg)
    np.testing.assert_allclose(np.asarray(params.constraints[0].A), [[1.0], [-1.0]])
    np.testing.assert_allclose(np.asarray(params.constraints[0].b), [0.5, 0.5])
    assert source["env"]["constraints"][0]["bound"] == 2.0  # the caller's mapping is not modified


def test_overrides_apply_in_order_and_null_restores_the_default():
    cfg = load_config(CONFIG_DIR / "cartpole_stabilization.yaml", ["env.ctrl_freq=25", "env.ctrl_freq=10", "env.Q="])
    assert cfg.env.ctrl_freq == 10 and cfg.env.Q is None
    again = load_config(cfg, overrides=["env.ctrl_freq=20"])  # a Config is a valid source
    assert again.env.ctrl_freq == 20 and dataclasses.replace(again.env, ctrl_freq=10) == cfg.env


# --------------------------------------------------------------------------------------------- errors
def _error(source, overrides=(), stage="load"):
    with pytest.raises(ConfigError) as err:
        cfg = load_config(source, overrides)
        assert stage == "make", f"load_config accepted it: {cfg}"
        make_from_config(cfg)
    return err.value


UNKNOWN_KEYS = [
    (
        {**_cartpole(), "controller": {}},
        "controller",
        ["controller: unknown key; allowed keys are env"],
    ),
    (
        _cartpole(trajctory={"shape": "circle"}),
        "env.trajctory",
        ["unknown key; allowed keys are system, task, ctrl_freq, physics_freq", "did you mean 'trajectory'"],
    ),
    (
        _tracking(trajectory={"speed": 2}),
        "env.trajectory.speed",
        ["unknown key; allowed keys are shape, num_cycles, plane, offset, scale"],
    ),
    (
        _cartpole(constraints=[{"type": "default"}, {"type": "abs_bound", "bond": 1.0}]),
        "env.constraints[1].bond",
        [
            "unknown key for a abs_bound constraint; allowed keys are type, on, active_dims, strict, tolerance, bound "
            "(did you mean 'bound'?)"
        ],
    ),
    (
        _cartpole(disturbances={"action": [{"type": "white_noise", "sdt": 0.1}]}),
        "env.disturbances.action[0].sdt",
        ["unknown key for a white_noise disturbance; allowed keys are type, mask, std (did you mean 'std'?)"],
    ),
    (
        _cartpole(disturbances={"wind": []}),
        "env.disturbances.wind",
        ["unknown key; allowed keys are action, observation, dynamics"],
    ),
    (
        _cartpole(physics_randomization={"pole_mass": {"type": "uniform", "lo": 0.9, "high": 1.1}}),
        "env.physics_randomization.pole_mass.lo",
        ["unknown key for a uniform distribution; allowed keys are type, relative, low, high (did you mean 'low'?)"],
    ),
    (_cartpole(adversary={"chanel": "action"}), "env.adversary.chanel", ["allowed keys are channel, scale"]),
]

WRONG_TYPES = [
    (_cartpole(ctrl_freq="fast"), "env.ctrl_freq", ["env.ctrl_freq: expected an integer, got 'fast'"]),
    (_cartpole(ctrl_freq=15.5), "env.ctrl_freq", ["expected an integer, got 15.5"]),
    (_cartpole(done_on_goal="yes"), "env.done_on_goal", ["expected true or false, got 'yes'"]),
    (_cartpole(constraints={"type": "default"}), "env.constraints", ["expected a list of constraint mappings"]),
    (
        _cartpole(disturbances={"action": [{"type": "white_noise", "std": "big"}]}),
        "env.disturbances.action[0].std",
        ["expected a number or a list of numbers, got 'big'"],
    ),
    (_cartpole(goal=[0, 0, "a", 0]), "env.goal[2]", ["expected a finite number, got 'a'"]),
    (_cartpole(physics={"pole_mass": "heavy"}), "env.physics.pole_mass", ["expected a finite number, got 'heavy'"]),
    (
        _cartpole(init_state="random"),
        "env.init_state",
        ["expected a distribution (a mapping with type: uniform, normal, choice), a number or a list of numbers"],
    ),
    ({"env": ["cartpole"]}, "env", ["expected a mapping with keys system, task, ctrl_freq"]),
    (
        _cartpole(constraints=[{"type": "bounded", "active_dims": [0, 1.5], "low": [0, 0], "high": [1, 1]}]),
        "env.constraints[0].active_dims[1]",
        ["expected an integer, got 1.5"],
    ),
    (
        _cartpole(constraints=[{"type": "default", "on": 1}]),
        "env.constraints[0].on",
        ["expected one of state, input, input_and_state, got 1"],
    ),
]

WRONG_SHAPES = [
    (
        _tracking(trajectory={"offset": [0.0, 1.0, 2.0]}),
        "env.trajectory.offset",
        ["expected 2 values, got 3: [0.0, 1.0, 2.0]"],
    ),
    (
        _cartpole(Q=[[1.0, 0.0], [0.0]]),
        "env.Q",
        ["expected a matrix (a list of equal-length lists of numbers), got rows of lengths [1, 2]"],
    ),
    (
        _cartpole(constraints=[{"type": "linear", "A": [1.0, 0.0], "b": [1.0]}]),
        "env.constraints[0].A",
        ["expected a matrix (a list of equal-length lists of numbers)"],
    ),
]

MISSING_AND_INVALID = [
    ({"env": {"task": "tracking"}}, "env.system", ["required; allowed values are cartpole, quadrotor_1d"]),
    ({}, "env", ["required"]),
    (
        _cartpole(system="pendulum"),
        "env.system",
        ["unknown value 'pendulum'; allowed values are cartpole, quadrotor_1d, quadrotor_2d, quadrotor_3d"],
    ),
    (
        _cartpole(constraints=[{"type": "box"}]),
        "env.constraints[0].type",
        ["unknown value 'box'; allowed values are bounded, abs_bound, linear, quadratic, default"],
    ),
    (
        _tracking(trajectory={"shape": "spiral"}),
        "env.trajectory.shape",
        ["unknown value 'spiral'; allowed values are circle, sinusoid, figure8, square"],
    ),
    (
        _cartpole(disturbances={"action": [{"type": "gust"}]}),
        "env.disturbances.action[0].type",
        ["unknown value 'gust'; allowed values are white_noise, uniform, step, impulse, periodic"],
    ),
    (_cartpole(integrator="midpoint"), "env.integrator", ["allowed values are euler, semi_implicit_euler, rk4"]),
    (
        _cartpole(constraints=[{"type": "quadratic", "P": [[1.0]], "active_dims": [0]}]),
        "env.constraints[0].b",
        ["required for a quadratic constraint"],
    ),
    (
        _cartpole(disturbances={"dynamics": [{"type": "step", "magnitude": 1.0, "start_step": "random"}]}),
        "env.disturbances.dynamics[0].start_step",
        ["'random' is only allowed for an impulse disturbance"],
    ),
    (_cartpole(adversary={"channel": "wind"}), "env.adversary.channel", ["allowed values are action, observation"]),
]

# Valid types and shapes, invalid values: ``make`` rejects them and ``make_from_config`` adds ``env.``.
MAKE_ERRORS = [
    (_cartpole(goal=[0.0, 0.0, 0.0]), "env.goal", ["expected 4 values, got 3: [0.0, 0.0, 0.0]"]),
    (
        _cartpole(disturbances={"observation": [{"type": "white_noise", "std": [0.1, 0.1]}]}),
        "env.disturbances.observation[0].std",
        ["expected a number or 4 values, got 2: [0.1, 0.1]"],
    ),
    (
        _cartpole(constraints=[{"type": "default", "active_dims": [7]}]),
        "env.constraints[0].active_dims",
        ["expected distinct integers in [0, 4)"],
    ),
    (
        _cartpole(constraints=[{"type": "bounded", "low": [0.0] * 4, "high": [1.0] * 4, "bound": 1.0}]),
        "env.constraints[0].bound",
        ["unknown key for a bounded constraint; allowed keys are type, on, active_dims, strict, tolerance, low, high"],
    ),
    (
        _cartpole(physics={"pole_length": 1.0}),
        "env.physics.pole_length",
        [
            "unknown parameter of cartpole; allowed parameters are cart_mass, pole_mass, pole_half_length, gravity, "
            "force_max (did you mean 'pole_half_length'?)"
        ],
    ),
    (_cartpole(physics={"cart_mass": -1.0}), "env.physics.cart_mass", ["must be a positive finite number"]),
    (
        _cartpole(ctrl_freq=15),
        "env.physics_freq",
        ["must be a multiple of ctrl_freq (15 Hz), got 1000 Hz; allowed values are 15, 30, 45"],
    ),
    (_cartpole(trajectory={"shape": "circle"}), "env.trajectory", ["only allowed with task 'tracking'"]),
    (_tracking(trajectory={"plane": "xx"}), "env.trajectory.plane", ["allowed values are two distinct letters"]),
    (
        _cartpole(physics_randomization={"pole_mass": {"type": "uniform", "low": 0.0, "high": 1.1, "relative": True}}),
        "env.physics_randomization.pole_mass.low",
        ["must be positive"],
    ),
    (
        _cartpole(disturbances={"action": [{"type": "impulse", "magnitude": 1.0, "duration": 0}]}),
        "env.disturbances.action[0].duration",
        ["expected an integer number of steps in [1, 250]"],
    ),
    (
        {"env": {"system": "quadrotor_2d", "reward_type": "upright"}},
        "env.reward_type",
        ["'upright' is only for cartpole; allowed values for quadrotor_2d are quadratic, exponential"],
    ),
]


@pytest.mark.parametrize(("source", "path", "parts"), UNKNOWN_KEYS + WRONG_TYPES + WRONG_SHAPES + MISSING_AND_INVALID)
def test_load_errors_name_the_dotted_path_and_what_is_allowed(source, path, parts):
    err = _error(source)
    assert err.path == path
    assert str(err).startswith(f"{path}: ")
    for part in parts:
        assert part in str(err)


@pytest.mark.parametrize(("source", "path", "parts"), MAKE_ERRORS)
def test_make_errors_carry_the_env_prefix(source, path, parts):
    err = _error(source, stage="make")
    assert err.path == path
    assert str(err).startswith(f"{path}: ")
    for part in parts:
        assert part in str(err)


OVERRIDE_ERRORS = [
    (
        ["env.ctrl_frq=15"],
        "env.ctrl_frq",
        ["unknown key; allowed keys are system, task, ctrl_freq", "(set by override 'env.ctrl_frq=15')"],
    ),
    (
        ["env.trajectory.shap=circle"],
        "env.trajectory.shap",
        ["unknown key; allowed keys are shape, num_cycles, plane, offset, scale"],
    ),
    (["env.ctrl_freq=fast"], "env.ctrl_freq", ["expected an integer, got 'fast'", "override 'env.ctrl_freq=fast'"]),
    (
        ["env.disturbances.action=[{type: white_nois}]"],
        "env.disturbances.action[0].type",
        ["unknown value 'white_nois'; allowed values are white_noise"],
    ),
    (["env.ctrl_freq"], "", ["override 'env.ctrl_freq': expected dotted.key=value, e.g. env.ctrl_freq=15"]),
    (["env..ctrl_freq=15"], "", ["override 'env..ctrl_freq=15': malformed key 'env..ctrl_freq'"]),
    (["env.constraints[x]=1"], "", ["malformed key 'env.constraints[x]'"]),
    (
        ["env.constraints[3].bound=1"],
        "env.constraints[3]",
        ["index out of range; the list has 2 entries (override 'env.constraints[3].bound=1')"],
    ),
    (["env.ctrl_freq.hz=1"], "env.ctrl_freq", ["is 50, not a mapping, so 'hz' cannot be set in it"]),
    (["env.ctrl_freq=[1"], "", ["override 'env.ctrl_freq=[1': invalid YAML"]),
]


@pytest.mark.parametrize(("overrides", "path", "parts"), OVERRIDE_ERRORS)
def test_override_errors(overrides, path, parts):
    err = _error(CONFIG_DIR / "cartpole_tracking.yaml", overrides)
    assert err.path == path
    for part in parts:
        assert part in str(err)


def test_overrides_must_be_a_list_not_a_string():
    with pytest.raises(TypeError, match="overrides: expected a list"):
        load_config(_cartpole(), "env.ctrl_freq=15")


def test_file_errors_name_the_file(tmp_path):
    path = tmp_path / "bad.yaml"
    path.write_text("env:\n  system: cartpole\n  ctrl_freq: fast\n")
    err = _error(path)
    assert err.path == "env.ctrl_freq" and f"(in {path})" in str(err)
    path.write_text("env:\n  system: cartpole\n  ctrl_freq: 15\n  ctrl_freq: 25\n")
    err = _error(path)
    assert "invalid YAML" in str(err) and "duplicate key 'ctrl_freq'" in str(err) and str(path) in str(err)


def test_yaml_12_scalars():
    text = (
        "env:\n  system: cartpole\n  violation_penalty: 1e-3\n  constraints:\n"
        "    - type: default\n      on: input\n    - {type: bounded, on: state, active_dims: [0],"
        " low: [-.inf], high: [2.0]}\n"
    )
    cfg = load_config(text)
    assert cfg.env.violation_penalty == 0.001
    assert cfg.env.constraints[0].on == "input" and cfg.env.constraints[1].low == (-np.inf,)
    env, params = make_from_config(cfg)
    assert env.constraint_specs[1].num_rows == 1  # the infinite bound gives no row
    np.testing.assert_allclose(np.asarray(params.constraints[1].b), [2.0])
    # A YAML 1.1 reader (plain yaml.safe_load) turns the key ``on`` into True; that is understood too.
    assert load_config(yaml.safe_load(text)) == cfg
    assert load_config(cfg.to_dict()) == cfg


# --------------------------------------------------------------------------------------------- dataclasses
def test_direct_construction_is_checked_and_normalised():
    with pytest.raises(ConfigError, match=r"^env\.ctrl_freq: expected an integer, got 'fast'"):
        EnvConfig(system="cartpole", ctrl_freq="fast")
    with pytest.raises(ConfigError, match=r"^trajectory\.offset: expected 2 values, got 3: \[0.0, 1.0, 2.0\]$"):
        TrajectoryConfig(offset=[0.0, 1.0, 2.0])
    built = EnvConfig(
        system="cartpole",
        Q=np.ones(4),
        constraints=[{"type": "default", "on": "input"}],
        physics_randomization={"pole_mass": {"type": "uniform", "low": 0.9, "high": 1.1, "relative": True}},
    )
    loaded = load_config(
        _cartpole(
            Q=[1, 1, 1, 1],
            constraints=[{"type": "default", "on": "input"}],
            physics_randomization={"pole_mass": {"type": "uniform", "low": 0.9, "high": 1.1, "relative": True}},
        )
    ).env
    assert built == loaded and built.Q == (1.0, 1.0, 1.0, 1.0)
    assert built.constraints == (ConstraintConfig(type="default", on="input"),)
    with pytest.raises(dataclasses.FrozenInstanceError):
        built.ctrl_freq = 10
    env, _ = make_from_config(built)  # an EnvConfig is accepted as well
    assert env.constraint_specs[0].on == "input"


def test_specs_and_params_match_a_full_config():
    cfg = load_config(
        _cartpole(
            init_state={"type": "normal", "mean": [0.0, 0.0, 0.0, 0.0], "std": 0.01},
            physics_randomization={
                "cart_mass": {"type": "uniform", "low": 0.9, "high": 1.1, "relative": True},
                "pole_mass": {"type": "normal", "mean": 0.1, "std": 0.01, "low": 0.05, "high": 0.15},
                "pole_half_length": {"type": "choice", "values": [0.4, 0.5, 0.6]},
            },
            constraints=[
                {"type": "default", "on": "state"},
                {"type": "abs_bound", "on": "input", "bound": 5.0, "strict": True, "tolerance": 0.01},
                {"type": "bounded", "active_dims": [0, 2], "low": [-1.0, -0.2], "high": [1.0, 0.2]},
                {"type": "linear", "on": "input_and_state", "A": [[1.0, 0.0, 0.0, 0.0, 1.0]], "b": [2.0]},
                {"type": "quadratic", "active_dims": [2, 3], "P": [[1.0, 0.0], [0.0, 1.0]], "b": 0.25},
            ],
            done_on_violation=True,
            violation_penalty=2.0,
            disturbances={
                "action": [
                    {"type": "white_noise", "std": 0.1},
                    {"type": "step", "magnitude": 0.5, "start_step": 10},
                ],
                "observation": [{"type": "uniform", "low": -0.01, "high": 0.01}],
                "dynamics": [
                    {"type": "impulse", "magnitude": [0.1, 0.0], "start_step": "random", "duration": 5, "decay": 0.9},
                    {"type": "periodic", "scale": 0.2, "frequency": 0.5},
                ],
            },
            adversary={"channel": "dynamics", "scale": [0.1, 0.2]},
        )
    )
    assert load_config(dump_config(cfg)) == cfg
    env, params = make_from_config(cfg)

    assert env.init_state_spec == DistributionSpec("normal", False, False, (4,))
    np.testing.assert_allclose(np.asarray(params.init_state.std), [0.01] * 4, rtol=1e-6)
    assert env.physics_randomization_specs == {
        "cart_mass": DistributionSpec("uniform", True, False, ()),
        "pole_mass": DistributionSpec("normal", False, True, ()),
        "pole_half_length": DistributionSpec("choice", False, False, ()),
    }
    np.testing.assert_allclose(np.asarray(params.physics_randomization["pole_half_length"].values), [0.4, 0.5, 0.6])
    np.testing.assert_allclose(float(params.physics_randomization["pole_mass"].high), 0.15, rtol=1e-6)

    assert env.constraint_specs == (
        ConstraintSpec("default", "state", (0, 1, 2, 3), False, "linear", 4),
        ConstraintSpec("abs_bound", "input", (0,), True, "linear", 2),
        ConstraintSpec("bounded", "state", (0, 2), False, "linear", 4),
        ConstraintSpec("linear", "input_and_state", (0, 1, 2, 3, 4), False, "linear", 1),
        ConstraintSpec("quadratic", "state", (2, 3), False, "quadratic", 1),
    )
    np.testing.assert_allclose(np.asarray(params.constraints[1].b), [5.0, 5.0])
    np.testing.assert_allclose(float(params.constraints[1].tolerance), 0.01, rtol=1e-6)
    np.testing.assert_allclose(np.asarray(params.constraints[2].b), [1.0, 0.2, 1.0, 0.2], rtol=1e-6)
    np.testing.assert_allclose(np.asarray(params.constraints[4].P), np.eye(2))
    np.testing.assert_allclose(float(params.constraints[4].b), 0.25)
    assert env.done_on_violation and float(params.violation_penalty) == 2.0

    assert env.disturbance_specs == {
        "action": (DisturbanceSpec("white_noise", "action", 1), DisturbanceSpec("step", "action", 1)),
        "observation": (DisturbanceSpec("uniform", "observation", 4),),
        "dynamics": (DisturbanceSpec("impulse", "dynamics", 2, True), DisturbanceSpec("periodic", "dynamics", 2)),
    }
    assert int(params.disturbances["action"][1].start_step) == 10
    np.testing.assert_allclose(np.asarray(params.disturbances["action"][1].magnitude), [0.5])
    np.testing.assert_allclose(np.asarray(params.disturbances["observation"][0].low), [-0.01] * 4, rtol=1e-6)
    assert int(params.disturbances["dynamics"][0].duration) == 5
    np.testing.assert_allclose(float(params.disturbances["dynamics"][0].decay), 0.9, rtol=1e-6)
    np.testing.assert_allclose(float(params.disturbances["dynamics"][1].frequency), 0.5)

    assert env.adversary_channel == "dynamics"
    np.testing.assert_allclose(np.asarray(params.adversary_scale), [0.1, 0.2], rtol=1e-6)


def test_the_config_accepts_exactly_the_registered_safety_filters():
    """The env layer cannot import the filter registry, so it holds the names; they are the registry's, in order."""
    assert SAFETY_FILTER_NAMES == tuple(FILTERS)
    assert load_config({"env": {"system": "cartpole"}, "safety_filters": {"cbf": {"slope": 2.0}}}).safety_filters == {
        "cbf": {"slope": 2.0}
    }
    with pytest.raises(ConfigError, match=r"^safety_filters.cfb: unknown key; allowed keys are cbf, learned_cbf"):
        load_config({"env": {"system": "cartpole"}, "safety_filters": {"cfb": {}}})


@pytest.mark.parametrize("path", CONFIG_FILES, ids=lambda p: p.stem)
def test_every_controllers_and_training_section_parses(path):
    """The option sections are checked when a controller or learner is built; check those of every shipped file."""
    cfg = load_config(path)
    for name, options in cfg.controllers.items():
        module = importlib.import_module(CONTROLLERS[name].partition(":")[0])
        parse_options(module.Options, options, f"controllers.{name}")
    for algo, options in cfg.training.items():
        config = parse_options(algorithm_module(algo, "Config"), options, f"training.{algo}")
        assert config.num_iterations >= 1
