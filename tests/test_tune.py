"""``scg-jax tune``: the CVaR objective by hand, a study whose best config ``train --config`` reproduces to the last
digit, resuming, a population whose members score what the same settings score trained alone, every learner's
traced options reaching its training program, pruning against the median, and the command line's Ctrl-C."""

import csv
import itertools
import json
import shutil
import types

import jax
import jax.numpy as jnp
import numpy as np
import optuna
import pytest

from scg_algorithms import runs
from scg_algorithms.evaluation import evaluate
from scg_algorithms.learners import build_learner, learner_part
from scg_algorithms.progress import Progress, Task
from scg_algorithms.rl.policy import policy_controller
from scg_algorithms.tune import SEARCH_SPACES, Param, objective_value, tune
from scg_algorithms.tune.population import make_population_train, stack_values
from scg_cli import main
from scg_jax.config import load_config, make_from_config

TINY_PPO = {"total_env_steps": 1024, "num_envs": 8, "rollout_length": 16, "num_minibatches": 2,
            "actor_hidden": [16, 16], "critic_hidden": [16, 16]}  # fmt: skip
CONFIG = {"env": {"system": "cartpole", "reward_type": "exponential"}, "training": {"ppo": TINY_PPO}}
SPACE = (
    Param("learning_rate", 1e-4, 3e-3, log=True, traced=True),
    Param("clip_eps", 0.1, 0.3, traced=True),
    Param("num_epochs", 1, 2, integer=True),
)
EPISODES = 4


def _rows(path):
    with open(path, newline="") as file:
        return list(csv.DictReader(file))


# --------------------------------------------------------------------------------------------- objective
def test_cvar_objective_is_the_mean_of_the_worst_share():
    per_episode = {"rmse": np.array([1.0, 4.0, 2.0, 3.0]), "return": np.array([10.0, 4.0, 6.0, 8.0])}
    assert objective_value(per_episode, "rmse", 0.5) == pytest.approx(3.5)  # the two largest: (4 + 3) / 2
    assert objective_value(per_episode, "rmse", 1.0) == pytest.approx(2.5)  # the mean
    assert objective_value(per_episode, "rmse", 0.25) == pytest.approx(4.0)  # the worst episode
    # 0.375 of 4 episodes is 1.5: the worst whole and half the next, (4 + 0.5 * 3) / 1.5.
    assert objective_value(per_episode, "rmse", 0.375) == pytest.approx(5.5 / 1.5)
    # The return's worst tail is its lowest values: (4 + 6) / 2; a higher objective is better.
    assert objective_value(per_episode, "return", 0.5) == pytest.approx(5.0)
    assert objective_value(per_episode, "return", 0.25) == pytest.approx(4.0)
    with pytest.raises(ValueError, match="metric: unknown value 'cost'"):
        objective_value(per_episode, "cost", 0.5)


# --------------------------------------------------------------------------------------------- a study
@pytest.fixture(scope="module")
def study(tmp_path_factory):
    """Two PPO trials with tiny budgets, trained alone (``train_run``)."""
    out = tmp_path_factory.mktemp("tune") / "study"
    notes = []
    result = tune("ppo", CONFIG, out, trials=2, eval_episodes=EPISODES, space=SPACE,
                  progress=Progress(note=notes.append))  # fmt: skip
    return out, result, notes


def test_the_best_config_trains_to_the_best_trials_score(study, tmp_path):
    out, result, notes = study
    rows = _rows(out / "trials.csv")
    assert [row["state"] for row in rows] == ["complete", "complete"] and len(notes) == 2
    values = [float(row["value"]) for row in rows]
    assert result.finished == 2 and result.best["value"] == min(values)
    best = rows[result.best["number"]]
    # Each trial's objective is the CVaR at 0.5 of its own evaluation's per-episode RMSE (its run's metrics.json).
    for row in rows:
        record = json.loads((out / "trials" / f"{int(row['number']):04d}" / "metrics.json").read_text())
        assert float(row["value"]) == objective_value(record["evaluation"]["per_episode"], "rmse", 0.5)
    cfg = load_config(out / "best.yaml")
    assert cfg.training["ppo"]["learning_rate"] == float(best["learning_rate"])
    assert cfg.training["ppo"]["num_epochs"] == int(best["num_epochs"])
    assert cfg.training["ppo"]["total_env_steps"] == TINY_PPO["total_env_steps"]  # the rest of the section kept
    run = tmp_path / "run"
    argv = ["train", "--algo", "ppo", "--config", str(out / "best.yaml"), "--out", str(run), "--eval-episodes",
            str(EPISODES), "--progress-interval", "600"]  # fmt: skip
    assert main(argv) == 0
    evaluation = json.loads((run / "metrics.json").read_text())["evaluation"]
    assert evaluation["worst_case_rmse_at_0.5"] == result.best["value"]  # same seed, same number


