"""The learner registry (``scg_algorithms.learners``) and ``scg_algorithms.train_run``: what lists learners derives
from the registry; ``train_run`` trains a tiny PPO into a folder, resumes bit-identically, refuses a folder holding a
run, evaluates the saved policy, reports through callbacks and prints nothing."""

from __future__ import annotations

import contextlib
import io
import json

import jax
import numpy as np
import pytest

import scg_algorithms
import scg_cli
import scg_jax
from scg_algorithms.evaluation import evaluate
from scg_algorithms.learners import LEARNERS, LearnerSpec, available, learner_part
from scg_algorithms.progress import Progress
from scg_algorithms.rl.checkpoint import load_metadata
from scg_algorithms.rl.policy import load_policy
from scg_algorithms.runs import train_run
from scg_experiments import common
from scg_jax.validation import FieldError
from tests.rl_helpers import tiny_ppo

# 1-s cart-pole episodes; PPO iterations of 8 copies x 16 steps (128 env steps), a constant step size (so a budget
# raised on resume follows the same schedule as a run of that budget in one go).
CONFIG = {
    "env": {"system": "cartpole", "episode_len_sec": 1.0},
    "training": {"ppo": {**tiny_ppo(256, num_epochs=1, num_minibatches=2), "lr_decay": False}},
}
SEED = 3


def _recorder(events: list) -> Progress:
    return Progress(
        start=lambda task: events.append(("start", task.name, task.total, task.completed)),
        update=lambda completed, info: events.append(("update", completed, info.get("env_steps"))),
        done=lambda: events.append(("done",)),
        note=lambda text: events.append(("note", text)),
    )


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """Two iterations in one go (evaluated on 2 episodes, progress recorded, output captured), and one iteration
    then resumed with the budget raised to two."""
    whole, split = tmp_path_factory.mktemp("whole"), tmp_path_factory.mktemp("split")
    events, out, err = [], io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        result = train_run("ppo", CONFIG, whole, seed=SEED, eval_episodes=2, progress=_recorder(events))
    first = train_run("ppo", CONFIG, split, seed=SEED, total_env_steps=128, eval_episodes=None)
    second = train_run("ppo", CONFIG, split, seed=SEED, resume=True, eval_episodes=None)
    return (whole, result, events, out.getvalue() + err.getvalue()), (split, first, second)


def test_progress_receives_the_iterations_in_order_and_the_library_prints_nothing(runs):
    (_, result, events, printed), _ = runs
    assert events == [
        ("start", "compiling ppo", None, 0), ("done",),
        ("start", "ppo", 2, 0), ("update", 1, 128), ("update", 2, 256), ("done",),
        ("start", "evaluating ppo on 2 episodes", None, 0), ("done",),
    ]  # fmt: skip
    assert printed == ""
    assert result.training["iterations"] == 2 and result.training["env_steps"] == 256


def test_a_resumed_train_run_is_bit_identical_to_one_in_one_go(runs):
    (whole, *_), (split, first, second) = runs
    assert first.training["iterations"] == 1 and first.evaluation is None and first.record is None
    assert not (split / "metrics.json").exists()
    assert second.training["resumed_from_iteration"] == 1 and second.training["env_steps"] == 256
    assert (split / "policy.msgpack").read_bytes() == (whole / "policy.msgpack").read_bytes()
    assert (split / "checkpoint.msgpack").read_bytes() == (whole / "checkpoint.msgpack").read_bytes()
    assert load_metadata(whole, "checkpoint")["iteration"] == load_metadata(split, "checkpoint")["iteration"] == 2
    rows = [[r[:2] + r[3:] for r in (line.split(",") for line in (d / "progress.csv").read_text().splitlines())]
            for d in (whole, split)]  # fmt: skip
    assert rows[0] == rows[1] and len(rows[0]) == 1 + 2  # the same metrics per iteration, wall times aside


