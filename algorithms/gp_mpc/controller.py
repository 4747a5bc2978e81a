"""The GP-MPC controller and its learning loop.

``GPMPC`` is the nonlinear MPC (``scg_algorithms.mpc.nonlinear``: IPOPT, warm start, soft constraints, fallbacks) with
two arguments set: its prediction model is ``f_prior(x, u) + μ([x; u])`` (``model.learned_model``), and its env
constraints are tightened at every stage by the margins of ``model.PlanUncertainty``: the GP's variance propagated
along the warm-start plan under the prior's LQR gain, at chance level ``prob`` (Hewing et al. 2020).

``learn`` is the original suite's learning loop on the batched JAX environments: round 0 collects episodes of the
prior's LQR (about the goal, or about the reference on tracking tasks) with exploration noise (all copies at once);
every round fits the GP to all transitions so far, evaluates the resulting GP-MPC with the common harness, and
collects the next round's episodes with it.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from typing import NamedTuple

import jax
import numpy as np

from scg_algorithms import controller_setup as setup
from scg_algorithms import gp
from scg_algorithms.base import check_fields, option, parse_options
from scg_algorithms.evaluation import evaluate
from scg_algorithms.gp_mpc import data
from scg_algorithms.gp_mpc.model import PlanUncertainty, fit_model_error, learned_model
from scg_algorithms.mpc.nonlinear import NonlinearMPC
from scg_algorithms.mpc.nonlinear import Options as NMPCOptions

PATH = "controllers.gp_mpc"


@dataclasses.dataclass(frozen=True)
class Options(setup.MPCOptions):
    """Options of GP-MPC (a config file's ``controllers.gp_mpc`` section): the MPC, the GP and the learning loop."""

    terminal_weight: str = option("dare", "terminal weight: dare or stage (Q)", choices=("dare", "stage"))
    soft_constraints: bool = option(True, "soften the (tightened) env constraints with slack variables")
    soft_penalty: float = option(1e3, "weight of the slack penalty sum(s + s^2)")
    warm_start: str = option(
        "primal_dual", "warm start: primal_dual, primal, none", choices=("primal_dual", "primal", "none")
    )
    max_iter: int = option(100, "IPOPT iteration limit per step")
    tol: float = option(1e-6, "IPOPT convergence tolerance")
    prob: float = option(0.95, "chance level of each tightened constraint, in (0, 1)")
    initial_std: float = option(0.0, "standard deviation of the initial-state uncertainty (every state entry)")
    num_inducing: int = option(30, "inducing points of the sparse (FITC) GP in the MPC")
    kernel: str = option("rbf", "GP kernel: rbf (squared exponential) or matern52", choices=gp.KERNELS)
    gp_iterations: int = option(50, "L-BFGS iterations of the hyperparameter fit")
    max_fit_points: int = option(200, "transitions the hyperparameters are fit on (a random subset)")
    rounds: int = option(2, "learning rounds after the prior's data (scg-jax train)")
    train_episodes: int = option(4, "episodes collected per round")
    exploration_std: float = option(0.05, "exploration noise of round 0, as a fraction of each input's range")
    eval_episodes: int = option(8, "episodes each round is evaluated on")
    seed: int = option(0, "seed of the data collection and the GP fit")

    def _check(self, path: str) -> None:
        positive_fields = ("horizon", "max_iter", "tol", "soft_penalty", "num_inducing", "gp_iterations",
                           "max_fit_points", "train_episodes", "eval_episodes")  # fmt: skip
        check_fields(self, path, positive_fields=positive_fields)
        if not 0.0 < self.prob < 1.0:
            raise ValueError(f"{path}.prob: must be in (0, 1), got {self.prob!r}")
        check_fields(self, path, nonnegative=("initial_std", "exploration_std", "rounds"))


class GPMPC(NonlinearMPC):
    """Host controller (``is_jax = False``); build it with ``make_gp_mpc``.

    Attributes (besides ``NonlinearMPC``'s): posterior: the GP (``None``: the prior alone). uncertainty: the
    ``PlanUncertainty`` that computes the margins. K: (nu, nx) the ancillary LQR gain of the prior.
    """

    name = "gp_mpc"

    def __init__(self, env, prior_params, opts: Options, posterior: gp.GPPosterior | None):
        # The MPC options both share (horizon, weights, soft constraints, IPOPT settings); the NMPC's others
        # (discretization rk4, margins, fallbacks) keep their defaults.
        shared = {f.name for f in dataclasses.fields(NMPCOptions)} & {f.name for f in dataclasses.fields(opts)}
        nmpc = NMPCOptions(**{name: getattr(opts, name) for name in shared})
        prior_fd = env.symbolic_model(prior_params, discretization=nmpc.discretization).fd
        self.gp_options = opts
        self.posterior = posterior
        super().__init__(env, prior_params, nmpc, prediction_model=learned_model(prior_fd, posterior), tightened=True)
        # The ancillary feedback of the uncertainty propagation: the prior's LQR about the goal.
        self.K, _ = setup.goal_lqr(
            env,
            prior_params,
            self.model,
            self.Q,
            self.R,
            PATH,
            field="q_diag",
            hint="the uncertainty propagation needs one;",
        )
        sigma0 = opts.initial_std**2 * np.eye(self.nx)
        self.uncertainty = PlanUncertainty(self.fd, posterior, self.K, opts.prob, sigma0, self.model.g)

    def stage_margins(self, x_guess, u_guess):
        if self.ng_env == 0:
            return None
        return self.uncertainty.plan_margins(x_guess, u_guess)

    @property
    def info(self) -> dict:
        return {
            **super().info,
            "prob": self.gp_options.prob,
            "num_inducing": None if self.posterior is None else int(self.posterior.inputs.shape[0]),
            "kernel": self.gp_options.kernel,
            "hyperparams": None if self.posterior is None else gp.hyperparams_dict(self.posterior.hyperparams),
        }


def make_gp_mpc(env, prior_params, options=None, posterior: gp.GPPosterior | None = None) -> GPMPC:
    """GP-MPC on the prior model ``env.symbolic_model(prior_params)`` plus the GP ``posterior``.

    Args:
        env: the environment. prior_params: unbatched ``EnvParams`` of the prior model (e.g.
            ``prior_params(env, params, 1.5)``). options: ``Options`` fields as a mapping (``controllers.gp_mpc``).
        posterior: the GP of the prior's one-step error over ``[x; u]`` (``learn`` fits it); ``None`` gives the
            prior's MPC with the same formulation (what round 0 of the learning loop evaluates).
    """
    opts = parse_options(Options, options, PATH)
    return GPMPC(env, prior_params, opts, posterior)


class LearningResult(NamedTuple):
    """What ``learn`` returns.

    Attributes:
        posterior: the GP of the last round (``None`` when ``rounds`` is 0).
        controller: the GP-MPC built from it.
        history: one dict per round: ``round``, ``transitions`` and ``data_seconds`` (simulated time of the data
            the GP was fit on), ``rmse``, ``rmse_std``, ``failure_rate``, ``constraint_violation_steps``,
            ``compute_time_per_step_s``, ``fit_s``, ``eval_s``.
        data: ``(inputs (n, nx + nu), targets (n, nx))``, every transition collected.
    """

    posterior: gp.GPPosterior | None
    controller: GPMPC
    history: list
    data: tuple


def _prior_explorer(env, prior_params, opts: Options):
    from scg_algorithms.lqr import make_lqr

    low, high = (np.asarray(b, dtype=float) for b in env.input_bounds(prior_params.physics))
    # LQR about the goal for stabilization, about each step's reference for tracking (the data must cover the path).
    return data.exploring(make_lqr(env, prior_params, {"mode": "auto"}), opts.exploration_std * (high - low))


def evaluation_key(seed: int):
    """The key of the episodes ``learn`` evaluates every round on (the same ones each round), for comparisons."""
    return jax.random.fold_in(jax.random.key(seed), 10_000)


def learn(env, params, prior_params, options=None, progress: Callable[[dict], None] | None = None) -> LearningResult:
    """The learning loop (module docstring): ``rounds`` rounds after the prior's data, each evaluated.

    Args:
        env, params: the environment and its true parameters (the plant the data comes from).
        prior_params: the prior model's parameters. options: ``controllers.gp_mpc`` options.
        progress: called with each round's history entry as it finishes.
    """
    opts = parse_options(Options, options, PATH)
    key = jax.random.key(opts.seed)
    fd_prior = env.symbolic_model(prior_params, discretization="rk4").fd
    eval_key = evaluation_key(opts.seed)  # the same evaluation episodes every round
    inputs, targets = np.zeros((0, env.nx + env.nu)), np.zeros((0, env.nx))
    history, posterior = [], None
    controller = make_gp_mpc(env, prior_params, opts, None)
    collector = _prior_explorer(env, prior_params, opts)
    for round_index in range(opts.rounds + 1):
        start = time.perf_counter()
        run = evaluate(env, params, controller, eval_key, opts.eval_episodes, measure_time=True)
        eval_s = time.perf_counter() - start
        entry = {
            "round": round_index,
            "transitions": int(len(inputs)),
            "data_seconds": float(len(inputs) * env.dt),
            **{
                name: run.summary[name]
                for name in (
                    "rmse",
                    "rmse_std",
                    "failure_rate",
                    "constraint_violation_steps",
                    "compute_time_per_step_s",
                )
            },  # fmt: skip
            "eval_s": eval_s,
        }
        if round_index == opts.rounds:
            history.append({**entry, "fit_s": 0.0})
            if progress:
                progress(history[-1])
            break
        collect_key = jax.random.fold_in(key, round_index)
        collected = evaluate(env, params, collector, collect_key, opts.train_episodes, measure_time=False)
        z, e = data.model_error(fd_prior, *data.transitions(collected.trajectory))
        inputs, targets = np.concatenate([inputs, z]), np.concatenate([targets, e])
        start = time.perf_counter()
        posterior, fit = fit_model_error(
            inputs, targets, num_inducing=min(opts.num_inducing, len(inputs)), kernel=opts.kernel,
            iterations=opts.gp_iterations, max_fit_points=opts.max_fit_points,
            key=jax.random.fold_in(key, 1_000 + round_index), path=PATH,
        )  # fmt: skip
        history.append({**entry, "fit_s": time.perf_counter() - start, "nll_final": fit["nll_final"]})
        if progress:
            progress(history[-1])
        controller = collector = make_gp_mpc(env, prior_params, opts, posterior)
    return LearningResult(posterior, controller, history, (inputs, targets))
