"""The evaluation harness: the JAX and host paths agree, results are deterministic, nothing retraces."""

import jax
import numpy as np
import pytest

import scg_jax
from scg_algorithms.base import JaxController, Reference
from scg_algorithms.evaluation import SUMMARY_KEYS, evaluate, evaluation_record
from scg_algorithms.lqr import make_lqr

NUM_EPISODES = 4


class HostWrapper:
    """The same controller run through the host path, one copy at a time with numpy arrays."""

    is_jax = False

    def __init__(self, controller):
        self.name = controller.name + "_host"
        self._reset = controller.reset
        self._act = jax.jit(controller.act)

    def reset(self, key, reference):
        return self._reset(key, Reference(*map(np.asarray, reference)))

    def act(self, ctrl_state, obs, step, reference):
        u, ctrl_state = self._act(ctrl_state, np.asarray(obs, np.float32), step, Reference(*reference))
        return np.asarray(u), ctrl_state


@pytest.fixture(scope="module")
def cartpole():
    # Observation noise and a random initial state, so the keys matter; a short episode keeps the test quick.
    env = scg_jax.make(
        "cartpole",
        episode_len_sec=1.0,
        init_state={"type": "uniform", "low": [-0.1] * 4, "high": [0.1] * 4},
        disturbances={"observation": [{"type": "white_noise", "std": 0.01}]},
        constraints=[{"type": "abs_bound", "on": "input", "bound": 1.0}],
    )
    params = env.default_params
    return env, params, make_lqr(env, params)


def test_jax_and_host_paths_give_the_same_episodes(cartpole):
    env, params, lqr = cartpole
    key = jax.random.key(3)
    on_device = evaluate(env, params, lqr, key, NUM_EPISODES)
    on_host = evaluate(env, params, HostWrapper(lqr), key, NUM_EPISODES)
    for name in ("x", "u_cmd", "reward", "cost"):
        np.testing.assert_allclose(on_host.trajectory[name], on_device.trajectory[name], rtol=1e-5, atol=1e-6)
    for name in ("rmse", "return", "violation_steps"):
        np.testing.assert_allclose(on_host.per_episode[name], on_device.per_episode[name], rtol=1e-5)
    # A 1 N bound on the input is tighter than what LQR asks for from a 0.1 rad tilt: violations are counted.
    assert on_device.summary["constraint_violation_steps"] > 0
    assert on_device.summary["failure_rate"] == 1.0
    assert on_host.summary["compute_time_per_step_s"] > 0


def test_trajectory_shapes_and_reference(cartpole):
    env, params, lqr = cartpole
    ev = evaluate(env, params, lqr, jax.random.key(0), NUM_EPISODES, measure_time=False)
    T = env.num_steps
    assert ev.trajectory["x"].shape == (T + 1, NUM_EPISODES, env.nx)
    assert ev.trajectory["u"].shape == (T, NUM_EPISODES, env.nu)
    assert ev.trajectory["constraint_values"].shape == (T, NUM_EPISODES, 2)
    x_ref, _ = jax.jit(env.reference)(params)
    np.testing.assert_allclose(ev.trajectory["x_ref"], np.broadcast_to(np.asarray(x_ref)[:, None], (T + 1, 4, 4)))
    # The recorded state before step k+1 is the state the step from k reached.
    first_state = ev.trajectory["x"][0]
    assert np.all(np.abs(first_state) <= 0.1 + 1e-6)
    assert ev.summary["compute_time_per_step_s"] is None


def test_same_key_same_result_other_key_other_result(cartpole):
    env, params, lqr = cartpole
    a = evaluate(env, params, lqr, jax.random.key(7), NUM_EPISODES, measure_time=False)
    b = evaluate(env, params, lqr, jax.random.key(7), NUM_EPISODES, measure_time=False)
    c = evaluate(env, params, lqr, jax.random.key(8), NUM_EPISODES, measure_time=False)
    np.testing.assert_array_equal(a.trajectory["x"], b.trajectory["x"])
    assert a.summary == {**b.summary}
    assert not np.allclose(a.trajectory["x"], c.trajectory["x"])


def test_a_second_evaluation_does_not_retrace(cartpole):
    env, params, lqr = cartpole
    traces = []

    def act(ctrl_state, obs, step, reference):
        traces.append(1)  # runs only while tracing
        return lqr.act(ctrl_state, obs, step, reference)

    counting = JaxController("counting", lqr.reset, act)
    first = evaluate(env, params, counting, jax.random.key(0), NUM_EPISODES)
    after_first = len(traces)
    second = evaluate(env, params.replace(goal=params.goal.at[0].set(0.05)), counting, jax.random.key(1), NUM_EPISODES)
    assert len(traces) == after_first
    assert second.timing["compile_s"] == 0.0 and first.timing["compile_s"] > 0.0


def test_batched_params_sweep_the_goal(cartpole):
    env, params, lqr = cartpole
    goals = np.zeros((NUM_EPISODES, 4), np.float32)
    goals[:, 0] = [0.0, 0.1, 0.2, 0.3]
    sweep = jax.tree.map(lambda a: np.broadcast_to(a, (NUM_EPISODES, *np.shape(a))), params)
    sweep = sweep.replace(goal=goals)
    key = jax.random.key(0)
    ev = evaluate(env, sweep, lqr, key, NUM_EPISODES, batched_params=True, measure_time=False)
    np.testing.assert_allclose(ev.trajectory["x_ref"][0, :, 0], goals[:, 0])
    # Copy i of the sweep is copy i of an unbatched evaluation with goal i (same key per copy).
    for i in (1, 3):
        single = evaluate(env, params.replace(goal=goals[i]), lqr, key, NUM_EPISODES, measure_time=False)
        np.testing.assert_allclose(ev.trajectory["x"][:, i], single.trajectory["x"][:, i], rtol=1e-5, atol=1e-6)


def test_record_has_the_paper_keys(cartpole):
    env, params, lqr = cartpole
    ev = evaluate(env, params, lqr, jax.random.key(0), NUM_EPISODES, measure_time=False)
    record = evaluation_record(ev, {"seed": 0})
    for key in ("rmse", "rmse_std", "worst_case_rmse_at_0.5", "failure_rate", "constraint_violation_steps", "return"):
        assert key in record
    assert set(SUMMARY_KEYS) <= set(record)
    assert record["seed"] == 0 and record["controller"] == "lqr"
    assert len(record["per_episode"]["rmse"]) == NUM_EPISODES


def test_bad_arguments_are_refused(cartpole):
    env, params, lqr = cartpole
    with pytest.raises(ValueError, match="num_episodes"):
        evaluate(env, params, lqr, jax.random.key(0), 0)
    with pytest.raises(TypeError, match="controller: missing"):
        evaluate(env, params, object(), jax.random.key(0), 2)