def test_metrics_json_holds_the_evaluation_of_the_saved_policy(runs):
    """The final evaluation is the common harness on the saved policy with the second half of ``split(key(seed))``;
    ``metrics.json`` records it with the budget and the config it was trained with."""
    (whole, result, *_), _ = runs
    record = json.loads((whole / "metrics.json").read_text())
    assert result.files == ("policy.msgpack", "progress.csv", "learning_curve.png", "metrics.json")
    assert record["algo"] == "ppo" and record["seed"] == SEED and record["training"]["env_steps"] == 256
    assert record["hyperparameters"]["total_env_steps"] == 256 and "total_env_steps: 256" in record["config"]
    env, params = scg_jax.make_from_config(scg_jax.load_config(CONFIG))
    _, eval_key = jax.random.split(jax.random.key(SEED))
    oracle = evaluate(env, params, load_policy(whole, env, params), eval_key, 2, measure_time=False)
    assert record["evaluation"]["num_episodes"] == 2
    np.testing.assert_allclose(record["evaluation"]["per_episode"]["return"], oracle.per_episode["return"], rtol=1e-6)
    assert record["evaluation"]["rmse"] == pytest.approx(oracle.summary["rmse"], rel=1e-6)


def test_a_folder_holding_a_run_is_refused_in_the_callers_words(runs):
    (whole, *_), _ = runs
    before = {path.name: path.read_bytes() for path in whole.iterdir()}
    with pytest.raises(FieldError) as error:
        train_run("ppo", CONFIG, whole, seed=SEED)
    assert error.value.path == "out_dir" and error.value.reason.endswith(
        "already holds a training run (checkpoint.json, checkpoint.msgpack, policy.json, policy.msgpack, progress.csv, "
        "learning_curve.png, metrics.json); pass resume=True to continue it or overwrite=True to replace it"
    )
    flags = {"algo": "--algo", "out_dir": "--out", "resume": "--resume", "overwrite": "--overwrite"}
    with pytest.raises(FieldError) as error:
        train_run("sac", CONFIG, whole, resume=True, names=flags)
    assert error.value.path == "resume"
    assert "holds a ppo run, not sac; resume it with --algo ppo, or train sac into another --out" in str(error.value)
    assert before == {path.name: path.read_bytes() for path in whole.iterdir()}  # nothing touched


@pytest.mark.parametrize(
    ("algo", "options", "field", "message"),
    [
        ("ppo", {"prior_scale": 1.5}, "prior_scale", "only gp_mpc and learned_cbf learn on a prior model; ppo has"),
        ("gp_mpc", {"prior_scale": 0.0}, "prior_scale", "must be a positive number, got 0.0"),
        ("gp_mpc", {"total_env_steps": 10}, "total_env_steps", "gp_mpc has no env-step budget"),
        ("gp_mpc", {"resume": True}, "resume", "a gp_mpc run is not resumable (it is written when its rounds finish)"),
        ("ppo", {"eval_episodes": 0}, "eval_episodes", "must be a positive integer or None, got 0"),
        ("ppo", {"resume": True, "overwrite": True}, "resume", "give resume or overwrite, not both"),
    ],
)
def test_an_argument_the_learner_cannot_take_is_named(tmp_path, algo, options, field, message):
    with pytest.raises(FieldError) as error:
        train_run(algo, CONFIG, tmp_path / "run", **options)
    assert error.value.path == field and message in error.value.reason
    assert not (tmp_path / "run").exists()


def test_unknown_learners_and_progress_values_are_refused(tmp_path):
    with pytest.raises(ValueError, match="algo: unknown name 'ppo2'; allowed values are ppo, sac, ddpg, td3, gp_mpc, "):
        train_run("ppo2", CONFIG, tmp_path)
    with pytest.raises(TypeError, match="progress: expected a scg_algorithms.progress.Progress, a function or None"):
        train_run("ppo", CONFIG, tmp_path, progress="bar")
    assert scg_algorithms.train_run is train_run


