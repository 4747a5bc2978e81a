"""Shared RL infrastructure: running observation statistics against numpy, checkpoints of any pytree, the training
env's episode bookkeeping, the collector, exact step counters, and ``run_training``'s resume (N iterations in one go
= N/2, then N/2 resumed), interrupt, extension, refusals and learning-curve conventions."""

import csv
import json
import shutil

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import serialization

import scg_jax
from scg_algorithms.ppo import make_learner
from scg_algorithms.progress import Progress
from scg_algorithms.rl.checkpoint import load_checkpoint, load_metadata, save_checkpoint
from scg_algorithms.rl.collector import ActOutput, collect, init_collector
from scg_algorithms.rl.counter import Count, add_count, count_at_least, count_to_float, count_value, zero_count
from scg_algorithms.rl.curves import rmse_label
from scg_algorithms.rl.envs import (
    episode_means,
    init_episode_stats,
    initial_episode_means,
    make_train_env,
    policy_action_to_input,
    update_episode_stats,
)
from scg_algorithms.rl.normalization import RunningStats, init_stats, normalize, update_stats
from scg_algorithms.rl.policy import load_policy, trained_system
from scg_algorithms.rl.replay import ReplayBuffer
from scg_algorithms.rl.training import TrainingInterrupted, init_while_compiling, run_training
from scg_algorithms.sac import make_learner as sac_make_learner
from tests.rl_helpers import tiny_ppo


# --------------------------------------------------------------------------------------------- normalisation
def test_running_stats_equal_numpy_over_the_concatenated_batches():
    with jax.enable_x64(True):
        rng = np.random.default_rng(0)
        # Batches of different sizes (one of a single sample) from different distributions.
        sizes = ((1, 5.0, 1.0), (7, -2.0, 3.0), (100, 0.5, 0.1), (3, 10.0, 2.0))
        batches = [rng.normal(loc, scale, size=(n, 3)) for n, loc, scale in sizes]
        stats = init_stats(3, jnp.float64)
        update = jax.jit(update_stats)
        for i, batch in enumerate(batches):
            stats = update(stats, batch)
            seen = np.concatenate(batches[: i + 1])
            np.testing.assert_allclose(stats.mean, seen.mean(axis=0), rtol=1e-12)
            np.testing.assert_allclose(stats.var, seen.var(axis=0), rtol=1e-12)  # population variance, ddof = 0
            assert float(stats.count) == len(seen)


def test_running_stats_are_accurate_in_float32_far_from_zero():
    """A mean of 1e4 and a standard deviation of 0.1: E[x^2] - E[x]^2 in float32 would lose every digit of the
    variance (1e8 with a resolution of 8), the pairwise merge keeps it to a fraction of a percent."""
    rng = np.random.default_rng(1)
    batches = [1e4 + 0.1 * rng.normal(size=(64, 2)) for _ in range(20)]
    stats = init_stats(2)
    for batch in batches:
        stats = update_stats(stats, jnp.asarray(batch, jnp.float32))
    seen = np.concatenate(batches)
    np.testing.assert_allclose(stats.mean, seen.mean(axis=0), rtol=1e-6)
    np.testing.assert_allclose(stats.var, seen.var(axis=0), rtol=1e-2)


def test_running_stats_refuse_a_batch_of_another_size():
    with pytest.raises(ValueError, match=r"batch of shape \(5, 3\) does not end in the statistics' size 2"):
        update_stats(init_stats(2), jnp.zeros((5, 3)))


def test_running_stats_flatten_leading_axes_and_normalize():
    rng = np.random.default_rng(2)
    rollout = rng.normal([1.0, -3.0], [2.0, 0.5], size=(16, 8, 2)).astype(np.float32)  # (T, N, obs)
    stats = update_stats(init_stats(2), rollout)
    flat = rollout.reshape(-1, 2)
    np.testing.assert_allclose(stats.mean, flat.mean(axis=0), rtol=1e-5)
    np.testing.assert_allclose(stats.var, flat.var(axis=0), rtol=1e-5)
    normalized = normalize(stats, flat)
    np.testing.assert_allclose(np.mean(normalized, axis=0), 0.0, atol=1e-5)
    np.testing.assert_allclose(np.var(normalized, axis=0), 1.0, rtol=1e-4)
    # Before any update the normaliser is the identity, up to the clip at +-clip.
    x = jnp.array([[-20.0, 0.3], [4.0, 15.0]])
    np.testing.assert_allclose(normalize(init_stats(2), x, clip=10.0), [[-10.0, 0.3], [4.0, 10.0]], rtol=1e-6)
    np.testing.assert_allclose(normalize(stats, 1e6 * jnp.ones(2), clip=5.0), 5.0)


