"""``train_run``: the one way to train a learner into a folder, used by ``scg-jax train`` and the reproduction.

Any learner of ``scg_algorithms.learners.LEARNERS`` trains the same way: ``train_run(algo, config, out_dir, ...)``
builds the env of the config, trains with the learner's options from the config (``training.<algo>``,
``controllers.gp_mpc``, ``safety_filters.learned_cbf``), saves the result (the JAX learners through
``scg_algorithms.rl.training.run_training``: policy, checkpoints, ``progress.csv``, learning curve), then
optionally evaluates it with the common harness and writes ``metrics.json`` (the command, config, seed, the
learner's own entries and the evaluation). It reports through a ``scg_algorithms.progress.Progress`` and prints
nothing.

Folder rules: a folder that holds a run is refused unless ``resume`` (JAX learners: continue from the checkpoint,
bit-identical to an uninterrupted run) or ``overwrite`` is given. Ctrl-C raises ``TrainingInterrupted`` (after
saving a checkpoint) during training, ``EvaluationInterrupted`` during the final evaluation (the trained result is
saved), and a plain ``KeyboardInterrupt`` during GP-MPC's rounds or the learned CBF's episodes (nothing saved).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from scg_algorithms.learners import GP_MPC, JAX, LEARNED_CBF, LearnerSpec, learner_spec, prior_learners
from scg_algorithms.progress import Progress, Task, as_progress, running
from scg_jax.validation import FieldError


class EvaluationInterrupted(KeyboardInterrupt):
    """Ctrl-C during ``train_run``'s final evaluation; what was trained is saved in ``out_dir``."""

    def __init__(self, out_dir: Path):
        super().__init__(f"interrupted during the final evaluation; the trained result is saved in {out_dir}")
        self.out_dir = out_dir


@dataclasses.dataclass(frozen=True)
class TrainResult:
    """What ``train_run`` returns.

    Attributes:
        algo: the learner. out_dir: its folder. system, task: the env's.
        files: the files written in ``out_dir`` (``metrics.json`` last, when written).
        training: the JAX learners' ``run_training`` summary (``iterations``, ``env_steps``, ``total_time_s``,
            ``resumed_from_iteration``, ...); GP-MPC's ``{"rounds", "history"}`` (one entry per round, round 0
            the prior's MPC); the learned CBF's ``{"episodes", "history"}``.
        evaluation: the final ``scg_algorithms.evaluation.Evaluation``, or None (``eval_episodes=None``).
        record: what ``metrics.json`` holds, or None where none was written (no evaluation, or not process 0).
    """

    algo: str
    out_dir: Path
    system: str
    task: str
    files: tuple[str, ...]
    training: dict
    evaluation: Any = None
    record: dict | None = None


@dataclasses.dataclass(frozen=True)
class _Job:
    """One ``train_run`` call's arguments, checked, with the env built."""

    spec: LearnerSpec
    cfg: Any
    env: Any
    params: Any
    out_dir: Path
    seed: int
    resume: bool
    overwrite: bool
    checkpoint_seconds: float
    eval_episodes: int | None
    prior_scale: float
    mesh: Any
    progress: Progress
    record: Mapping
    words: Mapping[str, str]


