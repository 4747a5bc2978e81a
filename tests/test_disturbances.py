"""Disturbances: statistics over 10,000 copies, exact timing, per-episode phases, channels, adversary."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import scg_jax

N = 10_000
U_MID = 0.1323  # 2D quadrotor hover per input: far from both actuator limits, so nothing is clipped


def _one_step_batch(env, key=0):
    """Reset and step N copies once with the hover input; returns (obs0, state0, out)."""
    params = env.default_params
    keys = jax.random.split(jax.random.key(key), N)
    obs, state = jax.vmap(env.reset, in_axes=(0, None))(keys, params)
    out = jax.vmap(env.step, in_axes=(0, None, None))(state, jnp.full(env.nu, U_MID), params)
    return obs, state, out


def test_white_noise_and_uniform_statistics_on_the_action_channel():
    env = scg_jax.make(
        "quadrotor_2d",
        disturbances={
            "action": [
                {"type": "white_noise", "std": [0.01, 0.02]},
                {"type": "uniform", "low": [0.0, -0.03], "high": [0.02, 0.03]},
            ]
        },
    )
    _, _, out = _one_step_batch(env)
    noise = np.asarray(out.info["u"]) - U_MID
    # Sum of N(0, s^2) and U(a, b): mean (a + b) / 2, variance s^2 + (b - a)^2 / 12.
    np.testing.assert_allclose(noise.mean(axis=0), [0.01, 0.0], atol=4e-4)
    np.testing.assert_allclose(noise.std(axis=0), np.sqrt([1e-4 + 0.02**2 / 12, 4e-4 + 0.06**2 / 12]), rtol=0.03)
    np.testing.assert_allclose(np.asarray(out.info["u_cmd"]), U_MID)  # the commanded input is unchanged


def test_observation_noise_leaves_the_true_state_alone():
    noisy = scg_jax.make(
        "quadrotor_2d", disturbances={"observation": [{"type": "white_noise", "std": 0.05, "mask": [1, 0, 1, 0, 0, 0]}]}
    )
    clean = scg_jax.make("quadrotor_2d")
    obs, state, out = _one_step_batch(noisy)
    _, clean_state, clean_out = _one_step_batch(clean)
    np.testing.assert_array_equal(np.asarray(state.x), np.asarray(clean_state.x))
    np.testing.assert_array_equal(np.asarray(out.state.x), np.asarray(clean_out.state.x))
    noise = np.asarray(out.obs) - np.asarray(out.state.x)
    np.testing.assert_allclose(noise.std(axis=0), [0.05, 0, 0.05, 0, 0, 0], rtol=0.03, atol=1e-7)
    np.testing.assert_allclose(noise.mean(axis=0), 0.0, atol=2e-3)
    assert np.abs(np.asarray(obs) - np.asarray(state.x)).max() > 0.05  # the reset observation is noisy too


def test_dynamics_noise_is_the_external_force():
    env = scg_jax.make("quadrotor_2d", disturbances={"dynamics": [{"type": "white_noise", "std": [0.001, 0.002]}]})
    _, state, out = _one_step_batch(env)
    f_ext = np.asarray(out.info["f_ext"])
    np.testing.assert_allclose(f_ext.std(axis=0), [0.001, 0.002], rtol=0.03)
    # The plant responds to exactly that force: re-integrate one copy with it.
    params = env.default_params
    x_next = env.integrate(state.x[0], jnp.full(2, U_MID), params.physics, jnp.asarray(f_ext[0]))
    np.testing.assert_allclose(np.asarray(out.state.x[0]), np.asarray(x_next), rtol=1e-6, atol=1e-7)


def _channel_series(env, steps, channel_value):
    params = env.default_params
    _, state = env.reset(jax.random.key(3), params)

    def body(state, _):
        out = env.step(state, jnp.full(env.nu, U_MID), params)
        return out.state, channel_value(out)

    return np.asarray(jax.lax.scan(body, state, None, steps)[1])


def test_step_and_impulse_timing_is_exact_to_the_step():
    env = scg_jax.make(
        "quadrotor_2d",
        disturbances={
            "action": [{"type": "step", "magnitude": [0.01, 0.0], "start_step": 7}],
            "dynamics": [{"type": "impulse", "magnitude": [0.004, 0.0], "start_step": 5, "duration": 3, "decay": 0.5}],
        },
    )
    action = _channel_series(env, 12, lambda out: out.info["u"][0] - U_MID)
    np.testing.assert_allclose(action, [0] * 7 + [0.01] * 5, atol=1e-8)
    force = _channel_series(env, 12, lambda out: out.info["f_ext"][0])
    np.testing.assert_allclose(force, [0, 0, 0, 0, 0, 0.004, 0.002, 0.001, 0, 0, 0, 0], atol=1e-10)


def test_random_impulse_start_is_drawn_once_per_episode_inside_the_episode():
    env = scg_jax.make(
        "quadrotor_2d",
        episode_len_sec=1.0,
        disturbances={"dynamics": [{"type": "impulse", "magnitude": 0.01, "start_step": "random", "duration": 10}]},
    )
    params = env.default_params
    starts = jax.vmap(lambda k: env.reset(k, params)[1].disturbances["dynamics"][0].start)(
        jax.random.split(jax.random.key(0), 2000)
    )
    starts = np.asarray(starts)
    assert starts.min() == 0 and starts.max() == env.num_steps - 10
    assert len(np.unique(starts)) == env.num_steps - 10 + 1


def test_periodic_phase_is_constant_within_an_episode_and_differs_across_episodes():
    env = scg_jax.make(
        "quadrotor_2d", disturbances={"action": [{"type": "periodic", "scale": [0.01, 0.02], "frequency": 2.0}]}
    )
    params = env.default_params
    _, state = env.reset(jax.random.key(3), params)  # the key _channel_series resets with
    phase = np.asarray(state.disturbances["action"][0].phase)
    values = _channel_series(env, 40, lambda out: out.info["u"] - U_MID)
    k = np.arange(40)[:, None]
    expected = np.array([0.01, 0.02]) * np.sin(2 * np.pi * 2.0 * k * env.dt + phase)
    np.testing.assert_allclose(values, expected, atol=2e-7)
    phases = jax.vmap(lambda key: env.reset(key, params)[1].disturbances["action"][0].phase)(
        jax.random.split(jax.random.key(0), 1000)
    )
    phases = np.asarray(phases)
    assert len(np.unique(phases[:, 0].round(6))) == 1000
    np.testing.assert_allclose(phases.mean(axis=0), np.pi, rtol=0.05)  # U(0, 2 pi)


def test_adversary_input_is_clipped_and_scaled_on_its_channel():
    env = scg_jax.make("quadrotor_2d", adversary={"channel": "dynamics", "scale": [0.002, 0.001]})
    params = env.default_params
    _, state = env.reset(jax.random.key(0), params)
    out = env.step(state, jnp.full(2, U_MID), params, adversary=jnp.array([3.0, -0.5]))
    np.testing.assert_allclose(np.asarray(out.info["f_ext"]), [0.002, -0.0005], rtol=1e-6)
    with pytest.raises(ValueError, match="adversary: this env was made without an adversary channel"):
        scg_jax.make("quadrotor_2d").step(state, jnp.full(2, U_MID), params, adversary=jnp.zeros(2))


@pytest.mark.parametrize(
    ("disturbances", "message"),
    [
        ({"wind": []}, r"disturbances.wind: unknown key; allowed keys are action, observation, dynamics$"),
        ({"action": [{"type": "gust"}]}, r"disturbances.action\[0\].type: unknown value 'gust'; allowed values"),
        ({"action": [{"type": "white_noise"}]}, r"disturbances.action\[0\].std: required"),
        (
            {"action": [{"type": "white_noise", "std": [1, 2, 3]}]},
            r"disturbances.action\[0\].std: expected a number "
            r"or 2 values",
        ),
        (
            {"dynamics": [{"type": "impulse", "magnitude": 1, "duration": 0}]},
            r"disturbances.dynamics\[0\].duration: expected an integer number of steps in \[1, 250\]",
        ),
        (
            {"observation": [{"type": "periodic", "scale": 1, "frequency": -1}]},
            r"disturbances.observation\[0\].frequency: expected a positive frequency",
        ),
    ],
)
def test_bad_disturbances_name_the_field(disturbances, message):
    with pytest.raises(ValueError, match=message):
        scg_jax.make("quadrotor_2d", disturbances=disturbances)


def test_random_start_is_only_for_impulses():
    with pytest.raises(ValueError, match=r"disturbances.action\[0\].start_step: expected a non-negative integer, got"):
        scg_jax.make(
            "quadrotor_2d", disturbances={"action": [{"type": "step", "magnitude": 1, "start_step": "random"}]}
        )