# --------------------------------------------------------------------------------------------- the registry
def _algo_action():
    _, subparsers = scg_cli.build_parser()
    (action,) = [a for a in subparsers["train"]._actions if a.dest == "algo"]
    return action


def test_the_registry_drives_the_cli_choices_help_and_the_experiments_availability(monkeypatch, capsys):
    action = _algo_action()
    assert tuple(action.choices) == tuple(LEARNERS) == common.train_algorithms()
    assert all(f"{name} ({spec.summary})" in action.help for name, spec in LEARNERS.items())
    # One line adds a learner everywhere; a learner whose module is not in the build is listed but not available.
    monkeypatch.setitem(LEARNERS, "toy", LearnerSpec("toy", "scg_algorithms.ppo", "a toy", section="training.toy"))
    monkeypatch.setitem(LEARNERS, "missing", LearnerSpec("missing", "scg_algorithms.no_such_learner", "absent"))
    assert {"toy", "missing"} <= set(_algo_action().choices)
    assert (
        common.learner_available("toy")
        and available("toy")
        and learner_part("toy", "Config") is learner_part("ppo", "Config")
    )
    assert not common.learner_available("missing") and "missing" not in common.train_algorithms()
    # Removing one removes it from the CLI and the results.
    monkeypatch.delitem(LEARNERS, "rap")
    assert "rap" not in _algo_action().choices and not common.learner_available("rap")
    assert scg_cli.main(["train", "--system", "cartpole", "--algo", "rap", "--out", "unused"]) == 2
    assert "argument --algo: invalid choice: 'rap'" in capsys.readouterr().err


def test_learner_parts_come_from_the_registry():
    from scg_algorithms.rl.policy import algorithm_module
    from scg_algorithms.robust import rarl

    assert algorithm_module("rarl", "make_policy_learner") is rarl.make_policy_learner
    assert learner_part("ppo", "make_policy_learner") is learner_part("ppo", "make_learner")  # the default
    with pytest.raises(ValueError, match="algo: gp_mpc is not a JAX learner"):
        learner_part("gp_mpc", "Config")
    assert [n for n, s in LEARNERS.items() if not s.is_jax] == ["gp_mpc", "learned_cbf"]
    assert LEARNERS["learned_cbf"].loads_as == "filter" and LEARNERS["gp_mpc"].section == "controllers.gp_mpc"


@pytest.mark.parametrize("algo", ["ppo", "sac"])
def test_collect_is_the_collection_of_the_iteration_update_runs(algo):
    # benchmarks/train.py times Learner.collect as the collection part of an iteration: it must be exactly that
    # part (same key, same policy), so the collector it returns is bit for bit the one update carries on with.
    from scg_algorithms.rl.policy import algorithm_module
    from tests.rl_helpers import TINY_OFF_POLICY

    env = scg_jax.make("cartpole", episode_len_sec=1.0)
    params = env.default_params
    options = tiny_ppo(256, num_epochs=1, num_minibatches=2) if algo == "ppo" else TINY_OFF_POLICY
    learner = algorithm_module(algo, "make_learner")(options, env)
    update = jax.jit(learner.update)
    state = learner.init(jax.random.key(SEED), params)
    for _ in range(getattr(learner.config, "warmup_iterations", 0)):  # SAC past its random-action warm-up
        state, _ = update(state, params)
    collector, transitions = jax.jit(learner.collect)(state, params)
    updated, _ = update(state, params)
    data = lambda a: np.asarray(jax.random.key_data(a) if jax.dtypes.issubdtype(a.dtype, jax.dtypes.prng_key) else a)  # noqa: E731
    for a, b in zip(jax.tree.leaves(collector), jax.tree.leaves(updated.collector), strict=True):
        np.testing.assert_array_equal(data(a), data(b))
    assert np.asarray(transitions.reward).size == learner.steps_per_iteration