def train_run(
    algo: str,
    config,
    out_dir,
    *,
    seed: int = 0,
    total_env_steps: int | None = None,
    resume: bool = False,
    overwrite: bool = False,
    checkpoint_seconds: float = 60.0,
    eval_episodes: int | None = 16,
    prior_scale: float = 1.0,
    mesh=None,
    progress=None,
    record: Mapping | None = None,
    names: Mapping[str, str] | None = None,
) -> TrainResult:
    """Train the learner ``algo`` on the env of ``config`` into ``out_dir`` (module docstring).

    Args:
        algo: a name of ``scg_algorithms.learners.LEARNERS``.
        config: a ``scg_jax.Config`` (or what ``scg_jax.load_config`` reads: a path, YAML text, a mapping): its
            env, and the learner's options in its section (``training.<algo>``; ``controllers.gp_mpc``;
            ``safety_filters.learned_cbf``).
        out_dir: the run's folder (created).
        seed: the PRNG seed; the same seed trains the same result. The JAX learners train with the first half of
            ``split(key(seed))`` and are evaluated with the second; GP-MPC and the learned CBF take ``seed`` as
            their ``seed`` option and are evaluated with ``key(seed + 1)``.
        total_env_steps: the JAX learners' budget, replacing ``training.<algo>.total_env_steps`` (None: the
            config's).
        resume: continue the JAX learner's run in ``out_dir`` from its checkpoint (same algorithm, options and env;
            ``total_env_steps`` may be raised); bit-identical to an uninterrupted run. overwrite: replace the run
            in ``out_dir``. Without either, a folder holding a run is refused.
        checkpoint_seconds: the JAX learners' checkpoint interval (also at the end and on Ctrl-C).
        eval_episodes: episodes of the final evaluation (written to ``metrics.json``); None: no evaluation.
        prior_scale: GP-MPC and the learned CBF learn on a prior model with every inertial parameter times this.
        mesh: ``scg_jax.sharding.make_mesh(devices)`` for a JAX learner (``run_training``); with several processes
            the final evaluation is spread over them too and process 0 writes ``metrics.json``.
        progress: a ``scg_algorithms.progress.Progress`` (or a function, its ``update``); None: silent.
        record: extra entries of ``metrics.json`` (the command line adds ``config_file`` and ``overrides``).
        names: how error messages name the arguments ``algo``, ``out_dir``, ``resume``, ``overwrite`` (the command
            line passes its flags); the field a ``FieldError`` names is always the argument's.

    Returns:
        ``TrainResult``.

    Raises:
        ValueError (mostly ``scg_jax.validation.FieldError``, naming the argument or the config's dotted path):
            an unknown ``algo``, a bad option, an argument the learner does not take, a folder holding a run.
        TrainingInterrupted, EvaluationInterrupted, KeyboardInterrupt: Ctrl-C (module docstring).
    """
    from scg_algorithms.rl.training import ARGUMENT_WORDS
    from scg_jax.config import Config, load_config, make_from_config

    spec = learner_spec(algo)
    cfg = config if isinstance(config, Config) else load_config(config)
    progress = as_progress(progress)
    _check_arguments(spec, total_env_steps, resume, overwrite, eval_episodes, prior_scale, mesh)
    if total_env_steps is not None:
        cfg = load_config(cfg, values={f"{spec.section}.total_env_steps": int(total_env_steps)})
    env, params = make_from_config(cfg)
    job = _Job(spec, cfg, env, params, Path(out_dir), int(seed), bool(resume), bool(overwrite),
               float(checkpoint_seconds), eval_episodes, float(prior_scale), mesh, progress, dict(record or {}),
               {**ARGUMENT_WORDS, **dict(names or {})})  # fmt: skip
    return _TRAINERS[spec.kind](job)


def _check_arguments(spec, total_env_steps, resume, overwrite, eval_episodes, prior_scale, mesh) -> None:
    if resume and overwrite:
        raise FieldError("resume", "give resume or overwrite, not both (continue the run in out_dir, or replace it)")
    counted = isinstance(eval_episodes, int) and not isinstance(eval_episodes, bool) and eval_episodes >= 1
    if eval_episodes is not None and not counted:
        raise FieldError("eval_episodes", f"must be a positive integer or None, got {eval_episodes!r}")
    if spec.is_jax:
        if prior_scale != 1.0:
            learners = " and ".join(prior_learners())
            raise FieldError("prior_scale", f"only {learners} learn on a prior model; {spec.name} has none")
        return
    if not (isinstance(prior_scale, int | float) and math.isfinite(prior_scale) and prior_scale > 0):
        raise FieldError("prior_scale", f"must be a positive number, got {prior_scale!r}")
    if total_env_steps is not None:
        raise FieldError("total_env_steps", f"{spec.name} has no env-step budget; its options are {spec.section}")
    if mesh is not None:
        raise FieldError("mesh", f"{spec.name} trains in one process on one device; a mesh is for the JAX learners")


