"""brax adapter: BraxEnv equals the functional env, per-episode resets, done/truncation flags, PPO and SAC learn."""

import functools
import time

import jax
import jax.numpy as jnp
import numpy as np
import pytest

# isort: off
# The adapter first: it imports brax without the warp message. A broken adapter fails this file, it is not skipped.
from scg_jax.adapters.brax import BraxEnv, wrap_for_training
from brax.envs.wrappers.training import wrap as brax_default_wrap
from brax.training.acting import Evaluator
# isort: on

import scg_jax

# brax 0.14.2's trainers call jax.device_put_replicated, deprecated in the pinned jax 0.9.2 (removed in 0.10).
_IGNORE_REPLICATED = pytest.mark.filterwarnings("ignore:jax.device_put_replicated:DeprecationWarning")
_THETA_CONSTRAINT = [{"type": "abs_bound", "on": "state", "active_dims": [2], "bound": 0.2}]


def _constrained_cartpole(**options):
    """The cart-pole with normalised actions, the exponential reward and the constraint |theta| <= 0.2 rad."""
    return scg_jax.make(
        "cartpole", action_mode="normalized", reward_type="exponential", constraints=_THETA_CONSTRAINT, **options
    )


def _run(wrapped, num_envs, actions, key=1):
    """Reset a wrapped (batched) env and apply ``actions`` (num_steps, num_envs, nu); return the states."""
    state = jax.jit(wrapped.reset)(jax.random.split(jax.random.PRNGKey(key), num_envs))
    step = jax.jit(wrapped.step)
    states = [state]
    for action in actions:
        state = step(state, action)
        states.append(state)
    return states


# ----------------------------------------------------------------------------------------- the adapter


@pytest.mark.parametrize(
    "system, task, options",
    [
        (
            "cartpole",
            "stabilization",
            {
                "reward_type": "upright",
                "constraints": [{"type": "abs_bound", "on": "state", "active_dims": [2], "bound": 0.05}],
            },
        ),
        (
            "quadrotor_2d",
            "tracking",
            {
                "obs_goal_horizon": 2,
                "physics_randomization": {"mass": {"type": "uniform", "low": 0.9, "high": 1.1, "relative": True}},
                "disturbances": {
                    "observation": [{"type": "white_noise", "std": 0.01}],
                    "action": [{"type": "periodic", "scale": 0.01, "frequency": 1.0}],
                },
                "constraints": [{"type": "abs_bound", "on": "state", "active_dims": [0], "bound": 0.4}],
            },
        ),
    ],
)
def test_reset_and_step_equal_the_functional_env(system, task, options):
    env = scg_jax.make(system, task, action_mode="normalized", episode_len_sec=0.5, **options)
    params = env.default_params
    brax_env = BraxEnv(env, params)
    assert (brax_env.observation_size, brax_env.action_size) == (env.observation_size, env.action_size)
    assert brax_env.backend == "scg_jax"

    key = jax.random.PRNGKey(3)
    obs, env_state = env.reset(key, params)
    state = jax.jit(brax_env.reset)(key)
    np.testing.assert_allclose(state.obs, obs, atol=1e-6)
    assert float(state.reward) == 0.0 and float(state.done) == 0.0
    assert set(state.metrics) == {"cost", "mse", "constraint_violation"}
    assert float(state.info["truncation"]) == 0.0

    env_step, brax_step = jax.jit(env.step), jax.jit(brax_env.step)
    actions = jax.random.uniform(jax.random.PRNGKey(4), (env.num_steps, env.action_size), minval=-1, maxval=1)
    costs = []
    for action in actions:
        out = env_step(env_state, action, params)
        state = brax_step(state, action)
        env_state = out.state
        np.testing.assert_allclose(state.obs, out.obs, atol=1e-6)
        np.testing.assert_allclose(state.pipeline_state.x, out.state.x, atol=1e-6)
        np.testing.assert_allclose(state.reward, out.reward, atol=1e-6)
        assert float(state.done) == float(out.terminated | out.truncated)
        assert float(state.info["truncation"]) == float(out.truncated)
        assert float(state.metrics["cost"]) == float(out.cost)
        np.testing.assert_allclose(state.metrics["mse"], out.info["mse"], rtol=1e-6)
        costs.append(float(out.cost))
        if float(state.done):
            break
    assert sum(costs) > 0  # the constraint was violated at least once, so the cost metric is exercised


def test_physical_action_mode_is_rejected_with_the_option_to_pass():
    with pytest.raises(ValueError, match="action_mode='normalized'"):
        BraxEnv(scg_jax.make("cartpole"))
    with pytest.raises(TypeError, match="scg_jax.Env"):
        BraxEnv("cartpole")


