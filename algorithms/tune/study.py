"""``tune``: a hyperparameter study of one method with Optuna, stored in a folder, resumable.

A *trial* trains the method with options drawn from its search space (``scg_algorithms.tune.spaces``) on top of the
config's section, evaluates the result on ``eval_episodes`` episodes drawn like the training ones, and scores it
with the objective: the CVaR at ``alpha`` of the per-episode RMSE (the mean of the worst ``alpha`` share, lower is
better) or of the per-episode return (the mean of the lowest ``alpha`` share, higher is better). Each trial trains
with the same ``seed``, so trials differ only in their options:

- a JAX learner or GP-MPC trains with ``scg_algorithms.train_run`` into ``out_dir/trials/NNNN`` (the same run as
  ``scg-jax train --config best.yaml --seed SEED --eval-episodes E``, so the best trial's score is reproduced to the
  last digit); its training curve is reported to the pruner;
- an MPC (``linear_mpc``, ``nonlinear_mpc``) is only evaluated, as ``scg-jax eval --controller NAME --seed SEED``;
- with ``population > 1`` (JAX learners), ``population`` trials train at once as one vmapped program
  (``scg_algorithms.tune.population``): the traced options differ between the members, the structural ones are the
  first member's. A member's score equals that setting trained alone to float rounding; population trials keep no
  folder.

Search: Optuna's TPE sampler (the first 5 trials random; a batch of a population sampled with the constant liar) and
a median pruner over the training curve (the training episodes' RMSE or return at 10 points of the budget: a
trial is stopped when it is worse than the median of the earlier trials at the same point, once 5 trials have
finished and from the third point on). Files in ``out_dir``:

- ``study.db``: the Optuna study (SQLite). Running ``tune`` again on the folder continues it until ``trials`` trials
  have finished (complete, pruned, or failed on invalid options); a trial cut short by Ctrl-C does not count.
- ``best.yaml``: the config with the best trial's options in the method's section (``scg-jax train --config``, or
  ``scg-jax eval --config`` for an MPC).
- ``trials.csv``: one row per trial: number, state, objective, the drawn options, the evaluation's mean RMSE,
  return and failure rate, and the error of a failed trial (written after every trial). ``trials.png``: the
  objective of every trial and the best so far (written when the study stops).

The library reports through a ``scg_algorithms.progress.Progress`` (a task counting trials, one note per trial) and
prints nothing; Optuna's own log lines are silenced while it runs.
"""

from __future__ import annotations

import contextlib
import csv as csv_lib
import dataclasses
import io
import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from scg_algorithms.learners import LEARNERS, learner_spec
from scg_algorithms.progress import Progress, Task, as_progress, running
from scg_algorithms.tune.spaces import SEARCH_SPACES, Param
from scg_jax.files import write_atomic
from scg_jax.metrics import cvar
from scg_jax.validation import FieldError

STUDY_FILE, BEST_FILE, TRIALS_FILE, PLOT_FILE = "study.db", "best.yaml", "trials.csv", "trials.png"
TUNE_FILES = (STUDY_FILE, BEST_FILE, TRIALS_FILE, PLOT_FILE)
STUDY_NAME = "scg-jax"
OBJECTIVES = {"rmse": "minimize", "return": "maximize"}
"""Objective metric -> Optuna's direction."""
REPORT_POINTS = 10
"""Points of the training budget at which a trial's training curve is reported to the pruner."""
STARTUP_TRIALS = 5
"""Trials drawn at random before TPE models the results, and finished trials before the pruner stops any."""
SETTINGS = ("algo", "metric", "alpha", "eval_episodes", "seed", "config")
"""What a study is stored with and must be resumed with (``population`` may change between runs)."""
ARGUMENT_WORDS = {"algo": "algo", "out_dir": "out_dir", "trials": "trials", "population": "population"}


