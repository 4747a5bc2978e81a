"""Bad options fail at ``make`` with a message that names the option and the allowed values."""

import numpy as np
import pytest

import scg_jax
from scg_jax.config import EnvConfig
from scg_jax.validation import FieldError

CASES = [
    (
        ("pendulum",),
        {},
        r"system: unknown value 'pendulum'; allowed values are cartpole, quadrotor_1d, "
        r"quadrotor_2d, quadrotor_3d",
    ),
    (("cartpole", "swingup"), {}, r"task: unknown value 'swingup'; allowed values are stabilization, tracking"),
    (
        ("cartpole", "tracking"),
        {"trajectory": {"shape": "spiral"}},
        r"trajectory.shape: unknown value 'spiral'; allowed values are circle, sinusoid, figure8, square",
    ),
    (("cartpole", "tracking"), {"trajectory": {"plane": "xx"}}, r"trajectory.plane: unknown value 'xx'"),
    (
        ("cartpole", "tracking"),
        {"trajectory": {"offset": [0.0, 1.0, 2.0]}},
        r"trajectory.offset: expected 2 values, got 3: \[0.0, 1.0, 2.0\]$",
    ),
    (("cartpole", "tracking"), {"trajectory": {"speed": 2}}, r"trajectory.speed: unknown key; allowed keys are"),
    (
        ("cartpole",),
        {"ctrl_freq": 15, "physics_freq": 1000},
        r"physics_freq: must be a multiple of ctrl_freq \(15 Hz\), got 1000 Hz; allowed values are 15, 30, 45",
    ),
    (("cartpole",), {"ctrl_freq": 0}, r"ctrl_freq: must be a positive integer"),
    (("cartpole",), {"episode_len_sec": 1.01}, r"episode_len_sec: must be positive and a whole number"),
    (("cartpole",), {"integrator": "midpoint"}, r"integrator: unknown value 'midpoint'; allowed values are euler"),
    (("cartpole",), {"action_mode": "raw"}, r"action_mode: unknown value 'raw'; allowed values are physical"),
    (("quadrotor_2d",), {"reward_type": "upright"}, r"reward_type: 'upright' is only for cartpole"),
    (("cartpole",), {"ctrl_frequency": 50}, r"ctrl_frequency: unknown option; allowed options are ctrl_freq"),
    (("cartpole",), {"trajectory": {"shape": "circle"}}, r"trajectory: only allowed with task 'tracking'"),
    (("cartpole",), {"physics": {"pole_length": 1.0}}, r"physics.pole_length: unknown parameter of cartpole"),
    (("cartpole",), {"Q": [1, 1, 1]}, r"Q: expected 4 diagonal values or an \(4, 4\) matrix"),
    (("cartpole",), {"R": [-1.0]}, r"R: must be symmetric positive semidefinite"),
    (("quadrotor_1d",), {"goal": [1.0]}, r"goal: expected 2 values"),
    (("cartpole",), {"obs_goal_horizon": -1}, r"obs_goal_horizon: must be a non-negative integer"),
    (("cartpole", "tracking"), {"done_on_goal": True}, r"done_on_goal: only allowed with task 'stabilization'"),
    (
        ("cartpole",),
        {"init_state": {"type": "uniform", "low": [1, 0, 0, 0], "high": [0, 0, 0, 0]}},
        r"init_state.low: must not exceed high",
    ),
]


@pytest.mark.parametrize(("args", "options", "message"), CASES)
def test_bad_option_names_field_and_allowed_values(args, options, message):
    with pytest.raises(ValueError, match=message):
        scg_jax.make(*args, **options)


# Wrong types name the option (not a TypeError from deep inside), and every message is exact.
EXACT = [
    ({"ctrl_freq": "50"}, "ctrl_freq", "expected an integer, got '50'"),
    ({"ctrl_freq": True}, "ctrl_freq", "expected an integer, got True"),
    ({"episode_len_sec": "5"}, "episode_len_sec", "expected a finite number, got '5'"),
    ({"done_on_goal": 1}, "done_on_goal", "expected true or false, got 1"),
    ({"goal_tolerance": 0.0}, "goal_tolerance", "must be positive, got 0"),
    ({"violation_penalty": -2.0}, "violation_penalty", "must be >= 0 (it is subtracted from the reward), got -2"),
    ({"Q": [1.0, 1.0, 1.0, float("nan")]}, "Q[3]", "must be finite, got nan"),
    ({"goal": [0.0, 0.0, float("inf"), 0.0]}, "goal[2]", "must be finite, got inf"),
    (
        {"integrator": "rk5"},
        "integrator",
        "unknown value 'rk5'; allowed values are euler, semi_implicit_euler, rk4 (did you mean 'rk4'?)",
    ),
    (
        {"disturbances": {"action": [{"type": "white_noise", "std": -1}]}},
        "disturbances.action[0].std",
        "must be >= 0, got -1.0",
    ),
    (
        {"physics": {"cart_mass": -1.0}},
        "physics.cart_mass",
        "must be a positive finite number for cartpole, got -1.0",
    ),
    (
        {"physics": {"pole_lenght": 1.0}},
        "physics.pole_lenght",
        "unknown parameter of cartpole; allowed parameters are cart_mass, pole_mass, pole_half_length, gravity, "
        "force_max (did you mean 'pole_half_length'?)",
    ),
]


@pytest.mark.parametrize(("options", "path", "reason"), EXACT)
def test_errors_are_field_errors_with_the_path_and_the_exact_reason(options, path, reason):
    with pytest.raises(FieldError) as err:
        scg_jax.make("cartpole", **options)
    assert isinstance(err.value, ValueError)
    assert (err.value.path, err.value.reason) == (path, reason)
    assert str(err.value) == f"{path}: {reason}"


def test_make_accepts_the_typed_config_and_builds_the_same_env():
    options = {"ctrl_freq": 25, "physics_freq": 500, "constraints": [{"type": "abs_bound", "on": "input", "bound": 3}]}
    from_kwargs = scg_jax.make("cartpole", **options)
    from_config = scg_jax.make(EnvConfig(system="cartpole", **options))
    assert (from_config.ctrl_freq, from_config.substeps) == (from_kwargs.ctrl_freq, from_kwargs.substeps) == (25, 20)
    assert from_config.constraint_specs == from_kwargs.constraint_specs
    np.testing.assert_array_equal(
        np.asarray(from_config.default_params.constraints[0].b), np.asarray(from_kwargs.default_params.constraints[0].b)
    )
    with pytest.raises(TypeError, match="pass either an EnvConfig alone"):
        scg_jax.make(EnvConfig(system="cartpole"), ctrl_freq=10)