# ----------------------------------------------------------------------------------------- auto-reset


def test_every_episode_draws_a_new_initial_state_and_parameters_unlike_brax_default_wrap():
    env = scg_jax.make(
        "cartpole",
        action_mode="normalized",
        episode_len_sec=0.1,  # 5 steps, truncated
        physics_randomization={"pole_mass": {"type": "uniform", "low": 0.5, "high": 1.5, "relative": True}},
        disturbances={"action": [{"type": "periodic", "scale": 0.5, "frequency": 1.0}]},
    )
    brax_env, num_envs, n = BraxEnv(env), 4, env.num_steps
    actions = jnp.zeros((2 * n, num_envs, 1))

    def episode_starts(states):
        assert all(float(s.done.max()) == 0.0 for i, s in enumerate(states) if i not in (n, 2 * n))
        return [states[0], states[n], states[2 * n]]  # after the reset and after each episode's last step

    ours = episode_starts(_run(wrap_for_training(brax_env, episode_length=n), num_envs, actions))
    default = episode_starts(_run(brax_default_wrap(brax_env, episode_length=n), num_envs, actions))
    for starts, fresh in ((ours, True), (default, False)):
        assert all(np.all(np.asarray(s.done) == 1.0) for s in starts[1:])
        for later in starts[1:]:
            first_ps, later_ps = starts[0].pipeline_state, later.pipeline_state
            np.testing.assert_array_equal(later_ps.step, 0)
            np.testing.assert_array_equal(later.obs, later_ps.x)
            same_x = np.isclose(first_ps.x, later_ps.x).all(axis=1)
            same_mass = np.isclose(first_ps.physics.pole_mass, later_ps.physics.pole_mass)
            same_phase = np.isclose(
                first_ps.disturbances["action"][0].phase, later_ps.disturbances["action"][0].phase
            ).all(axis=1)
            if fresh:  # a new draw in every copy, within the env's ranges
                assert not same_x.any() and not same_mass.any() and not same_phase.any()
                assert np.all(np.abs(later_ps.x) <= 0.05)
                assert np.all((later_ps.physics.pole_mass >= 0.05) & (later_ps.physics.pole_mass <= 0.15))
            else:  # brax restores the first state of the batch
                assert same_x.all() and same_mass.all() and same_phase.all()
    # the two episodes after the first differ from each other too
    assert not np.isclose(ours[1].pipeline_state.x, ours[2].pipeline_state.x).all(axis=1).any()


def test_wrapped_env_is_determined_by_the_reset_key():
    env = scg_jax.make("cartpole", action_mode="normalized", episode_len_sec=0.1)
    wrapped = wrap_for_training(BraxEnv(env), episode_length=env.num_steps)
    actions = jnp.full((12, 3, 1), 0.3)
    a, b, c = (_run(wrapped, 3, actions, key=k)[-1] for k in (5, 5, 6))
    np.testing.assert_array_equal(a.obs, b.obs)
    assert not np.allclose(a.obs, c.obs)


# ----------------------------------------------------------------------------------------- done and truncation


def test_done_and_truncation_at_a_crash_and_at_the_time_limit():
    # Crash: the pole starts at 1.5 rad and falls past pi/2 within a few steps: done, not truncated.
    crash = scg_jax.make("cartpole", action_mode="normalized", episode_len_sec=1.0, init_state=[0.0, 0.0, 1.5, 0.0])
    # Time limit: exactly upright with no force stays at the equilibrium for all 10 steps.
    upright = scg_jax.make("cartpole", action_mode="normalized", episode_len_sec=0.2, init_state=[0.0, 0.0, 0.0, 0.0])
    for env, expect_truncation in ((crash, 0.0), (upright, 1.0)):
        for brax_episode_length in (env.num_steps, 1000):  # equal to the env's own limit, or longer
            wrapped = wrap_for_training(BraxEnv(env), episode_length=brax_episode_length)
            states = _run(wrapped, 2, jnp.zeros((env.num_steps, 2, 1)))[1:]
            done = np.array([np.asarray(s.done) for s in states])
            last = int(np.flatnonzero(done[:, 0])[0])
            assert last == env.num_steps - 1 if expect_truncation else last < 5
            np.testing.assert_array_equal(done[:last], 0.0)
            np.testing.assert_array_equal(done[last], 1.0)
            np.testing.assert_array_equal(states[last].info["truncation"], expect_truncation)
            np.testing.assert_array_equal(states[last].info["time_out"], expect_truncation)
            np.testing.assert_array_equal(states[last].info["steps"], last + 1)
            metrics = states[last].info["episode_metrics"]
            np.testing.assert_array_equal(metrics["length"], last + 1)
            np.testing.assert_allclose(metrics["sum_reward"], sum(np.asarray(s.reward) for s in states[: last + 1]))
    # brax's default EpisodeWrapper turns the env's own time limit into a termination (truncation = 1 - done).
    states = _run(brax_default_wrap(BraxEnv(upright), episode_length=upright.num_steps), 2, jnp.zeros((10, 2, 1)))
    np.testing.assert_array_equal(states[-1].done, 1.0)
    np.testing.assert_array_equal(states[-1].info["truncation"], 0.0)

    # A brax time limit shorter than the env's truncates there; the counter restarts with the new episode.
    wrapped = wrap_for_training(BraxEnv(upright), episode_length=3)
    states = _run(wrapped, 2, jnp.zeros((7, 2, 1)))[1:]
    np.testing.assert_array_equal([float(s.done[0]) for s in states], [0, 0, 1, 0, 0, 1, 0])
    np.testing.assert_array_equal([float(s.info["truncation"][0]) for s in states], [0, 0, 1, 0, 0, 1, 0])
    np.testing.assert_array_equal([int(s.pipeline_state.step[0]) for s in states], [1, 2, 0, 1, 2, 0, 1])