def objective_value(per_episode: Mapping, metric: str, alpha: float) -> float:
    """The CVaR at ``alpha`` of the worst tail of ``per_episode[metric]`` (``scg_jax.metrics.cvar``).

    ``rmse``: the mean of the largest ``alpha`` share of the episodes' RMSE (lower is better). ``return``: the mean of
    the smallest ``alpha`` share of their returns (higher is better). ``alpha = 1`` is the plain mean.

    Args:
        per_episode: ``{"rmse": (n,), "return": (n,)}`` (an ``Evaluation.per_episode``). metric: ``rmse`` or
            ``return``. alpha: tail share in (0, 1].
    """
    if metric not in OBJECTIVES:
        raise FieldError("metric", f"unknown value {metric!r}; allowed values are {', '.join(OBJECTIVES)}")
    if metric == "rmse":
        return cvar(per_episode["rmse"], alpha)
    return -cvar(-np.asarray(per_episode["return"], dtype=np.float64), alpha)


class TuneInterrupted(KeyboardInterrupt):
    """Ctrl-C during ``tune``: the trials in flight are stored as failed (they do not count), the files written
    from the finished ones; running ``tune`` again continues the study.

    Attributes:
        out_dir: the study's folder. finished: trials finished so far. trials: the number asked for.
    """

    def __init__(self, out_dir: Path, finished: int, trials: int):
        super().__init__(f"tuning interrupted after {finished} of {trials} trials")
        self.out_dir, self.finished, self.trials = out_dir, finished, trials


@dataclasses.dataclass(frozen=True)
class TuneResult:
    """What ``tune`` returns.

    Attributes:
        algo: the method. out_dir: the study's folder. finished: trials finished in the study (all runs).
        best: the best trial: ``{"number", "value", "params", "options"}`` (``options``: the method's whole section
            as ``best.yaml`` holds it), or None when no trial completed. files: the files written in ``out_dir``.
    """

    algo: str
    out_dir: Path
    finished: int
    best: dict | None
    files: tuple[str, ...]


# --------------------------------------------------------------------------------------------- the method
@dataclasses.dataclass(frozen=True)
class _Study:
    """One ``tune`` call, checked: the method, the env and what every trial shares."""

    algo: str
    kind: str  # "jax", "gp_mpc" or "controller"
    section: str
    space: tuple[Param, ...]
    cfg: Any
    env: Any
    params: Any
    out_dir: Path
    trials: int
    population: int
    seed: int
    metric: str
    alpha: float
    eval_episodes: int
    progress: Progress

    @property
    def base_options(self) -> dict:
        """The method's section of the config (its options before a trial changes some)."""
        group, name = self.section.split(".")
        return dict(getattr(self.cfg, group).get(name) or {})


def tunable_methods() -> tuple[str, ...]:
    """The methods with a search space: ``scg-jax tune --algo`` choices."""
    return tuple(SEARCH_SPACES)


def _kind(algo: str) -> str:
    if algo in LEARNERS:
        return "jax" if learner_spec(algo).is_jax else learner_spec(algo).kind
    return "controller"


def _section(algo: str) -> str:
    return learner_spec(algo).section if algo in LEARNERS else f"controllers.{algo}"


def _check_arguments(algo, trials, population, seed, metric, alpha, eval_episodes) -> None:
    if algo not in SEARCH_SPACES:
        raise FieldError("algo", f"no search space for {algo!r}; the methods to tune are {', '.join(SEARCH_SPACES)}")
    for name, value in (("trials", trials), ("population", population), ("eval_episodes", eval_episodes)):
        if isinstance(value, bool) or not isinstance(value, int) or value < 1:
            raise FieldError(name, f"must be a positive integer, got {value!r}")
    if isinstance(seed, bool) or not isinstance(seed, int):
        raise FieldError("seed", f"must be an integer, got {seed!r}")
    if metric not in OBJECTIVES:
        raise FieldError("metric", f"unknown value {metric!r}; allowed values are {', '.join(OBJECTIVES)}")
    if isinstance(alpha, bool) or not isinstance(alpha, int | float) or not 0.0 < alpha <= 1.0:
        raise FieldError("alpha", f"must be in (0, 1], got {alpha!r}")
    if population > 1 and _kind(algo) != "jax":
        jax_tunable = ", ".join(name for name in SEARCH_SPACES if _kind(name) == "jax")
        raise FieldError("population", f"a population trains JAX learners ({jax_tunable}); {algo} has none")