# --------------------------------------------------------------------------------------------- checkpoints
def _example_tree():
    return {
        "net": {"w": jnp.arange(12.0).reshape(3, 4), "b": jnp.array([0.5, -1.5, 2.0, 0.0])},
        "stats": RunningStats(mean=jnp.array([1.0, 2.0]), var=jnp.array([3.0, 4.0]), count=jnp.array(7.0)),
        "buffer": ReplayBuffer(
            data={"x": jnp.arange(10, dtype=jnp.int32).reshape(5, 2)},
            position=jnp.array(3, jnp.int32),
            size=jnp.array(5, jnp.int32),
        ),
        "flags": jnp.array([True, False, True]),
        "key": jax.random.key(42),
        "raw_key": jax.random.PRNGKey(7),
        "steps": [jnp.array(1, jnp.int32), jnp.array(2.5, jnp.float32)],
    }


def _zeros_like_tree(tree):
    """Same structure and dtypes, other values (typed keys: another key)."""
    is_key = lambda x: jax.dtypes.issubdtype(x.dtype, jax.dtypes.prng_key)  # noqa: E731
    return jax.tree.map(lambda x: jax.random.key(0) if is_key(x) else jnp.zeros_like(x), tree)


def test_checkpoint_round_trip_of_a_mixed_pytree(tmp_path):
    tree = _example_tree()
    save_checkpoint(tmp_path, "state", tree, {"algo": "test", "iteration": 3})
    for target in (jax.eval_shape(lambda: tree), _zeros_like_tree(tree)):
        restored, meta = load_checkpoint(tmp_path, "state", target)
        assert jax.tree.structure(restored) == jax.tree.structure(tree)
        assert isinstance(restored["stats"], RunningStats) and isinstance(restored["buffer"], ReplayBuffer)
        for name in ("net", "stats", "buffer", "flags", "raw_key", "steps"):
            for got, want in zip(jax.tree.leaves(restored[name]), jax.tree.leaves(tree[name]), strict=True):
                assert np.asarray(got).dtype == np.asarray(want).dtype
                np.testing.assert_array_equal(got, want)
        # A typed key comes back typed and draws the same numbers.
        assert jax.dtypes.issubdtype(restored["key"].dtype, jax.dtypes.prng_key)
        np.testing.assert_array_equal(jax.random.normal(restored["key"], (3,)), jax.random.normal(tree["key"], (3,)))
        assert meta["algo"] == "test" and meta["iteration"] == 3
    # The arrays file is a flat mapping from leaf paths to arrays, readable without the code that wrote it.
    stored = serialization.msgpack_restore((tmp_path / "state.msgpack").read_bytes())
    np.testing.assert_array_equal(stored["['net']['w']"], tree["net"]["w"])
    meta = load_metadata(tmp_path, "state")
    assert meta["checkpoint"]["format"] == "scg-jax-pytree-v1" and len(meta["checkpoint"]["sha256"]) == 64
    assert sorted(p.name for p in tmp_path.iterdir()) == ["state.json", "state.msgpack"]  # no temporary files left


def test_checkpoint_detects_mismatched_files_and_structures(tmp_path):
    tree = _example_tree()
    save_checkpoint(tmp_path / "a", "state", tree, {})
    other = jax.tree.map(lambda x: x, tree)
    other["net"]["w"] = other["net"]["w"] + 1.0
    save_checkpoint(tmp_path / "b", "state", other, {})
    target = jax.eval_shape(lambda: tree)
    # New arrays beside old metadata (a crash between the two renames) are reported, not silently paired.
    (tmp_path / "a" / "state.msgpack").write_bytes((tmp_path / "b" / "state.msgpack").read_bytes())
    with pytest.raises(ValueError, match="does not match state.json"):
        load_checkpoint(tmp_path / "a", "state", target)
    restored, _ = load_checkpoint(tmp_path / "b", "state", target)
    np.testing.assert_array_equal(restored["net"]["w"], other["net"]["w"])
    # Another structure or shape than the file's.
    missing = {**target, "extra": jax.ShapeDtypeStruct((2,), jnp.float32)}
    with pytest.raises(ValueError, match=r"leaves do not match the target structure \(missing \['extra'\]\)"):
        load_checkpoint(tmp_path / "b", "state", missing)
    fewer = {name: value for name, value in target.items() if name != "flags"}
    with pytest.raises(ValueError, match=r"unexpected \['flags'\]"):
        load_checkpoint(tmp_path / "b", "state", fewer)
    reshaped = {**target, "flags": jax.ShapeDtypeStruct((4,), jnp.bool_)}
    with pytest.raises(ValueError, match=r"\['flags'\] has shape \(3,\), expected \(4,\)"):
        load_checkpoint(tmp_path / "b", "state", reshaped)
    retyped = {**target, "flags": jax.ShapeDtypeStruct((3,), jnp.int32)}
    with pytest.raises(ValueError, match=r"\['flags'\] has dtype bool, expected int32"):
        load_checkpoint(tmp_path / "b", "state", retyped)
    with pytest.raises(FileNotFoundError):
        load_checkpoint(tmp_path / "missing", "state", target)