# --------------------------------------------------------------------------------------------- JAX learners
def _train_jax(job: _Job) -> TrainResult:
    """A JAX learner through ``run_training``; the final policy evaluated with the second half of the seed's key."""
    import jax

    from scg_algorithms.learners import build_learner
    from scg_algorithms.rl import training
    from scg_algorithms.rl.policy import load_policy
    from scg_jax import sharding
    from scg_jax.config import dump_config

    algo = job.spec.name
    config, learner = build_learner(algo, job.cfg.training.get(algo), job.env)
    distributed = job.mesh is not None and jax.process_count() > 1
    if distributed and job.eval_episodes is not None:  # the final evaluation's episodes are spread over processes
        sharding.check_divisible(job.eval_episodes, job.mesh, "eval_episodes")
    training.check_run_folder(job.out_dir, algo, job.resume, job.overwrite, job.words)
    train_key, eval_key = jax.random.split(jax.random.key(job.seed))
    summary = training.run_training(
        learner, job.env, job.params, train_key, job.out_dir, resume=job.resume, overwrite=job.overwrite,
        checkpoint_seconds=job.checkpoint_seconds, progress=job.progress, env_config=dump_config(job.cfg),
        mesh=job.mesh,
    )  # fmt: skip
    files = (f"{training.POLICY_NAME}.msgpack", training.CSV_NAME, training.CURVE_NAME)
    if job.eval_episodes is None:
        return _result(job, files, summary)
    policy = load_policy(job.out_dir, job.env, job.params)  # every process: run_training returns once it is written
    evaluation = _evaluate(job, policy, eval_key, job.mesh if distributed else None)
    if not sharding.is_main_process():  # process 0 writes metrics.json
        return _result(job, files, summary, evaluation)
    hyperparameters = dataclasses.asdict(config)
    return _write_metrics(job, files, summary, evaluation, hyperparameters=hyperparameters, training=summary,
                          device=str(jax.devices()[0]))  # fmt: skip


# --------------------------------------------------------------------------------------------- prior learners
def _train_gp_mpc(job: _Job) -> TrainResult:
    """GP-MPC's learning rounds (``scg_algorithms.gp_mpc.controller.learn``); ``gp_mpc.json/npz`` and the curve."""
    from scg_algorithms.base import parse_options
    from scg_algorithms.gp_mpc.controller import PATH, Options, learn
    from scg_algorithms.gp_mpc.run import RUN_NAME, save_run, write_learning_curve
    from scg_algorithms.rl.curves import rmse_label

    env, params = job.env, job.params
    opts = parse_options(Options, {**dict(job.cfg.controllers.get("gp_mpc") or {}), "seed": job.seed}, PATH)
    if opts.rounds < 1:
        raise FieldError(f"{PATH}.rounds", f"train needs at least one round, got {opts.rounds}")
    own = (f"{RUN_NAME}.json", f"{RUN_NAME}.npz", "learning_curve.csv")
    prior = _prior_folder_checks(job, own)
    intro = (f"gp_mpc on the {env.system.name} ({env.task}), prior scale {job.prior_scale:g}: {opts.rounds} rounds "
             f"of {opts.train_episodes} episodes, each evaluated on {opts.eval_episodes}")  # fmt: skip
    result = _learning_loop(job, opts.rounds, intro, lambda report: learn(env, params, prior, opts, progress=report),
                            lambda entry: f"round {entry['round']}: {entry['data_seconds']:.1f} s of data, RMSE "
                            f"{entry['rmse']:.4f} (std {entry['rmse_std']:.4f}), failure rate "
                            f"{entry['failure_rate']:.2f}, fit {entry['fit_s']:.1f} s, evaluation "
                            f"{entry['eval_s']:.1f} s")  # fmt: skip
    save_run(job.out_dir, result, opts, system=env.system.name, prior_scale=job.prior_scale, extra=_provenance(job))
    write_learning_curve(job.out_dir, result.history, rmse_label(env, params))
    files = (*own[:2], "learning_curve.csv", "learning_curve.png")
    return _evaluate_prior_learner(job, files, result.controller, opts, result.history)


def _train_learned_cbf(job: _Job) -> TrainResult:
    """The learned CBF's blending episodes (``train_learned_cbf``), saved; evaluated around random inputs."""
    from scg_algorithms.base import parse_options
    from scg_algorithms.safety_filters import filtered
    from scg_algorithms.safety_filters.learned_cbf import PATH, RUN_NAME, Options, save_run, train_learned_cbf
    from scg_algorithms.safety_filters.uncertified import random_input

    env, params = job.env, job.params
    opts = parse_options(Options, {**dict(job.cfg.safety_filters.get("learned_cbf") or {}), "seed": job.seed}, PATH)
    own = (f"{RUN_NAME}.json", f"{RUN_NAME}.msgpack")
    prior = _prior_folder_checks(job, own)
    intro = (f"learned_cbf on the {env.system.name}, prior scale {job.prior_scale:g}: {opts.num_episodes} blending "
             f"episodes of {opts.num_copies} copies x {env.num_steps} steps")  # fmt: skip
    result = _learning_loop(job, opts.num_episodes, intro,
                            lambda report: train_learned_cbf(env, params, prior, opts, progress=report),
                            lambda row: f"episode {row['episode']}: {row['data_seconds']:.0f} s of data, violating "
                            f"steps {100 * row['violation_fraction']:.3f} %, interventions "
                            f"{100 * row['intervention_fraction']:.1f} %")  # fmt: skip
    save_run(job.out_dir, result, system=env.system.name, prior_scale=job.prior_scale, extra=_provenance(job))
    controller = filtered(random_input(env, params), result.filter, env)
    files = (*own, "progress.csv", "learning_curve.png")
    return _evaluate_prior_learner(job, files, controller, opts, result.history)