def _check_base_options(study: _Study) -> None:
    """The config's own section must be valid, or every trial would fail: checked before the study starts."""
    if study.kind == "jax":
        from scg_algorithms.learners import build_learner

        config, _ = build_learner(study.algo, study.base_options, study.env)
        options = [field.name for field in dataclasses.fields(config)]
        for param in study.space:
            if param.name not in options:
                raise FieldError("space", f"{param.name!r} is not an option of {study.section}; its options are "
                                          f"{', '.join(options)}")  # fmt: skip
    elif study.kind == "gp_mpc":
        from scg_algorithms.base import parse_options
        from scg_algorithms.gp_mpc.controller import PATH, Options

        parse_options(Options, study.base_options, PATH)
    else:
        from scg_algorithms import make_controller

        make_controller(study.algo, study.env, study.params, study.base_options)


# --------------------------------------------------------------------------------------------- drawing options
def _size(param: Param, env) -> int:
    return {"nx": env.nx, "nu": env.nu}[param.size]


def _suggest_one(trial, name: str, param: Param):
    if param.choices:
        return trial.suggest_categorical(name, list(param.choices))
    if param.integer:
        return trial.suggest_int(name, int(param.low), int(param.high), log=param.log)
    return trial.suggest_float(name, float(param.low), float(param.high), log=param.log)


def suggest(trial, space: tuple[Param, ...], env) -> dict:
    """The options of one trial, drawn by ``trial`` (an ``optuna.Trial``), as the method's section holds them: a
    width as hidden sizes (``[64, 64]``), a diagonal as a list (``q_diag: [q_0, ..., q_{nx-1}]``)."""
    options = {}
    for param in space:
        if param.size is not None:
            options[param.name] = [_suggest_one(trial, f"{param.name}_{i}", param) for i in range(_size(param, env))]
            continue
        value = _suggest_one(trial, param.name, param)
        options[param.name] = [value] * param.layers if param.layers else value
    return options


def _structural_params(trial, space: tuple[Param, ...], env) -> dict:
    """The Optuna parameters of ``trial`` that a population shares (the options that are not ``traced``)."""
    names = []
    for param in space:
        if not param.traced:
            names += [f"{param.name}_{i}" for i in range(_size(param, env))] if param.size else [param.name]
    return {name: trial.params[name] for name in names}


def trial_config(study: _Study, options: Mapping):
    """The config of a trial: the study's config with ``options`` set in the method's section."""
    from scg_jax.config import load_config

    return load_config(study.cfg, values={f"{study.section}.{name}": value for name, value in options.items()})


# --------------------------------------------------------------------------------------------- one trial
class _PruningProgress:
    """The progress of a trial's training run, forwarded to the study's ``Progress``, that reports the training
    curve (the latest ``episode_<metric>``) to the pruner at ``REPORT_POINTS`` points of the budget and stops the
    run (``optuna.TrialPruned``) when the pruner says so."""

    def __init__(self, outer: Progress, trial, metric: str, unit: str):
        self.outer, self.trial, self.metric, self.unit = outer, trial, metric, unit
        self.tasks: list[Task] = []
        self.reported = 0

    def start(self, task: Task) -> None:
        self.tasks.append(task)
        self.outer.start(task)

    def done(self) -> None:
        if self.tasks:
            self.tasks.pop()
        self.outer.done()

    def update(self, completed: int, info: Mapping) -> None:
        self.outer.update(completed, info)
        task = self.tasks[-1] if self.tasks else None
        if task is None or task.unit != self.unit or not task.total:
            return
        value = info.get(f"episode_{self.metric}")
        point = completed * REPORT_POINTS // task.total
        if value is None or not math.isfinite(value) or point <= self.reported:
            return
        import optuna

        self.reported = point
        self.trial.report(float(value), point)
        if self.trial.should_prune():
            raise optuna.TrialPruned(f"pruned at {point}/{REPORT_POINTS} of the budget")

    def as_progress(self) -> Progress:
        return Progress(start=self.start, update=self.update, done=self.done, note=self.outer.note)


