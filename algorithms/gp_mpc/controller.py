"""The GP-MPC controller and its learning loop.

``GPMPC`` is the nonlinear MPC (``scg_algorithms.mpc.nonlinear``: IPOPT, warm start, soft constraints, fallbacks) with
two arguments set: its prediction model is ``f_prior(x, u) + μ([x; u])`` (``model.learned_model``), and its env
constraints are tightened at every stage by the margins of ``model.PlanUncertainty``: the GP's variance propagated
along the warm-start plan under the prior's LQR gain, at chance level ``prob`` (Hewing et al. 2020).

``learn`` is the original suite's learning loop on the batched JAX environments: round 0 collects episodes of the
prior's LQR (about the goal, or about the reference on tracking tasks) with exploration noise (all copies at once);
every round fits the GP to all transitions so far, evaluates the resulting GP-MPC with the common harness, and
collects the next round's episodes with it.

``solver="sqp_rti"`` builds the same controller in JAX instead (``gp_sqp_mpc_builder``): one SQP real-time iteration per
step on the structured horizon-QP solver (``scg_algorithms.mpc.sqp``) with the same prediction model and the same
margins, computed along the shifted plan; the harness runs it inside its jitted, batched closed loop, and ``learn``
evaluates every round's GP with one compiled program (the GP's arrays are arguments, so a new GP of the same size
compiles nothing).
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from scg_algorithms import controller_setup as setup
from scg_algorithms import gp
from scg_algorithms.base import JaxController, check_fields, option, parse_options
from scg_algorithms.evaluation import evaluate, make_evaluator
from scg_algorithms.gp_mpc import data, tightening
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
    solver: str = option(
        "ipopt",
        "ipopt (CasADi, host, one copy: the reference) or sqp_rti (JAX, batched: one QP per step about the shifted "
        "plan, scg_algorithms.mpc.sqp)",
        choices=("ipopt", "sqp_rti"),
    )
    # The tightened input box makes QPs whose ADMM converges slowly (about 170 iterations of 200 at 1,024 copies,
    # where the nonlinear MPC's need 20); the active-set polish after it finds the same plans from 20. On the paper
    # cart-pole (Fig. 6) RMSE 0.1646 against 0.1642 at 0.59x the time per step; on its constraint setting (Fig. 7) no
    # violating step after learning either way, at 0.36x; on the 2D quadrotor circle (Figs. 5, 6) rounds 1-3 at
    # 0.2315, 0.0904, 0.0981 against 0.229, 0.0868, 0.0994, at 0.80x.
    qp_max_iter: int = option(20, "sqp_rti: ADMM iterations at most per QP, before its active-set polish")
    # The nonlinear MPC's 6 rounds cost GP-MPC 1.1x the time per step on the paper cart-pole for the same RMSE.
    qp_polish_rounds: int = option(3, "sqp_rti: rounds of the QP's active-set polish, at most (0: none)")

    def _check(self, path: str) -> None:
        positive_fields = ("horizon", "max_iter", "tol", "soft_penalty", "num_inducing", "gp_iterations",
                           "max_fit_points", "train_episodes", "eval_episodes", "qp_max_iter")  # fmt: skip
        check_fields(self, path, positive_fields=positive_fields)
        if not 0.0 < self.prob < 1.0:
            raise ValueError(f"{path}.prob: must be in (0, 1), got {self.prob!r}")
        check_fields(self, path, nonnegative=("initial_std", "exploration_std", "rounds", "qp_polish_rounds"))


def _nmpc_options(opts: Options) -> NMPCOptions:
    """The MPC options GP-MPC shares with the nonlinear MPC (horizon, weights, soft constraints, IPOPT settings,
    solver); the NMPC's others (discretization rk4, margins, fallbacks, SQP settings) keep their defaults."""
    shared = {f.name for f in dataclasses.fields(NMPCOptions)} & {f.name for f in dataclasses.fields(opts)}
    return NMPCOptions(**{name: getattr(opts, name) for name in shared})


def _ancillary_gain(env, prior_params, model, Q, R):
    """(nu, nx) the feedback of the uncertainty propagation: the prior's LQR about the goal."""
    gain, _ = setup.goal_lqr(
        env, prior_params, model, Q, R, PATH, field="q_diag", hint="the uncertainty propagation needs one;"
    )
    return gain


class GPMPC(NonlinearMPC):
    """Host controller (``is_jax = False``); build it with ``make_gp_mpc``.

    Attributes (besides ``NonlinearMPC``'s): posterior: the GP (``None``: the prior alone). uncertainty: the
    ``PlanUncertainty`` that computes the margins. K: (nu, nx) the ancillary LQR gain of the prior.
    """

    name = "gp_mpc"

    def __init__(self, env, prior_params, opts: Options, posterior: gp.GPPosterior | None):
        nmpc = _nmpc_options(opts)
        prior_fd = env.symbolic_model(prior_params, discretization=nmpc.discretization).fd
        self.gp_options = opts
        self.posterior = posterior
        super().__init__(env, prior_params, nmpc, prediction_model=learned_model(prior_fd, posterior), tightened=True)
        self.K = _ancillary_gain(env, prior_params, self.model, self.Q, self.R)
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