def test_checkpoint_with_bad_metadata_writes_nothing(tmp_path):
    with pytest.raises(TypeError):
        save_checkpoint(tmp_path, "state", _example_tree(), {"bad": object()})
    assert list(tmp_path.iterdir()) == []


# --------------------------------------------------------------------------------------------- training env
def test_train_env_keeps_the_final_observation_and_counts_episodes():
    # 5-step episodes (0.1 s at 50 Hz) on 3 copies, 7 steps with action 0: each copy is truncated at step 5.
    env = scg_jax.make("cartpole", episode_len_sec=0.1)
    params = env.default_params
    train_env = make_train_env(env, 3)

    @jax.jit
    def rollout(key):
        obs, state = train_env.reset(key, params)

        def step(carry, _):
            state, stats = carry
            out = train_env.step(state, jnp.zeros((3, 1)), params)
            stats, finished = update_episode_stats(stats, out)
            return (out.state, stats), (out, finished)

        return obs, jax.lax.scan(step, (state, init_episode_stats(3)), None, 7)[1]

    _, (out, finished) = rollout(jax.random.key(0))
    done = np.asarray(out.truncated)
    np.testing.assert_array_equal(done, np.tile((np.arange(7) == 4)[:, None], (1, 3)))
    assert not np.any(out.terminated)
    # The final observation is the reached one; the observation to act on next is a fresh episode's.
    np.testing.assert_array_equal(out.final_obs[:4], out.obs[:4])
    assert np.all(np.any(out.final_obs[4] != out.obs[4], axis=-1))
    # The finished episodes' totals: 5 steps, the return is the sum of the 5 rewards.
    np.testing.assert_array_equal(finished.episode_length[4], 5.0)
    np.testing.assert_allclose(finished.episode_return[4], np.sum(out.reward[:5], axis=0), rtol=1e-6)
    np.testing.assert_allclose(finished.episode_rmse[4], np.sqrt(np.mean(out.info["mse"][:5], axis=0)), rtol=1e-6)
    means = episode_means(finished, initial_episode_means())
    np.testing.assert_allclose(means["episode_return"], np.mean(np.sum(out.reward[:5], axis=0)), rtol=1e-6)
    assert float(means["episodes_finished"]) == 3.0
    # Where no episode finished, the previous means are repeated.
    nothing = jax.tree.map(lambda x: x[:4], finished)
    previous = {name: jnp.float32(i + 1.0) for i, name in enumerate(initial_episode_means())}
    repeated = episode_means(nothing, previous)
    assert {name: float(repeated[name]) for name in previous} == {n: float(v) for n, v in previous.items()}
    with pytest.raises(ValueError, match="num_envs: must be a positive integer"):
        make_train_env(env, 0)


