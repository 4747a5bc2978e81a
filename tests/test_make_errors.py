"""Bad options fail at ``make`` with a message that names the option and the allowed values."""

import pytest

import scg_jax

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
        r"trajectory.offset: expected 2 values, got shape \(3,\)",
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