def gp_sqp_mpc_builder(env, prior_params, opts: Options):
    """GP-MPC in JAX by SQP-RTI (``scg_algorithms.mpc.sqp`` with a ``Prediction``): the model ``f_prior + μ([x; u])``
    and the margins of ``GPMPC`` (same gain ``K``, quantile and initial covariance).

    The host-side set-up is done here, once; the returned ``build(posterior) -> JaxController`` does none, so it may
    run inside ``jax.jit`` with the GP's arrays traced (``make_evaluator``): the GP is data of the compiled program,
    not a constant of it. ``posterior``: a ``gp.GPPosterior`` (host arrays), a ``gp.SplitPosterior`` (what a jitted
    caller passes: float64 values as float32 pairs; the GP is evaluated in float64) or ``None``: the prior alone
    (margins from ``initial_std`` only).
    """
    from scg_algorithms.mpc.sqp import Prediction, sqp_mpc_builder

    nmpc = _nmpc_options(opts)
    nx, nu = env.nx, env.nu
    model = setup.prior_model(env, prior_params, nmpc.discretization)
    Q, R = setup.cost_weights(env, prior_params, opts.q_diag, opts.r_diag, PATH, positive_definite_r=False)
    gain = _ancillary_gain(env, prior_params, model, Q, R)
    z_q, sigma0 = tightening.quantile(opts.prob, nx), opts.initial_std**2 * np.eye(nx)
    build_sqp = sqp_mpc_builder(env, prior_params, nmpc, name="gp_mpc", adaptive_rho=True)

    def build(posterior: gp.GPPosterior | gp.SplitPosterior | None) -> JaxController:
        if isinstance(posterior, gp.GPPosterior):
            posterior = gp.split_posterior(posterior)
        if posterior is not None and (posterior.hi.num_inputs != nx + nu or posterior.hi.num_outputs != nx):
            raise ValueError(
                f"gp: expected a GP from [x; u] ({nx + nu} inputs) to the state ({nx} outputs), got "
                f"{posterior.hi.num_inputs} inputs and {posterior.hi.num_outputs} outputs"
            )

        def mean(x, u):
            if posterior is None:
                return jnp.zeros_like(x)
            # hi + lo: the float32 GP with x64 off, the float64 one with it on.
            exact = jax.tree.map(lambda h, lo: h.astype(x.dtype) + lo.astype(x.dtype), posterior.hi, posterior.lo)
            return gp.predict_mean(exact, jnp.concatenate([x, u]))

        def variance(x, u):
            if posterior is None:
                return jnp.zeros_like(x)
            # Float64 inside: the float32 variance of a GP pinned down by its data is mostly round-off (on the paper
            # cart-pole's GP: errors of 1e-2 on variances of at most 5e-4), and the margins with it. The float32
            # mean is good to 5e-5 of the largest target there.
            return gp.predict_split(posterior, jnp.concatenate([x, u]))

        with_model = posterior is not None or opts.initial_std > 0
        controller = build_sqp(Prediction(mean, variance, gain, z_q, sigma0) if with_model else None)
        info = {
            **controller.info,
            "prob": opts.prob,
            "num_inducing": None if posterior is None else int(posterior.hi.inputs.shape[0]),
            "kernel": opts.kernel,
        }
        return dataclasses.replace(controller, info=info)

    build.__name__ = "gp_mpc"
    return build


def make_gp_mpc(env, prior_params, options=None, posterior: gp.GPPosterior | None = None) -> GPMPC | JaxController:
    """GP-MPC on the prior model ``env.symbolic_model(prior_params)`` plus the GP ``posterior``.

    Args:
        env: the environment. prior_params: unbatched ``EnvParams`` of the prior model (e.g.
            ``prior_params(env, params, 1.5)``). options: ``Options`` fields as a mapping (``controllers.gp_mpc``).
        posterior: the GP of the prior's one-step error over ``[x; u]`` (``learn`` fits it); ``None`` gives the
            prior's MPC with the same formulation (what round 0 of the learning loop evaluates).

    Returns:
        ``solver="ipopt"`` (default): a ``GPMPC`` host controller; ``"sqp_rti"``: a ``JaxController``
        (``gp_sqp_mpc_builder``) for the jitted, batched loop.
    """
    opts = parse_options(Options, options, PATH)
    if opts.solver == "sqp_rti":
        return gp_sqp_mpc_builder(env, prior_params, opts)(posterior)
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
    controller: GPMPC | JaxController
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


def _batched_runs(env, prior_params, opts: Options):
    """With ``solver="sqp_rti"``: ``{"eval": fn, "collect": fn}``, ``fn(posterior, key, params) -> Evaluation`` on
    ``eval_episodes`` and ``train_episodes`` copies, the GP an argument of the compiled loop (``make_evaluator``:
    one compile per GP shape, no compute-time measurement); ``None`` with IPOPT."""
    if opts.solver != "sqp_rti":
        return None
    build = gp_sqp_mpc_builder(env, prior_params, opts)
    return {
        "eval": make_evaluator(env, build, opts.eval_episodes),
        "collect": make_evaluator(env, build, opts.train_episodes),
    }


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
    run_gp_mpc = _batched_runs(env, prior_params, opts)
    for round_index in range(opts.rounds + 1):
        start = time.perf_counter()
        if run_gp_mpc is None:
            run = evaluate(env, params, controller, eval_key, opts.eval_episodes, measure_time=True)
        else:
            run = run_gp_mpc["eval"](None if posterior is None else gp.split_posterior(posterior), eval_key, params)
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
        if run_gp_mpc is None or round_index == 0:
            collected = evaluate(env, params, collector, collect_key, opts.train_episodes, measure_time=False)
        else:
            collected = run_gp_mpc["collect"](gp.split_posterior(posterior), collect_key, params)
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