def _evaluation_attrs(evaluation) -> dict:
    summary = evaluation.summary
    return {"rmse": summary["rmse"], "return": summary["return"], "failure_rate": summary["failure_rate"]}


def _train_trial(study: _Study, trial, options: dict) -> tuple[float, dict]:
    """A sequential trial: ``train_run`` (learners) or ``evaluate`` (MPC); ``(objective, user attributes)``."""
    import jax

    cfg = trial_config(study, options)
    if study.kind == "controller":
        from scg_algorithms import make_controller
        from scg_algorithms.evaluation import evaluate

        controller = make_controller(study.algo, study.env, study.params, cfg.controllers.get(study.algo))
        evaluation = evaluate(study.env, study.params, controller, jax.random.key(study.seed), study.eval_episodes,
                              measure_time=False, progress=study.progress)  # fmt: skip
        return objective_value(evaluation.per_episode, study.metric, study.alpha), _evaluation_attrs(evaluation)
    from scg_algorithms.runs import train_run

    folder = study.out_dir / "trials" / f"{trial.number:04d}"
    reporter = _PruningProgress(study.progress, trial, study.metric, learner_spec(study.algo).unit)
    result = train_run(study.algo, cfg, folder, seed=study.seed, eval_episodes=study.eval_episodes,
                       overwrite=True, progress=reporter.as_progress(),
                       record={"tune": {"out_dir": str(study.out_dir), "trial": trial.number}})  # fmt: skip
    attrs = {**_evaluation_attrs(result.evaluation), "folder": str(folder)}
    if study.kind == "jax":
        attrs.update(train_s=result.training["total_time_s"], env_steps=result.training["env_steps"])
    return objective_value(result.evaluation.per_episode, study.metric, study.alpha), attrs


# --------------------------------------------------------------------------------------------- a population
def _population_trials(study: _Study, optuna_study, size: int) -> list[tuple[Any, dict]]:
    """``size`` new trials whose structural options are the first one's: ``[(trial, options)]``."""
    first = optuna_study.ask()
    batch = [(first, suggest(first, study.space, study.env))]
    fixed = _structural_params(first, study.space, study.env)
    for _ in range(size - 1):
        optuna_study.enqueue_trial(fixed)
        trial = optuna_study.ask()
        batch.append((trial, suggest(trial, study.space, study.env)))
    return batch


def _train_population(study: _Study, batch: list[tuple[Any, dict]], cache: dict) -> list[tuple[float, dict, Any]]:
    """Train ``batch`` as one population; ``[(objective, user attributes, training curve (iterations,))]``."""
    import jax

    from scg_algorithms.evaluation import evaluate
    from scg_algorithms.learners import build_learner
    from scg_algorithms.rl.policy import policy_controller
    from scg_algorithms.tune import population

    names = tuple(param.name for param in study.space if param.traced)
    configs = population.check_members(study.algo, _learner_config(study, batch[0][1]),
                                       [options for _, options in batch])  # fmt: skip
    # The traced options at their defaults: the structure alone, so one compiled program serves every population
    # of the same structural options (and size).
    defaults = type(configs[0])()
    structure = dataclasses.replace(configs[0], **{name: getattr(defaults, name) for name in names})
    key = (structure, len(batch))
    if key not in cache:
        cache.clear()  # one program at a time: a population of other structural options compiles anew
        cache[key] = jax.jit(population.make_population_train(study.algo, structure, study.env, names))
    train_key, eval_key = jax.random.split(jax.random.key(study.seed))
    values = population.stack_values([{name: getattr(c, name) for name in names} for c in configs], names)
    keys = jax.numpy.stack([train_key] * len(batch))
    with running(study.progress, Task(f"population of {len(batch)} {study.algo} trials")):
        states, metrics = jax.block_until_ready(cache[key](keys, study.params, values))
    results = []
    for index, config in enumerate(configs):
        _, learner = build_learner(study.algo, config, study.env)
        policy_params = learner.policy_params(population.member(states, index))
        controller = policy_controller(study.env, study.params, learner, policy_params)
        evaluation = evaluate(study.env, study.params, controller, eval_key, study.eval_episodes,
                              measure_time=False, progress=study.progress)  # fmt: skip
        value = objective_value(evaluation.per_episode, study.metric, study.alpha)
        curve = np.asarray(metrics[f"episode_{study.metric}"][index], dtype=np.float64)
        results.append((value, {**_evaluation_attrs(evaluation), "population": len(batch)}, curve))
    return results