def test_a_study_resumes_and_refuses_other_settings(study, tmp_path):
    out, first, _ = study
    copy = tmp_path / "study"
    shutil.copytree(out, copy)
    notes = []
    result = tune("ppo", CONFIG, copy, trials=3, eval_episodes=EPISODES, space=SPACE,
                  progress=Progress(note=notes.append))  # fmt: skip
    rows = _rows(copy / "trials.csv")
    assert result.finished == 3 and [row["number"] for row in rows] == ["0", "1", "2"]
    assert [row["value"] for row in rows[:2]] == [row["value"] for row in _rows(out / "trials.csv")]
    assert len(notes) == 1 and notes[0].startswith("trial 2: CVaR 0.5 of rmse")
    assert result.best["value"] <= first.best["value"]
    with pytest.raises(ValueError, match=r"^out_dir: .* holds a study with other settings \(alpha: 0.5 there, 0.25"):
        tune("ppo", CONFIG, copy, trials=4, alpha=0.25, eval_episodes=EPISODES, space=SPACE)
    # Enough trials already: nothing runs.
    again = tune("ppo", CONFIG, copy, trials=3, eval_episodes=EPISODES, space=SPACE)
    assert again.finished == 3 and again.best == result.best


# --------------------------------------------------------------------------------------------- populations
def test_population_members_score_what_their_settings_score_alone(tmp_path):
    out = tmp_path / "population"
    result = tune("ppo", CONFIG, out, trials=2, population=2, eval_episodes=EPISODES, space=SPACE)
    rows = _rows(out / "trials.csv")
    assert result.finished == 2 and [row["population"] for row in rows] == ["2", "2"]
    assert rows[0]["num_epochs"] == rows[1]["num_epochs"]  # structural options are shared
    assert rows[0]["learning_rate"] != rows[1]["learning_rate"]  # traced ones differ
    cfg = load_config(CONFIG)
    env, params = make_from_config(cfg)
    train_key, eval_key = jax.random.split(jax.random.key(0))
    # The members' scores differ (their settings do); the second member, trained alone, scores what it scored in
    # the population (one training program compiled, not one per member: each member's settings are constants there).
    assert rows[0]["value"] != rows[1]["value"]
    for row in rows[1:]:
        options = {**TINY_PPO, "learning_rate": float(row["learning_rate"]), "clip_eps": float(row["clip_eps"]),
                   "num_epochs": int(row["num_epochs"])}  # fmt: skip
        config, learner = build_learner("ppo", options, env)
        state, _ = jax.jit(learner_part("ppo", "make_train")(config, env))(train_key, params)
        controller = policy_controller(env, params, learner, learner.policy_params(state))
        alone = evaluate(env, params, controller, eval_key, EPISODES, measure_time=False)
        np.testing.assert_allclose(float(row["value"]), objective_value(alone.per_episode, "rmse", 0.5), rtol=1e-4)


@pytest.mark.parametrize("algo", [name for name, spec in SEARCH_SPACES.items() if any(p.traced for p in spec)])
def test_every_traced_option_reaches_the_training_program(algo):
    """Each option a population varies is an input the traced training program computes with (an option that the
    learner dropped, or read as a Python number, would leave its input unused or fail to trace)."""
    env, params = make_from_config(load_config("configs/cartpole_stabilization.yaml"))
    names = tuple(p.name for p in SEARCH_SPACES[algo] if p.traced)
    config, _ = build_learner(algo, None, env)
    train = make_population_train(algo, config, env, names)
    values = stack_values([{name: getattr(config, name) for name in names}] * 2, names)
    keys = jnp.stack([jax.random.key(0)] * 2)
    jaxpr = jax.make_jaxpr(train)(keys, params, values).jaxpr
    value_vars = jaxpr.invars[-len(names) :]  # the dict's leaves, in sorted key order, come last
    used = {id(v) for eqn in jaxpr.eqns for v in eqn.invars} | {id(v) for v in jaxpr.outvars}
    unused = [name for name, var in zip(sorted(names), value_vars, strict=True) if id(var) not in used]
    assert unused == []