def test_action_repeat_stops_a_copy_at_its_crash():
    env = scg_jax.make(
        "cartpole", action_mode="normalized", reward_type="upright", init_state=[0.0, 0.0, 1.5, 0.0], episode_len_sec=1
    )
    single = _run(wrap_for_training(BraxEnv(env), episode_length=50), 1, jnp.zeros((10, 1, 1)))[1:]
    crash_step = int(np.flatnonzero([float(s.done[0]) for s in single])[0]) + 1  # steps to the crash
    repeat = crash_step + 2  # one agent step covers the crash and two more env steps
    state = _run(wrap_for_training(BraxEnv(env), episode_length=50, action_repeat=repeat), 1, jnp.zeros((1, 1, 1)))[1]
    assert float(state.done[0]) == 1.0 and float(state.info["truncation"][0]) == 0.0
    # the upright reward is 1 per step inside the bounds, 0 at the crash step, and nothing after it
    assert float(state.reward[0]) == sum(float(s.reward[0]) for s in single[:crash_step]) == crash_step - 1


def test_randomization_fn_gives_each_slot_its_own_params():
    env = scg_jax.make("cartpole", action_mode="normalized", episode_len_sec=0.1, init_state=[0.0, 0.0, 0.1, 0.0])
    lengths = jnp.array([0.3, 0.5, 0.8, 1.2])

    def randomization_fn(params, rng):  # brax's signature, with EnvParams in place of a brax System
        batched = params.replace(physics=params.physics.replace(pole_half_length=lengths[: rng.shape[0]]))
        in_axes = jax.tree.map(lambda _: None, params).replace(
            physics=jax.tree.map(lambda _: None, params.physics).replace(pole_half_length=0)
        )
        return batched, in_axes

    rng = jax.random.split(jax.random.PRNGKey(0), 4)
    wrapped = wrap_for_training(
        BraxEnv(env), episode_length=env.num_steps, randomization_fn=functools.partial(randomization_fn, rng=rng)
    )
    states = _run(wrapped, 4, jnp.zeros((2 * env.num_steps, 4, 1)))
    for state in (states[0], states[env.num_steps], states[-1]):  # kept across auto-resets
        np.testing.assert_allclose(state.pipeline_state.physics.pole_half_length, lengths)
    # from the same start a longer pole falls more slowly: the slots really run different plants
    theta_dot = np.asarray(states[3].pipeline_state.x[:, 3])
    assert np.all(np.diff(theta_dot) < 0) and theta_dot[-1] > 0