def _prior_folder_checks(job: _Job, own: tuple[str, ...]):
    """Refuse ``resume`` (these runs are written whole at their end) and a folder holding a run without
    ``overwrite``; the prior model's params."""
    from scg_algorithms.rl.training import existing_run_files
    from scg_jax.env import prior_params

    words, algo = job.words, job.spec.name
    if job.resume:
        raise FieldError(
            "resume", f"a {algo} run is not resumable (it is written when its {job.spec.unit}s finish); use "
            f"{words['overwrite']}"
        )  # fmt: skip
    others = existing_run_files(job.out_dir)
    mine = [name for name in own if (job.out_dir / name).exists()]
    if (others or mine) and not job.overwrite:
        what = f"a training run of another algorithm ({', '.join(others)})" if others and not mine else "a run"
        raise FieldError("out_dir", f"{job.out_dir} already holds {what}; pass {words['overwrite']} to replace it")
    return job.params if job.prior_scale == 1.0 else prior_params(job.env, job.params, job.prior_scale)


def _learning_loop(job: _Job, total: int, intro: str, loop, line):
    """``loop(report)`` (GP-MPC's rounds, the learned CBF's episodes) as the task ``<algo>`` counting ``total``
    units, after the note ``intro``: each history entry it reports updates the count (``entry[unit]``) and becomes
    the note ``line(entry)``."""
    progress, unit = job.progress, job.spec.unit
    progress.note(intro)

    def report(entry):
        progress.update(entry[unit], entry)
        progress.note(line(entry))

    with running(progress, Task(job.spec.name, total, 0, unit)):
        return loop(report)


def _evaluate_prior_learner(job: _Job, files, controller, opts, history) -> TrainResult:
    import jax

    count = {"rounds" if job.spec.kind == GP_MPC else "episodes": len(history) - 1}
    training = {**count, "history": history}
    if job.eval_episodes is None:
        return _result(job, files, training)
    evaluation = _evaluate(job, controller, jax.random.key(job.seed + 1), None)
    return _write_metrics(job, files, training, evaluation, prior_scale=job.prior_scale,
                          options=dataclasses.asdict(opts), history=history)  # fmt: skip


# --------------------------------------------------------------------------------------------- shared
def _provenance(job: _Job) -> dict:
    """The config text and the overrides it came with, stored with a GP-MPC or learned CBF run."""
    from scg_jax.config import dump_config

    return {"config": dump_config(job.cfg), "overrides": list(job.record.get("overrides", []))}


def _evaluate(job: _Job, controller, key, mesh):
    """The final evaluation; Ctrl-C raises ``EvaluationInterrupted`` (the trained result is saved)."""
    from scg_algorithms.evaluation import evaluate

    try:
        return evaluate(job.env, job.params, controller, key, job.eval_episodes, mesh=mesh, progress=job.progress)
    except KeyboardInterrupt:
        raise EvaluationInterrupted(job.out_dir) from None


def _result(job: _Job, files, training, evaluation=None, record=None) -> TrainResult:
    return TrainResult(job.spec.name, job.out_dir, job.env.system.name, job.env.task, tuple(files), training,
                       evaluation, record)  # fmt: skip


def _write_metrics(job: _Job, files, summary, evaluation, **specific) -> TrainResult:
    """``metrics.json``: the run's command, config and seed, the learner's own entries and the evaluation."""
    from scg_algorithms.evaluation import evaluation_record
    from scg_algorithms.rl.training import json_ready
    from scg_jax.config import dump_config
    from scg_jax.files import write_json

    record = {
        "command": "train",
        "algo": job.spec.name,
        "system": job.env.system.name,
        "task": job.env.task,
        "config_file": None,
        "config": dump_config(job.cfg),
        "overrides": [],
        **job.record,
        "seed": job.seed,
        **json_ready(specific),
        "evaluation": evaluation_record(evaluation),
    }
    write_json(job.out_dir / "metrics.json", record)
    return _result(job, (*files, "metrics.json"), summary, evaluation, record)


_TRAINERS = {JAX: _train_jax, GP_MPC: _train_gp_mpc, LEARNED_CBF: _train_learned_cbf}