# --------------------------------------------------------------------------------------------- the driver
def _fake_train_run(curve_of):
    """A stand-in for ``train_run`` that reports a training curve ``curve_of(options)`` (10 points) through the
    progress and evaluates to 4 episodes of RMSE equal to the curve's last point: no training, only the driver."""

    def train_run(algo, cfg, folder, *, progress, eval_episodes, **_):
        options = dict(cfg.training[algo])
        curve = curve_of(options)
        progress.start(Task(algo, len(curve), 0, "iteration"))
        try:
            for i, value in enumerate(curve, start=1):
                progress.update(i, {"episode_rmse": value})
        finally:
            progress.done()
        rmse = np.full(eval_episodes, curve[-1])
        evaluation = types.SimpleNamespace(
            per_episode={"rmse": rmse, "return": -rmse},
            summary={"rmse": curve[-1], "return": -curve[-1], "failure_rate": 0.0},
        )
        return types.SimpleNamespace(evaluation=evaluation, training={"total_time_s": 0.0, "env_steps": 1})

    return train_run


def test_trials_worse_than_the_median_are_pruned(tmp_path, monkeypatch):
    # Trial k reports a flat training curve at k: after 5 completed trials (0..4, median 2) every later trial is
    # worse than the median at the third reported point, and stops there.
    counter = itertools.count()
    monkeypatch.setattr(runs, "train_run", _fake_train_run(lambda options: [float(next(counter))] * 10))
    space = (Param("learning_rate", 1e-4, 3e-3, log=True, traced=True),)
    result = tune("ppo", CONFIG, tmp_path / "s", trials=8, eval_episodes=EPISODES, space=space)
    study = optuna.load_study(study_name="scg-jax", storage=f"sqlite:///{tmp_path / 's' / 'study.db'}")
    assert result.finished == 8 and result.best["value"] == 0.0
    states = [trial.state for trial in study.trials]
    assert states == [optuna.trial.TrialState.COMPLETE] * 5 + [optuna.trial.TrialState.PRUNED] * 3
    assert [trial.value for trial in study.trials[:5]] == [0.0, 1.0, 2.0, 3.0, 4.0]
    assert [max(trial.intermediate_values) for trial in study.trials[5:]] == [3, 3, 3]
    assert [row["state"] for row in _rows(tmp_path / "s" / "trials.csv")][5:] == ["pruned"] * 3


def test_ctrl_c_keeps_the_study_and_the_same_command_continues_it(tmp_path, monkeypatch, capsys):
    out = tmp_path / "s"
    overrides = [arg for name, value in TINY_PPO.items() for arg in ("--set", f"training.ppo.{name}={value}")]
    argv = ["tune", "--algo", "ppo", "--system", "cartpole", "--trials", "2", "--out", str(out), *overrides]

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(runs, "train_run", interrupted)
    assert main(argv) == 130
    text = capsys.readouterr().out
    assert "interrupted after 0 of 2 trials" in text and "scg-jax tune --algo ppo" in text
    assert [row["state"] for row in _rows(out / "trials.csv")] == ["interrupted"]
    monkeypatch.setattr(runs, "train_run", _fake_train_run(lambda options: [options["clip_eps"]] * 10))
    assert main(argv) == 0
    rows = _rows(out / "trials.csv")
    assert [row["state"] for row in rows] == ["interrupted", "complete", "complete"]
    assert [float(row["value"]) for row in rows[1:]] == [float(row["clip_eps"]) for row in rows[1:]]
    assert "best of 2 trials" in capsys.readouterr().out


@pytest.mark.parametrize(
    ("flags", "message"),
    [
        (["--algo", "linear_mpc", "--population", "2"], "argument --population: a population trains JAX learners"),
        (["--algo", "ppo", "--alpha", "0"], "argument --alpha: expected a number in (0, 1]"),
        (["--algo", "rarl"], "argument --algo: invalid choice"),
    ],
)
def test_bad_tune_flags_exit_2_naming_the_flag(tmp_path, capsys, flags, message):
    assert main(["tune", "--system", "cartpole", "--trials", "1", "--out", str(tmp_path / "s"), *flags]) == 2
    assert message in capsys.readouterr().err
    assert not (tmp_path / "s").exists()


def test_tune_refuses_a_space_option_the_learner_lacks(tmp_path):
    with pytest.raises(ValueError, match=r"^space: .*'alpha_lr'.* not an option of training\.ppo"):
        tune("ppo", CONFIG, tmp_path / "s", trials=1, space=(Param("alpha_lr", 1e-4, 1e-3, traced=True),))