def test_brax_evaluator_reports_the_episode_cost_and_reward_of_the_functional_env():
    # Deterministic: falls through |theta| = 0.2 and on to a crash.
    env = _constrained_cartpole(episode_len_sec=1.0, init_state=[0.0, 0.0, 0.15, 0.0])
    params = env.default_params
    traj = scg_jax.rollout(env, params, lambda *_: jnp.zeros(1), jax.random.key(0), num_envs=1, auto_reset=False)
    done = np.asarray(traj.terminated[:, 0] | traj.truncated[:, 0])
    end = int(np.flatnonzero(done)[0]) + 1 if done.any() else env.num_steps
    expected_cost = float(np.asarray(traj.cost[:end, 0]).sum())
    expected_reward = float(np.asarray(traj.reward[:end, 0]).sum())
    assert end < env.num_steps and 0 < expected_cost < end  # a crash; some steps in violation, not all

    evaluator = Evaluator(
        wrap_for_training(BraxEnv(env, params), episode_length=env.num_steps),
        lambda _: lambda obs, key: (jnp.zeros((obs.shape[0], 1)), {}),
        num_eval_envs=4,
        episode_length=env.num_steps,
        action_repeat=1,
        key=jax.random.PRNGKey(0),
    )
    metrics = evaluator.run_evaluation(None, training_metrics={})
    assert metrics["eval/episode_cost"] == pytest.approx(expected_cost)
    assert metrics["eval/episode_constraint_violation"] == pytest.approx(expected_cost)
    assert metrics["eval/episode_reward"] == pytest.approx(expected_reward, rel=1e-5)
    assert metrics["eval/avg_episode_length"] == pytest.approx(end)


# ----------------------------------------------------------------------------------------- learning
# The cart-pole stabilization task with the exponential reward exp(-c) (c = 1/2 x'Qx + 1/2 u'Ru): the return is
# at most 100 (2 s at 50 Hz). The untrained policies score 8-14 (the pole falls within ~1 s, and the reward decays
# as it tilts); with these budgets every seed tried (0, 1, 2) reached >= 90 for both agents. The tests ask for a
# gain of 40 (less than half of the ~80 seen) and a final return of 60, far outside the spread of a 64-episode
# evaluation mean. The constraint |theta| <= 0.2 rad gives eval/episode_cost: 20-30 violating steps untrained,
# 0-1.3 after training (the exponential reward also penalises the angle), asserted as a decrease.


def _learning_env():
    env = _constrained_cartpole(episode_len_sec=2.0)
    return env, BraxEnv(env)


def _recorder():
    """A brax ``progress_fn`` recording (step, eval reward, eval cost), and the list it appends to."""
    curve = []

    def progress(step, metrics):
        assert "eval/episode_cost" in metrics and "eval/episode_mse" in metrics
        curve.append((step, float(metrics["eval/episode_reward"]), float(metrics["eval/episode_cost"])))

    return curve, progress


def _learns(name, train, **options):
    """Run brax's ``train`` on the learning env (3 evaluations of 64 envs, seed 0, normalised observations, plus
    ``options``) and check that the evaluated reward rises and the cost falls."""
    env, brax_env = _learning_env()
    curve, progress = _recorder()
    start = time.time()
    _, _, metrics = train(
        brax_env,
        episode_length=env.num_steps,
        wrap_env_fn=wrap_for_training,
        normalize_observations=True,
        num_evals=3,
        num_eval_envs=64,
        seed=0,
        progress_fn=progress,
        **options,
    )
    print(f"{name}: {time.time() - start:.1f} s")
    assert len(curve) == 3 and "eval/episode_cost" in metrics
    first, last = curve[0], curve[-1]
    print("eval curve (step, episode_reward, episode_cost):", [(s, round(r, 2), round(c, 2)) for s, r, c in curve])
    assert last[1] > first[1] + 40.0 and last[1] > 60.0
    assert last[2] < first[2]


def _sac_agent():
    """brax's SAC ``train`` and the options it learns the cart-pole with (small networks, a short run).

    At this budget (seed 0): the evaluated reward goes 11.4 -> 44.0 -> 72.3 and the cost 23.6 -> 14.4 -> 0 (the test
    asks for a rise of 40 to above 60; 12 k steps before)."""
    from brax.training.agents.sac import networks, train

    networks = functools.partial(networks.make_sac_networks, hidden_layer_sizes=(32, 32))
    options = dict(
        num_timesteps=6_000, num_envs=16, batch_size=256, grad_updates_per_step=16, min_replay_size=1000,
        max_replay_size=100_000, learning_rate=3e-3, discounting=0.97, tau=0.05,
    )  # fmt: skip
    return train.train, {**options, "network_factory": networks}


@pytest.mark.slow
@_IGNORE_REPLICATED
def test_brax_sac_learns_cartpole_stabilization():
    """brax's SAC learns on the adapter. That brax's PPO learns (100 k steps; at 50 k its cost rose, 20.2 -> 26.5) is
    the example of docs/adapters.md, which tests/test_docs.py runs with these checks (one PPO training per run)."""
    train, options = _sac_agent()
    _learns("sac", train, **options)


def test_importing_the_adapter_prints_no_warp_message():
    import subprocess
    import sys

    code = "import scg_jax.adapters.brax; print('imported')"
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, timeout=300)
    assert result.stdout.strip() == "imported"
    assert "warp" not in result.stdout + result.stderr