def _learner_config(study: _Study, options: Mapping):
    from scg_algorithms.learners import build_learner

    cfg = trial_config(study, options)
    return build_learner(study.algo, cfg.training.get(study.algo), study.env)[0]


def _report_curve(trial, curve: np.ndarray) -> None:
    """A population member's training curve at the pruner's points (after the fact: it is not pruned, but later
    trials are compared with it)."""
    for point in range(1, REPORT_POINTS + 1):
        value = curve[max(0, point * len(curve) // REPORT_POINTS - 1)]
        if math.isfinite(value):
            trial.report(float(value), point)


# --------------------------------------------------------------------------------------------- the study
@contextlib.contextmanager
def _quiet_optuna():
    """Optuna's log lines silenced (the library prints nothing), its level restored after."""
    import optuna

    level = optuna.logging.get_verbosity()
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    try:
        yield optuna
    finally:
        optuna.logging.set_verbosity(level)


def _settings(study: _Study) -> dict:
    from scg_jax.config import dump_config

    return {"algo": study.algo, "metric": study.metric, "alpha": float(study.alpha),
            "eval_episodes": study.eval_episodes, "seed": study.seed, "config": dump_config(study.cfg)}  # fmt: skip


def _open_study(optuna, study: _Study, words: Mapping[str, str]):
    """The folder's study (created, or loaded and checked against this call's settings)."""
    out_dir = study.out_dir
    existing = (out_dir / STUDY_FILE).exists()
    others = [name for name in TUNE_FILES[1:] if (out_dir / name).exists()]
    if not existing and others:
        raise FieldError("out_dir", f"{out_dir} holds {', '.join(others)} but no {STUDY_FILE} to continue; use "
                                    f"another {words['out_dir']} or remove them")  # fmt: skip
    out_dir.mkdir(parents=True, exist_ok=True)
    storage = optuna.storages.RDBStorage(f"sqlite:///{(out_dir / STUDY_FILE).resolve()}")
    settings = _settings(study)
    if existing:
        opened = optuna.load_study(study_name=STUDY_NAME, storage=storage, sampler=_sampler(optuna, study, 0),
                                   pruner=_pruner(optuna))  # fmt: skip
        saved = opened.user_attrs.get("settings", {})
        differences = [
            "the config (env or sections)" if name == "config" else f"{name}: {saved.get(name)!r} there, {value!r} now"
            for name, value in settings.items()
            if saved.get(name) != value
        ]
        if differences:
            raise FieldError(
                "out_dir", f"{out_dir} holds a study with other settings ({'; '.join(differences)}); continue it "
                f"with the same ones or use another {words['out_dir']}"
            )  # fmt: skip
        opened.sampler = _sampler(optuna, study, len(opened.trials))
        return opened
    created = optuna.create_study(study_name=STUDY_NAME, storage=storage, direction=OBJECTIVES[study.metric],
                                  sampler=_sampler(optuna, study, 0), pruner=_pruner(optuna))  # fmt: skip
    created.set_user_attr("settings", settings)
    return created


def _sampler(optuna, study: _Study, trials_so_far: int):
    # Seeded with the trials so far: a resumed study draws new points, not the first run's again.
    return optuna.samplers.TPESampler(seed=study.seed + trials_so_far, n_startup_trials=STARTUP_TRIALS,
                                      constant_liar=True)  # fmt: skip


def _pruner(optuna):
    return optuna.pruners.MedianPruner(n_startup_trials=STARTUP_TRIALS, n_warmup_steps=3)


def _counts(optuna, trial) -> bool:
    """Whether a stored trial counts towards ``trials``: complete, pruned, or failed on its options (a failed
    trial without an ``error`` was interrupted)."""
    state = trial.state
    if state in (optuna.trial.TrialState.COMPLETE, optuna.trial.TrialState.PRUNED):
        return True
    return state == optuna.trial.TrialState.FAIL and "error" in trial.user_attrs


def _close_stale(optuna, optuna_study) -> None:
    """Trials left running by a process that was killed (not interrupted) are stored as interrupted."""
    for trial in optuna_study.get_trials(deepcopy=False, states=(optuna.trial.TrialState.RUNNING,)):
        optuna_study.tell(trial.number, state=optuna.trial.TrialState.FAIL)


def tune(
    algo: str,
    config,
    out_dir,
    *,
    trials: int,
    population: int = 1,
    seed: int = 0,
    metric: str = "rmse",
    alpha: float = 0.5,
    eval_episodes: int = 16,
    space: Sequence[Param] | None = None,
    progress=None,
    names: Mapping[str, str] | None = None,
) -> TuneResult:
    """Run (or continue) the study of ``algo`` in ``out_dir`` until ``trials`` trials have finished (module
    docstring).

    Args:
        algo: a method of ``SEARCH_SPACES`` (``tunable_methods()``).
        config: a ``scg_jax.Config`` (or what ``load_config`` reads): the env and the method's section, which every
            trial starts from (a smaller ``training.<algo>.total_env_steps`` makes trials cheaper).
        out_dir: the study's folder (created; an existing study in it is continued).
        trials: trials finished in the study when it stops (a continued study runs the rest).
        population: trials trained at once as one vmapped program (JAX learners).
        seed: the training and evaluation seed of every trial (and the sampler's).
        metric: ``rmse`` or ``return``; alpha: the CVaR's tail share in (0, 1] (1: the mean).
        eval_episodes: evaluation episodes per trial.
        space: the options to search (default ``SEARCH_SPACES[algo]``; e.g. only its learning rates).
        progress: a ``scg_algorithms.progress.Progress`` (or a function, its ``update``); None: silent.
        names: how error messages name the arguments ``algo``, ``out_dir``, ``trials``, ``population`` (the command
            line passes its flags).

    Returns:
        ``TuneResult``.

    Raises:
        ValueError (mostly ``FieldError``): a bad argument, an invalid section in the config, a folder holding a
            study of other settings. TuneInterrupted (a KeyboardInterrupt): Ctrl-C.
    """
    from scg_jax.config import Config, load_config, make_from_config

    _check_arguments(algo, trials, population, seed, metric, alpha, eval_episodes)
    cfg = config if isinstance(config, Config) else load_config(config)
    env, params = make_from_config(cfg)
    space = SEARCH_SPACES[algo] if space is None else tuple(space)
    study = _Study(algo, _kind(algo), _section(algo), space, cfg, env, params, Path(out_dir),
                   trials, population, seed, metric, float(alpha), eval_episodes, as_progress(progress))  # fmt: skip
    _check_base_options(study)
    words = {**ARGUMENT_WORDS, **dict(names or {})}
    with _quiet_optuna() as optuna:
        optuna_study = _open_study(optuna, study, words)
        _close_stale(optuna, optuna_study)
        finished = sum(_counts(optuna, trial) for trial in optuna_study.trials)
        with running(study.progress, Task(f"tuning {algo}", trials, min(finished, trials), "trial")):
            finished = _run_trials(optuna, study, optuna_study, finished)
        files = write_outputs(study, optuna_study)
        return TuneResult(algo, study.out_dir, finished, _best(optuna, optuna_study), files)


def _run_trials(optuna, study: _Study, optuna_study, finished: int) -> int:
    """Trials (or populations of them) until ``study.trials`` have finished; Ctrl-C stores the trials in flight
    as interrupted, writes the files and raises ``TuneInterrupted``."""
    cache: dict = {}
    while finished < study.trials:
        size = min(study.population, study.trials - finished)
        in_flight: list = []
        try:
            if size > 1:
                batch = _population_trials(study, optuna_study, size)
                in_flight = [trial for trial, _ in batch]
                outcomes = _population_outcomes(study, batch, cache)
            else:
                trial = optuna_study.ask()
                in_flight = [trial]
                options = suggest(trial, study.space, study.env)
                outcomes = [_sequential_outcome(optuna, study, trial, options)]
        except BaseException as error:  # the trials in flight are stored as interrupted (they do not count)
            for trial in in_flight:
                optuna_study.tell(trial, state=optuna.trial.TrialState.FAIL)
            if not isinstance(error, KeyboardInterrupt):
                raise
            write_outputs(study, optuna_study)
            raise TuneInterrupted(study.out_dir, finished, study.trials) from None
        for trial, (state, value, attrs, note) in zip(in_flight, outcomes, strict=True):
            for name, attr in attrs.items():
                trial.set_user_attr(name, attr)
            optuna_study.tell(trial, value if state == optuna.trial.TrialState.COMPLETE else None, state=state)
            finished += 1
            study.progress.note(f"trial {trial.number}: {note}")
        write_outputs(study, optuna_study, plot=False)
        best = _best(optuna, optuna_study)
        study.progress.update(min(finished, study.trials), {} if best is None else {"best": best["value"]})
    return finished


def _describe(options: Mapping) -> str:
    def show(value):
        if isinstance(value, list):
            return "[" + ", ".join(show(v) for v in value) + "]"
        return f"{value:.4g}" if isinstance(value, float) else str(value)

    return ", ".join(f"{name}={show(value)}" for name, value in options.items())


def _sequential_outcome(optuna, study: _Study, trial, options: dict):
    """``(state, objective, user attributes, note)`` of one trial trained alone."""
    name = f"CVaR {study.alpha:g} of {study.metric}"
    try:
        value, attrs = _train_trial(study, trial, options)
    except optuna.TrialPruned as pruned:
        return optuna.trial.TrialState.PRUNED, None, {"options": options}, f"{pruned} ({_describe(options)})"
    except ValueError as error:  # options the method refuses (e.g. minibatches that do not divide the batch)
        return optuna.trial.TrialState.FAIL, None, {"options": options, "error": str(error)}, f"failed: {error}"
    if not math.isfinite(value):
        return optuna.trial.TrialState.FAIL, None, {**attrs, "options": options, "error": "objective not finite"}, (
            f"failed: the {name} is {value}")  # fmt: skip
    note = f"{name} {value:.4g} ({_describe(options)})"
    return optuna.trial.TrialState.COMPLETE, value, {**attrs, "options": options}, note


def _population_outcomes(study: _Study, batch, cache: dict):
    import optuna

    name = f"CVaR {study.alpha:g} of {study.metric}"
    try:
        results = _train_population(study, batch, cache)
    except ValueError as error:  # a member's options refused: the whole population fails
        return [(optuna.trial.TrialState.FAIL, None, {"options": options, "error": str(error)}, f"failed: {error}")
                for _, options in batch]  # fmt: skip
    outcomes = []
    for (trial, options), (value, attrs, curve) in zip(batch, results, strict=True):
        _report_curve(trial, curve)
        state = optuna.trial.TrialState.COMPLETE if math.isfinite(value) else optuna.trial.TrialState.FAIL
        note = f"{name} {value:.4g} (population; {_describe(options)})"
        outcomes.append((state, value, {**attrs, "options": options}, note))
    return outcomes


# --------------------------------------------------------------------------------------------- outputs
def _best(optuna, optuna_study) -> dict | None:
    completed = [t for t in optuna_study.trials if t.state == optuna.trial.TrialState.COMPLETE]
    if not completed:
        return None
    best = optuna_study.best_trial
    return {"number": best.number, "value": best.value, "params": dict(best.params),
            "options": dict(best.user_attrs.get("options", {}))}  # fmt: skip


def write_outputs(study: _Study, optuna_study, plot: bool = True) -> tuple[str, ...]:
    """``trials.csv``, (once a trial completed) ``best.yaml`` and, with ``plot``, ``trials.png``, each written
    whole. The files are written after every trial, the plot when the study stops."""
    import optuna

    trials = optuna_study.trials
    _write_trials_csv(study.out_dir / TRIALS_FILE, trials)
    files = [STUDY_FILE, TRIALS_FILE]
    if plot:
        _plot_trials(study, trials, study.out_dir / PLOT_FILE)
        files.append(PLOT_FILE)
    best = _best(optuna, optuna_study)
    if best is not None:
        _write_best(study, best, len(trials))
        files.insert(1, BEST_FILE)
    return tuple(files)


_ATTR_COLUMNS = ("rmse", "return", "failure_rate", "train_s", "env_steps", "population", "folder", "error")


def _write_trials_csv(path: Path, trials) -> None:
    params = sorted({name for trial in trials for name in trial.params})
    header = ["number", "state", "value", *params, *_ATTR_COLUMNS]
    text = io.StringIO()
    writer = csv_lib.writer(text, lineterminator="\n")
    writer.writerow(header)
    for trial in trials:
        attrs = trial.user_attrs
        state = trial.state.name.lower()
        if state == "fail":
            state = "failed" if "error" in attrs else "interrupted"
        row = [trial.number, state, "" if trial.value is None else repr(float(trial.value))]
        row += [trial.params.get(name, "") for name in params]
        row += [attrs.get(name, "") for name in _ATTR_COLUMNS]
        writer.writerow(row)
    write_atomic(path, lambda file: file.write(text.getvalue().encode()))


def _write_best(study: _Study, best: dict, num_trials: int) -> None:
    from scg_jax.config import dump_config

    header = (f"# scg-jax tune --algo {study.algo}: the best of {num_trials} trials (trial {best['number']}), CVaR "
              f"{study.alpha:g} of the evaluation {study.metric} {best['value']:.6g} on {study.eval_episodes} "
              f"episodes, seed {study.seed}.\n# Its options are in {study.section}.\n")  # fmt: skip
    text = header + dump_config(trial_config(study, best["options"]))
    write_atomic(study.out_dir / BEST_FILE, lambda file: file.write(text.encode()))


def _plot_trials(study: _Study, trials, path: Path) -> None:
    """The objective of each completed trial (dots), pruned ones at their last reported value (crosses), and the
    best so far (a step line)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(6.4, 3.6), layout="constrained")
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 1, 1)
    done = [(t.number, t.value) for t in trials if t.value is not None]
    pruned = [(t.number, t.intermediate_values[max(t.intermediate_values)]) for t in trials
              if t.state.name == "PRUNED" and t.intermediate_values]  # fmt: skip
    if done:
        numbers, values = np.array(done).T
        ax.plot(numbers, values, "o", label="trial")
        better = np.minimum if study.metric == "rmse" else np.maximum
        ax.step(numbers, better.accumulate(values), where="post", label="best so far")
    if pruned:
        ax.plot(*np.array(pruned).T, "x", color="grey", label="pruned (training curve)")
    ax.set_xlabel("trial")
    ax.set_ylabel(f"CVaR {study.alpha:g} of the {study.metric}")
    ax.set_title(f"{study.algo} on the {study.env.system.name} ({study.env.task})", fontsize=10)
    ax.grid(alpha=0.3)
    if done or pruned:
        ax.legend(fontsize=8)
    write_atomic(path, lambda file: fig.savefig(file, format="png", dpi=100))