def test_action_scale_widens_a_quadrotor_policy_to_twice_hover_thrust():
    env = scg_jax.make("quadrotor_2d")
    params = env.default_params
    hover = np.asarray(env.system.equilibrium_input(params.physics))
    a = jnp.array([1.0, -0.5])
    # Scale 1 is the env's normalised action: hover (1 + 0.1 a); scale 10: hover (1 + a); a is clipped first.
    np.testing.assert_allclose(policy_action_to_input(env, a, params.physics), hover * [1.1, 0.95], rtol=1e-6)
    np.testing.assert_allclose(policy_action_to_input(env, a, params.physics, 10.0), hover * [2.0, 0.5], rtol=1e-6)
    np.testing.assert_allclose(
        policy_action_to_input(env, 3 * a, params.physics, 10.0), hover * [2.0, 0.0], rtol=1e-6, atol=1e-9
    )
    # The training env commands the scaled input; the plant clips it to the motors' limits.
    train_env = make_train_env(env, 2, action_scale=10.0)
    _, state = train_env.reset(jax.random.key(0), params)
    out = train_env.step(state, jnp.stack([a, -a]), params)
    np.testing.assert_allclose(out.info["u_cmd"][0], hover * [2.0, 0.5], rtol=1e-6)
    u_low, u_high = env.system.input_bounds(params.physics)
    np.testing.assert_allclose(out.info["u"][0], np.clip(hover * [2.0, 0.5], u_low, u_high), rtol=1e-6)
    with pytest.raises(ValueError, match="action_scale: must be positive"):
        make_train_env(env, 2, action_scale=0.0)


# --------------------------------------------------------------------------------------------- resume
# 6 iterations of 8 copies x 16 steps; a constant step size, so the training program does not depend on the budget
# and every run below (any budget, chunks of 2) reuses one compiled chunk (the persistent compile cache).
TINY_PPO = {**tiny_ppo(total_env_steps=768, num_epochs=2, num_minibatches=2), "lr_decay": False}
ITERATIONS = 6


def _read_csv(path):
    with open(path, newline="") as file:
        rows = list(csv.reader(file))
    return rows[0], rows[1:]


