"""A vmap sweep over action-noise levels under fixed LQR feedback: the error grows with the noise, no retrace."""

import jax
import jax.numpy as jnp
import numpy as np
import scipy.linalg

import scg_jax

LEVELS = np.array([0.0, 0.5, 1.0, 2.0, 4.0])  # N, std of the white noise on the cart force
COPIES = 32


def test_tracking_error_grows_with_action_noise_without_retracing():
    env = scg_jax.make("cartpole", episode_len_sec=2.0, disturbances={"action": [{"type": "white_noise", "std": 1.0}]})
    base = env.default_params
    lin = env.symbolic_model(base).linearize(np.zeros(4), np.zeros(1))
    P = scipy.linalg.solve_discrete_are(lin.Ad, lin.Bd, np.asarray(base.Q), np.asarray(base.R))
    K = jnp.asarray(np.linalg.solve(np.asarray(base.R) + lin.Bd.T @ P @ lin.Bd, lin.Bd.T @ P @ lin.Ad), jnp.float32)
    traces = []

    def lqr(obs, state, params, key):
        traces.append(1)
        return -K @ obs

    rollout = scg_jax.make_rollout(env, lqr, num_envs=len(LEVELS) * COPIES, auto_reset=False, batched_params=True)

    def sweep(levels):
        stds = jnp.repeat(jnp.asarray(levels, jnp.float32), COPIES)
        params = jax.vmap(
            lambda s: base.replace(
                disturbances={"action": (base.disturbances["action"][0].replace(std=jnp.full(1, s)),)}
            )
        )(stds)
        traj = rollout(jax.random.key(0), params)
        rmse = np.sqrt(np.asarray(traj.info["mse"]).mean(axis=0))
        return rmse.reshape(len(levels), COPIES).mean(axis=1), np.asarray(traj.terminated).any()

    rmse, failed = sweep(LEVELS)
    assert not failed
    assert np.all(np.diff(rmse) > 0), rmse
    assert rmse[-1] > 3 * rmse[0]
    rmse_again, _ = sweep(LEVELS * 1.1)
    assert np.all(rmse_again[1:] > rmse[1:]) and rmse_again[0] == rmse[0]  # 1.1 x 0 is still 0
    assert len(traces) == 1