@pytest.fixture(scope="module")
def resume_runs(tmp_path_factory):
    """PPO trained for 6 iterations in one go (adaptive chunks), and for 3 then resumed for 3 (chunks of 2)."""
    env = scg_jax.make("cartpole")
    params, key = env.default_params, jax.random.key(11)
    learner = make_learner(TINY_PPO, env)
    whole_dir, split_dir = tmp_path_factory.mktemp("whole"), tmp_path_factory.mktemp("split")
    whole = run_training(learner, env, params, key, whole_dir)
    half = learner._replace(num_iterations=ITERATIONS // 2)
    first = run_training(half, env, params, key, split_dir, chunk=2)
    first_checkpoint = json.loads((split_dir / "checkpoint.json").read_text())
    second = run_training(learner, env, params, key, split_dir, chunk=2, resume=True)
    return env, params, key, learner, (whole_dir, whole), (split_dir, first, first_checkpoint, second)


def test_resumed_training_is_bit_identical_to_an_uninterrupted_run(resume_runs):
    env, params, key, learner, (whole_dir, whole), (split_dir, first, first_checkpoint, second) = resume_runs
    assert first["iterations"] == ITERATIONS // 2 and first_checkpoint["iteration"] == ITERATIONS // 2
    assert second["resumed_from_iteration"] == ITERATIONS // 2
    assert whole["iterations"] == second["iterations"] == ITERATIONS
    assert whole["env_steps"] == second["env_steps"] == 768
    target = jax.eval_shape(learner.init, jax.random.key_data(key), params)
    whole_state, whole_meta = load_checkpoint(whole_dir, "checkpoint", target)
    split_state, split_meta = load_checkpoint(split_dir, "checkpoint", target)
    assert whole_meta["iteration"] == split_meta["iteration"] == ITERATIONS
    for a, b in zip(jax.tree.leaves(whole_state), jax.tree.leaves(split_state), strict=True):
        np.testing.assert_array_equal(a, b)
    assert count_value(whole_state.env_steps) == 768
    assert (whole_dir / "policy.msgpack").read_bytes() == (split_dir / "policy.msgpack").read_bytes()
    # progress.csv: one row per iteration, the same metrics (wall times aside).
    whole_header, whole_rows = _read_csv(whole_dir / "progress.csv")
    split_header, split_rows = _read_csv(split_dir / "progress.csv")
    assert whole_header == split_header and whole_header[:3] == ["iteration", "env_steps", "wall_time_s"]
    assert [row[0] for row in split_rows] == [str(i) for i in range(1, ITERATIONS + 1)]
    drop_time = lambda rows: [row[:2] + row[3:] for row in rows]  # noqa: E731
    assert drop_time(whole_rows) == drop_time(split_rows)
    assert (whole_dir / "learning_curve.png").stat().st_size > 0


def test_init_compiled_beside_the_loop_is_the_plain_jitted_init(resume_runs):
    """run_training's start: the init compiled on a worker thread, its shapes handed out first, then its state."""
    env, params, key, learner, *_ = resume_runs
    shapes, finish = init_while_compiling(learner.init, key, params)
    state, expected = finish(), jax.jit(learner.init)(key, params)
    assert jax.tree.structure(shapes) == jax.tree.structure(state) == jax.tree.structure(expected)

    def data(leaf):
        return jax.random.key_data(leaf) if jnp.issubdtype(leaf.dtype, jax.dtypes.prng_key) else leaf

    leaves = zip(jax.tree.leaves(shapes), jax.tree.leaves(state), jax.tree.leaves(expected), strict=True)
    for shape, got, want in leaves:
        assert (shape.shape, shape.dtype) == (got.shape, got.dtype) == (want.shape, want.dtype)
        np.testing.assert_array_equal(data(got), data(want))


def test_resume_with_another_config_is_refused(resume_runs, tmp_path):
    env, params, key, _, _, (split_dir, *_) = resume_runs
    other = make_learner({**TINY_PPO, "learning_rate": 3e-4}, env)
    with pytest.raises(ValueError, match="resume: .*checkpoint.json was written by 'ppo' with another config"):
        run_training(other, env, params, key, split_dir, resume=True)


def test_resume_with_another_config_names_the_settings_that_differ(resume_runs):
    env, params, key, _, _, (split_dir, *_) = resume_runs
    other = make_learner({**TINY_PPO, "learning_rate": 3e-4, "num_epochs": 3}, env)
    with pytest.raises(ValueError) as error:
        run_training(other, env, params, key, split_dir, resume=True)
    message = str(error.value)
    assert "learning_rate: 0.001 in the checkpoint, 0.0003 now" in message
    assert "num_epochs: 2 in the checkpoint, 3 now" in message
    assert "total_env_steps:" not in message  # the same budget: not listed


def test_resume_of_a_checkpoint_older_than_an_option_counts_it_at_its_default(resume_runs, tmp_path):
    """A field added to a learner after a checkpoint was written (absent from its saved config) counts at its
    default: the run resumes when the current value is the default, and is refused, naming it, when not."""
    env, params, key, learner, _, (split_dir, *_) = resume_runs
    old = tmp_path / "old"
    shutil.copytree(split_dir, old)
    meta = json.loads((old / "checkpoint.json").read_text())
    assert meta["config"].pop("ent_coef") == 0.0
    (old / "checkpoint.json").write_text(json.dumps(meta))
    resumed = run_training(learner, env, params, key, old, resume=True)
    assert resumed["resumed_from_iteration"] == ITERATIONS and resumed["iterations"] == ITERATIONS
    other = make_learner({**TINY_PPO, "ent_coef": 0.01}, env)
    with pytest.raises(ValueError, match=r"ent_coef: 0\.0 in the checkpoint, 0\.01 now"):
        run_training(other, env, params, key, old, resume=True)


def test_resume_of_another_algorithm_says_so(resume_runs):
    env, params, key, _, _, (split_dir, *_) = resume_runs
    sac = sac_make_learner({"num_envs": 8, "total_env_steps": 64, "batch_size": 16, "buffer_size": 64}, env)
    with pytest.raises(
        ValueError, match=r"^resume: .* holds a ppo run, not sac; resume it with algo ppo, or train sac"
    ):
        run_training(sac, env, params, key, split_dir, resume=True)


def test_a_folder_holding_a_run_is_refused_unless_resume_or_overwrite(resume_runs, tmp_path):
    env, params, key, learner, (whole_dir, _), _ = resume_runs
    before = {name: (whole_dir / name).read_bytes() for name in ("checkpoint.json", "policy.msgpack")}
    with pytest.raises(
        ValueError,
        match=r"^out_dir: .* already holds a training run \(checkpoint.json, .*pass resume=True to continue it",
    ):
        run_training(learner, env, params, key, whole_dir)
    with pytest.raises(ValueError, match="^resume, overwrite: give one of them"):
        run_training(learner, env, params, key, whole_dir, resume=True, overwrite=True)
    # Nothing was touched by the refusals.
    assert before == {name: (whole_dir / name).read_bytes() for name in before}
    # overwrite replaces the run: a shorter run leaves only its own files (no stale metrics.json, 3 CSV rows).
    copy = tmp_path / "copy"
    copy.mkdir()
    for path in whole_dir.iterdir():
        (copy / path.name).write_bytes(path.read_bytes())
    (copy / "metrics.json").write_text("{}")
    (copy / "notes.txt").write_text("mine")
    half = learner._replace(num_iterations=ITERATIONS // 2)
    result = run_training(half, env, params, key, copy, overwrite=True)
    assert result["iterations"] == 3 and not (copy / "metrics.json").exists()
    assert (copy / "notes.txt").read_text() == "mine"  # only the run's own files are removed
    assert len(_read_csv(copy / "progress.csv")[1]) == 3


def test_interrupt_saves_a_checkpoint_and_the_resumed_run_is_bit_identical(resume_runs, tmp_path, capsys):
    """Ctrl-C (a KeyboardInterrupt raised after the second iteration) saves that iteration although no checkpoint
    was due (the time-based interval is an hour); resuming completes the run bit-identically. The progress callbacks
    see the compilation, then each iteration in order with its env steps, and both tasks end; nothing is printed."""
    env, params, key, learner, (whole_dir, _), _ = resume_runs
    out = tmp_path / "interrupted"
    events = []

    def interrupt(iteration):
        if iteration == 2:
            raise KeyboardInterrupt

    progress = Progress(start=lambda task: events.append(("start", task.name, task.total, task.completed)),
                        update=lambda done, info: events.append(("update", done, info["env_steps"])),
                        done=lambda: events.append(("done",)))  # fmt: skip
    with pytest.raises(TrainingInterrupted) as stop:
        run_training(
            learner, env, params, key, out, chunk=1, checkpoint_seconds=3600.0, progress=progress, on_chunk=interrupt
        )
    assert stop.value.iteration == 2 and stop.value.checkpoint == out / "checkpoint.msgpack"
    assert load_metadata(out, "checkpoint")["iteration"] == 2
    assert [row[0] for row in _read_csv(out / "progress.csv")[1]] == ["1", "2"]
    assert not (out / "policy.json").exists()
    assert events == [("start", "compiling ppo", None, 0), ("done",), ("start", "ppo", 6, 0), ("update", 1, 128),
                      ("update", 2, 256), ("done",)]  # fmt: skip
    assert capsys.readouterr() == ("", "")

    result = run_training(learner, env, params, key, out, resume=True)
    assert result["resumed_from_iteration"] == 2 and result["iterations"] == ITERATIONS
    assert (out / "policy.msgpack").read_bytes() == (whole_dir / "policy.msgpack").read_bytes()
    drop_time = lambda rows: [row[:2] + row[3:] for row in rows]  # noqa: E731
    assert drop_time(_read_csv(out / "progress.csv")[1]) == drop_time(_read_csv(whole_dir / "progress.csv")[1])


def test_a_finished_run_is_extended_by_raising_the_budget(tmp_path):
    """2 iterations, then resumed with a budget of 4: the same as 4 in one go (constant step size, so the schedule
    does not depend on the budget). A budget below the checkpoint is refused."""
    env = scg_jax.make("cartpole")
    params, key = env.default_params, jax.random.key(3)
    short = make_learner({**TINY_PPO, "total_env_steps": 256}, env)
    long = make_learner({**TINY_PPO, "total_env_steps": 512}, env)
    run_training(short, env, params, key, tmp_path / "split", chunk=2)
    extended = run_training(long, env, params, key, tmp_path / "split", chunk=2, resume=True)
    whole = run_training(long, env, params, key, tmp_path / "whole", chunk=2)
    assert extended["resumed_from_iteration"] == 2 and extended["iterations"] == whole["iterations"] == 4
    assert extended["env_steps"] == 512
    assert (tmp_path / "split" / "policy.msgpack").read_bytes() == (tmp_path / "whole" / "policy.msgpack").read_bytes()
    tiny = make_learner({**TINY_PPO, "total_env_steps": 128}, env)
    with pytest.raises(ValueError, match=r"is at iteration 4 \(512 env steps\), beyond this budget of 1 iterations"):
        run_training(tiny, env, params, key, tmp_path / "split", resume=True)


def test_learning_curve_has_nan_before_the_first_episode_ends(resume_runs):
    _, _, _, _, (whole_dir, whole), _ = resume_runs
    header, rows = _read_csv(whole_dir / "progress.csv")
    column = {name: [row[i] for row in rows] for i, name in enumerate(header)}
    finished = np.cumsum([float(v) for v in column["episodes_finished"]])
    # 16 steps per copy per iteration: no 250-step episode can have ended in the first iteration.
    assert finished[0] == 0
    for name in ("episode_return", "episode_rmse", "episode_length", "episode_cost"):
        values = np.array([float(v) for v in column[name]])
        np.testing.assert_array_equal(np.isnan(values), finished == 0)
        assert column[name][0] == "nan"
    # The summary's JSON has null, not NaN, where no episode finished.
    if finished[-1] == 0:
        assert whole["final_metrics"]["episode_return"] is None


def test_rmse_axis_label_has_units():
    cartpole = scg_jax.make("cartpole")
    assert rmse_label(cartpole, cartpole.default_params) == "RMSE (weighted state error, mixed units)"
    quadrotor = scg_jax.make("quadrotor_2d")
    assert rmse_label(quadrotor, quadrotor.default_params) == "RMSE (m)"


@pytest.mark.parametrize(("steps", "ctrl_freq"), [(65_536 * np.arange(1, 65), 15.0), (8_192 * np.arange(1, 5), 0.25)])
def test_learning_curve_tick_labels_do_not_overlap_and_no_y_label_crowds_a_panel(tmp_path, steps, ctrl_freq):
    """Up to 4,194,304 env steps (labels 0-4M, no "1e6" offset) and a log axis inside one decade (1-2-5 labels, no
    minor "3x10^4" labels): within each panel no two x tick labels overlap, and no panel has a y label (its title
    names the quantity), so nothing reaches into the panel on its left."""
    from scg_algorithms.rl.curves import compact_number, learning_curve_figure

    assert [compact_number(v) for v in (0, 500, 30_000, 1_500_000, 4_194_304, -2e9)] == [
        "0", "500", "30k", "1.5M", "4.19M", "-2G"
    ]  # fmt: skip
    columns = ("env_steps", "episode_return", "episode_rmse", "episode_cost", "episode_length", "policy_loss")
    rows = [(int(n), -100 + i, 1 / (i + 1), 10 / (i + 1), 250, 0.1) for i, n in enumerate(steps)]
    (tmp_path / "p.csv").write_text("\n".join([",".join(columns)] + [",".join(map(str, r)) for r in rows]) + "\n")
    fig = learning_curve_figure(tmp_path / "p.csv", "RMSE (weighted state error, mixed units)", ctrl_freq)
    renderer = fig.canvas.get_renderer()
    fig.draw(renderer)
    assert len(fig.axes) == 6 and fig.axes[-1].get_xscale() == "log"
    for ax in fig.axes:
        assert ax.get_ylabel() == "" and ax.get_title()
        labels = [t for t in ax.get_xticklabels() if t.get_visible() and t.get_text()]
        assert len(labels) >= 2 and ax.xaxis.get_offset_text().get_text() == ""
        boxes = sorted((t.get_window_extent(renderer) for t in labels), key=lambda box: box.x0)
        assert all(a.x1 < b.x0 for a, b in zip(boxes, boxes[1:], strict=False)), [t.get_text() for t in labels]
    for left, right in zip(fig.axes, fig.axes[1:], strict=False):  # the y tick labels stay clear of the neighbour
        if abs(left.get_position().y0 - right.get_position().y0) < 1e-6:
            assert right.get_tightbbox(renderer).x0 > left.get_window_extent(renderer).x1


def test_a_policy_refuses_another_system(resume_runs):
    _, _, _, _, (whole_dir, _), _ = resume_runs
    assert load_metadata(whole_dir, "policy")["system"] == "cartpole"
    quadrotor = scg_jax.make("quadrotor_1d", obs_goal_horizon=1)  # 2 + 2 observations: the cart-pole's 4
    assert quadrotor.observation_size == 4
    with pytest.raises(ValueError, match="trained on the cartpole and cannot control the quadrotor_1d"):
        load_policy(whole_dir, quadrotor, quadrotor.default_params)
    # A policy file from before the system was recorded: its stored env config says it.
    assert trained_system({"env_config": "env:\n  system: cartpole\n  task: stabilization\n"}) == "cartpole"
    assert trained_system({}) is None


# --------------------------------------------------------------------------------------------- counters
def test_count_stays_exact_past_two_to_the_31_and_32():
    @jax.jit
    def advance(count, n):
        # 5 additions of 2^30 - 1 + n: past 2^31 (int32's limit) and 2^32 (one word's).
        return jax.lax.fori_loop(0, 5, lambda i, c: add_count(c, jnp.uint32(2**30 - 1) + n), count)

    count = advance(zero_count(), jnp.uint32(3))
    assert count_value(count) == 5 * (2**30 + 2) and int(count.hi) == 1
    assert count_value(add_count(Count(jnp.uint32(0), jnp.uint32(2**32 - 1)), 1)) == 2**32
    assert float(count_to_float(count)) == pytest.approx(5 * (2**30 + 2), rel=1e-7)
    assert bool(count_at_least(count, 2**32 - 1)) and not bool(count_at_least(zero_count(), 1))
    with pytest.raises(ValueError, match=r"n must be in \[0, 2\^32\)"):
        add_count(zero_count(), 2**32)
    # Stacked (a scan's metrics): exact uint64 on the host.
    stacked = Count(jnp.asarray([0, 2], jnp.uint32), jnp.asarray([5, 7], jnp.uint32))
    np.testing.assert_array_equal(count_value(stacked), [5, 2 * 2**32 + 7])


def test_a_learner_counts_env_steps_past_two_to_the_31(resume_runs):
    env, params, key, learner, *_ = resume_runs
    state = jax.jit(learner.init)(jax.random.key_data(key), params)
    state = state._replace(env_steps=Count(jnp.uint32(0), jnp.uint32(2**31 - 64)))
    state, metrics = jax.jit(learner.update)(state, params)
    assert count_value(state.env_steps) == count_value(metrics["env_steps"]) == 2**31 + 64


# --------------------------------------------------------------------------------------------- collector
def test_collector_records_what_every_learner_needs():
    """4 copies, 6 steps of a constant action: transitions (T, N, ...) with cost, info entries and the act's
    extras; the normaliser holds exactly the observations acted on."""
    bound = {"type": "abs_bound", "on": "input", "bound": 0.5}
    env = scg_jax.make("cartpole", episode_len_sec=0.08, constraints=[bound])
    params = env.default_params
    train_env = make_train_env(env, 4)

    def act(obs, key):
        return ActOutput(jnp.full((4, 1), 0.3), {"obs_sum": jnp.sum(obs, axis=-1)})

    @jax.jit
    def run(key):
        state = init_collector(train_env, key, params)
        return collect(train_env, params, state, act, jax.random.key(1), 6, info_keys=("constraint_values",))

    state, steps, episode, labels = run(jax.random.key(0))
    assert labels is None and "label" not in steps.extras
    assert steps.obs.shape == (6, 4, 4) and steps.action.shape == (6, 4, 1) and steps.adversary is None
    np.testing.assert_allclose(steps.extras["obs_sum"], np.sum(steps.obs, axis=-1), rtol=1e-6)
    # Force 0.3 * 10 N = 3 N against a 0.5 N bound: every step violates, cost 1.
    np.testing.assert_array_equal(steps.cost, 1.0)
    assert steps.info["constraint_values"].shape[:2] == (6, 4)
    # 4-step episodes: truncated at step 4, next_obs is the reached observation, obs the next episode's first.
    np.testing.assert_array_equal(steps.truncated, np.tile((np.arange(6) == 3)[:, None], (1, 4)))
    np.testing.assert_array_equal(steps.next_obs[:3], steps.obs[1:4])
    assert float(episode["episodes_finished"]) == 4.0 and float(episode["episode_cost"]) == 4.0
    expected = update_stats(init_stats(4), steps.obs)  # outside jit: equal up to rounding
    for a, b in zip(state.obs_stats, expected, strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-6)
    np.testing.assert_array_equal(state.obs_stats.count, 24.0)
    np.testing.assert_array_equal(state.episode_stats.episode_length, 2.0)


def test_collector_passes_the_adversary_input_to_the_env():
    """An adversary on the action channel (scale 2 N): with the protagonist's action 0 and the adversary's +1 (times
    the scale, clipped to [-1, 1]), the applied force is 2 N; it is stored with the transitions."""
    env = scg_jax.make("cartpole", adversary={"channel": "action", "scale": 2.0})
    params = env.default_params
    train_env = make_train_env(env, 3)

    def act(obs, key):
        return ActOutput(jnp.zeros((3, 1)), {}, adversary=jnp.full((3, 1), 1.5))

    @jax.jit
    def run(key):
        state = init_collector(train_env, key, params)
        return collect(train_env, params, state, act, jax.random.key(1), 4, info_keys=("u",))

    steps = run(jax.random.key(0)).transitions
    np.testing.assert_allclose(steps.info["u"], 2.0, rtol=1e-6)
    np.testing.assert_array_equal(steps.adversary, 1.5)
