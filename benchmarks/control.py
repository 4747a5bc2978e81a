"""Cost of the MPC controllers: IPOPT MPC time per step, and batched linear MPC solves per second.

Two measurements per system (cart-pole and 2D quadrotor, each in its paper configuration), in one run:

1. **Nonlinear MPC** (``scg_algorithms.mpc.nonlinear``, IPOPT, horizon ``--horizon``) against a **reference
   formulation built in the same run**: the original safe-control-gym's MPC as it is usually written (CasADi
   ``Opti``, multiple shooting over the same one-step RK4 prior model, quadratic stage cost with the same full
   ``Q``/``R``, the same constraints, ``opti.solver("ipopt", {"expand": True})``, ``opti.set_value`` /
   ``opti.set_initial`` with the shifted previous plan, ``opti.solve()`` every step). Both controllers see the
   same observation at every step of ``--episodes`` closed-loop episodes run by ``scg_algorithms.evaluation.evaluate``
   with ours in the loop; each keeps its own warm start. Two settings:

   - ``default``: our default options (Riccati terminal weight, primal-dual warm start with a small barrier
     parameter, ``tol`` 1e-6); the reference gets the same terminal weight, IPOPT options and the (unshifted)
     previous multipliers through ``opti.set_initial(opti.lam_g, ...)``.
   - ``original``: the original suite's choices: terminal weight ``Q``, primal warm start only, IPOPT's defaults
     (``tol`` 1e-8, ``max_iter`` 3000) on both sides.

   Reported per control step: median and 95th percentile of IPOPT's wall time (our solver call alone), of our
   whole ``act`` (packing the parameters and the warm start, the solver call, the fallbacks) and of the
   reference's ``set_value`` + ``set_initial`` + ``opti.solve()`` + reading the plan back; the ratio of the two
   medians (ours / reference: below 1 is faster); IPOPT iterations of each; the largest difference between the two
   first inputs (the same NLP, so at solver tolerance). The original suite's own figures (about 6 ms per step on the
   cart-pole and 11 ms on the 2D quadrotor, machine unknown) are printed for scale only.
2. **Batched linear MPC** (``scg_algorithms.mpc.linear.make_linear_mpc``, the condensed QP solved by qpax, horizon
   ``--horizon``): one jitted ``vmap`` of ``act`` over ``--batch`` copies (their observations from a vmapped
   ``env.reset`` of the config's initial-state distribution, control step 0), timed per call; solves per second =
   batch / time per call. Next to it, in the same run with alternating timed runs, the env's own throughput at the
   same batch: a jitted ``vmap(env.step)`` scanned over ``--env-steps`` control steps with the constant equilibrium
   input (as ``benchmarks/throughput.py``'s env column). The ratio is MPC solves per second over env steps per
   second: how much slower a closed loop with this controller is than the bare simulation.

Configs: ``configs/paper_cartpole_lqr_mpc.yaml`` (stabilization, 15 Hz, 90 steps per episode) and
``configs/paper_quadrotor_2d.yaml`` (figure-8 tracking, 50 Hz, 300 steps). Results go to
``benchmarks/results/control.json``. Run ``python benchmarks/control.py --help``; see benchmarks/README.md.

Two more parts, each with its own page: ``--parts solvers`` (the structured QP solvers against qpax, qpOASES and OSQP
on every system, GP-MPC on SQP-RTI; ``docs/benchmarks/mpc_solvers.md``) and ``--parts rti`` (SQP-RTI against IPOPT;
``docs/benchmarks/sqp_rti.md``).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import casadi as cs
import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from machine import (  # benchmarks/machine.py, beside this script
    load_average,
    markdown_table,
    print_machine,
    run_record,
    write_markdown_table,
)
from rich import box
from rich.console import Console
from rich.table import Table
from throughput import measure_pair  # benchmarks/throughput.py: compile, calibrate, alternate timed runs

import scg_jax
from scg_algorithms.base import Reference
from scg_algorithms.evaluation import evaluate
from scg_algorithms.gp_mpc.controller import learn
from scg_algorithms.mpc import structured
from scg_algorithms.mpc.cases import CASES, make_case_env, random_states
from scg_algorithms.mpc.linear import Options as LinearOptions
from scg_algorithms.mpc.linear import make_linear_mpc, make_linear_mpc_casadi
from scg_algorithms.mpc.nonlinear import make_nonlinear_mpc
from scg_jax.config import load_config, make_from_config
from scg_jax.files import write_json

ROOT = Path(__file__).resolve().parent.parent
CONFIGS = {
    "cartpole": ROOT / "configs" / "paper_cartpole_lqr_mpc.yaml",
    "quadrotor_2d": ROOT / "configs" / "paper_quadrotor_2d.yaml",
}
# The original suite's IPOPT MPC, ms per control step, as reported for it (machine unknown; for scale only).
ORIGINAL_NMPC_MS = {"cartpole": 6.0, "quadrotor_2d": 11.0}
DEFAULT_MARKDOWN = Path(__file__).resolve().parents[1] / "docs" / "benchmarks" / "control.md"
DEFAULT_JSON = Path(__file__).resolve().parent / "results" / "control.json"
FULL_DEFAULTS = {"episodes": 2, "batch": 1024, "repeats": 5, "min_time": 0.5}
QUICK_DEFAULTS = {"episodes": 1, "batch": 256, "repeats": 2, "min_time": 0.05}


SOLVERS_MARKDOWN = Path(__file__).resolve().parents[1] / "docs" / "benchmarks" / "mpc_solvers.md"
RTI_MARKDOWN = Path(__file__).resolve().parents[1] / "docs" / "benchmarks" / "sqp_rti.md"


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        description="Nonlinear (IPOPT) MPC time per step and batched linear (qpax) MPC solves per second.",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    parser.add_argument("--systems", nargs="+", default=list(CONFIGS), choices=list(CONFIGS), help="systems")
    parser.add_argument(
        "--parts",
        nargs="+",
        default=["nonlinear", "linear"],
        choices=["nonlinear", "linear", "solvers", "rti"],
        help="rti: SQP-RTI against IPOPT on --solver-systems (writes sqp_rti.json and --rti-markdown); solvers: the "
        "structured QP solvers against qpOASES, OSQP and qpax, and GP-MPC on SQP-RTI (writes --solvers-markdown)",
    )
    parser.add_argument(
        "--solver-systems", nargs="+", default=list(CASES), choices=list(CASES), help="solvers and rti parts"
    )
    parser.add_argument("--batches", nargs="+", type=int, default=[1, 1024, 4096], help="solvers part: copies")
    parser.add_argument("--parity-states", type=int, default=1000, help="solvers part: states compared to qpOASES")
    parser.add_argument("--rti-episodes", type=int, default=2, help="rti part: episodes of SQP-RTI and IPOPT")
    parser.add_argument("--solvers-markdown", type=Path, default=SOLVERS_MARKDOWN, help="solvers part: generated page")
    parser.add_argument("--rti-markdown", type=Path, default=RTI_MARKDOWN, help="rti part: generated page")
    parser.add_argument(
        "--settings", nargs="+", default=list(SETTINGS), choices=list(SETTINGS), help="nonlinear MPC option sets"
    )
    parser.add_argument("--horizon", type=int, default=20, help="MPC horizon, control steps (both controllers)")
    parser.add_argument("--episodes", type=int, default=None, help="nonlinear MPC episodes per system [default: 2]")
    parser.add_argument("--batch", type=int, default=None, help="copies of the batched linear MPC [default: 1024]")
    parser.add_argument("--env-steps", type=int, default=100, help="control steps per timed env call (lax.scan)")
    parser.add_argument("--repeats", type=int, default=None, help="timed runs per measurement [default: 5]")
    parser.add_argument(
        "--min-time", type=float, default=None, help="minimum seconds per timed run (sets calls per run) [default: 0.5]"
    )
    parser.add_argument("--stat", choices=("median", "min"), default="median", help="statistic over timed runs")
    parser.add_argument("--seed", type=int, default=0, help="seed of the episode and reset keys")
    parser.add_argument("--json", type=Path, default=DEFAULT_JSON, help="where to write the results")
    parser.add_argument(
        "--markdown", type=Path, default=None, help=f"generated table [default: {DEFAULT_MARKDOWN}; none with --quick]"
    )
    parser.add_argument(
        "--quick", action="store_true", help="smoke run: 1 episode, batch 256, 2 repeats (explicit options still win)"
    )
    args = parser.parse_args(argv)
    defaults = QUICK_DEFAULTS if args.quick else FULL_DEFAULTS
    for name, value in defaults.items():
        if getattr(args, name) is None:
            setattr(args, name, value)
    for name in ("horizon", "episodes", "batch", "env_steps", "repeats"):
        if getattr(args, name) < 1:
            parser.error(f"--{name.replace('_', '-')}: must be a positive integer")
    if not args.min_time > 0:
        parser.error("--min-time: must be positive")
    return args


# --------------------------------------------------------------------------------------------- nonlinear MPC
SETTINGS = {
    # name: (our options, reference IPOPT options or None for ours, reference warm-starts the multipliers)
    "default": ({}, None, True),
    "original": ({"terminal_weight": "stage", "warm_start": "primal", "tol": 1e-8, "max_iter": 3000}, {}, False),
}


class ReferenceNMPC:
    """The original suite's MPC formulation, written as it usually is: ``Opti``, multiple shooting, ``expand``.

    It takes the prediction model, weights, terminal weight, bounds and constraints of one of our controllers
    (``ours``), so both solve the same NLP; only the formulation and the solver plumbing differ.
    """

    def __init__(self, ours, ipopt_options: dict, dual_warm_start: bool):
        self.ours = ours
        H, nx, nu = ours.horizon, ours.nx, ours.nu
        model = ours.model
        opti = cs.Opti()
        X, U = opti.variable(nx, H + 1), opti.variable(nu, H)
        x_init, x_ref = opti.parameter(nx), opti.parameter(nx, H + 1)
        cost = 0
        opti.subject_to(X[:, 0] == x_init)
        for i in range(H):
            dx, du = X[:, i] - x_ref[:, i], U[:, i] - ours.u_eq
            cost += cs.bilin(ours.Q, dx, dx) + cs.bilin(ours.R, du, du)
            opti.subject_to(X[:, i + 1] == model.fd(X[:, i], U[:, i]))
            opti.subject_to(opti.bounded(ours.u_low, U[:, i], ours.u_high))
            if ours.ng_env:
                opti.subject_to(model.g(X[:, i + 1], U[:, i]) + ours.options.constraint_margin <= 0)
        dx = X[:, H] - x_ref[:, H]
        cost += cs.bilin(ours.P, dx, dx)
        opti.minimize(cost)
        plugin = {"expand": True, "print_time": False, "error_on_fail": False}
        opti.solver("ipopt", plugin, {"print_level": 0, "sb": "yes", **ipopt_options})
        self.opti, self.X, self.U, self.x_init, self.x_ref = opti, X, U, x_init, x_ref
        self.dual_warm_start = dual_warm_start

    def act(self, plan, x0, window):
        """Solve from ``x0`` along ``window`` (H + 1, nx) from ``plan`` (``None`` or the previous ``(x, u, lam)``).
        Returns ``(u0, plan, wall_s, iterations)``; ``wall_s`` covers set_value, set_initial, solve, read-back."""
        opti, H = self.opti, self.ours.horizon
        tick = time.perf_counter()
        opti.set_value(self.x_init, x0)
        opti.set_value(self.x_ref, window.T)
        if plan is None:
            opti.set_initial(self.X, np.tile(x0, (H + 1, 1)).T)
            opti.set_initial(self.U, np.tile(self.ours.u_eq, (H, 1)).T)
        else:
            xs, us, lam = plan
            xs = np.concatenate([xs[1:], xs[-1:]])
            xs[0] = x0
            opti.set_initial(self.X, xs.T)
            opti.set_initial(self.U, np.concatenate([us[1:], us[-1:]]).T)
            if self.dual_warm_start and lam is not None:
                opti.set_initial(opti.lam_g, lam)
        opti.solve()
        stats = opti.stats()
        xs = np.asarray(opti.debug.value(self.X)).reshape(self.ours.nx, H + 1).T
        us = np.asarray(opti.debug.value(self.U)).reshape(self.ours.nu, H).T
        lam = np.asarray(opti.debug.value(opti.lam_g)).ravel() if stats["success"] else None
        wall = time.perf_counter() - tick
        return us[0], (xs, us, lam), wall, int(stats["iter_count"])


class _SideBySide:
    """A host controller that runs ours and, on the same observation, the reference; it times both."""

    is_jax = False

    def __init__(self, controller, reference_controller):
        self.controller = controller
        self.reference_controller = reference_controller
        self.name = controller.name
        self.act_s: list[float] = []
        self.ref_s: list[float] = []
        self.ref_iterations: list[int] = []
        self.du: list[float] = []
        self.final_states: dict[int, object] = {}
        self.plans: dict[int, object] = {}

    def reset(self, key, reference):
        return self.controller.reset(key, reference)

    def act(self, ctrl_state, obs, step, reference):
        tick = time.perf_counter()
        u, ctrl_state = self.controller.act(ctrl_state, obs, step, reference)
        self.act_s.append(time.perf_counter() - tick)
        copy = id(reference)  # one Reference object per copy in the host path
        self.final_states[copy] = ctrl_state
        x0 = np.asarray(obs, dtype=np.float64)[: self.controller.nx]
        window = self.controller.reference_window(reference, int(step))
        plan = self.plans.get(copy) if int(step) > 0 else None
        u_ref, self.plans[copy], wall, iterations = self.reference_controller.act(plan, x0, window)
        self.ref_s.append(wall)
        self.ref_iterations.append(iterations)
        self.du.append(float(np.max(np.abs(np.asarray(u) - u_ref))))
        return u, ctrl_state


def _ms(values) -> dict:
    values = 1e3 * np.asarray(values, dtype=np.float64)
    return {"median": float(np.median(values)), "p95": float(np.percentile(values, 95))}


def measure_nonlinear(env, params, horizon: int, episodes: int, seed: int, setting: str) -> dict:
    options, ipopt_reference, dual = SETTINGS[setting]
    tick = time.perf_counter()
    controller = make_nonlinear_mpc(env, params, {"horizon": horizon, **options})
    build_s = time.perf_counter() - tick
    if ipopt_reference is None:  # the same IPOPT options as ours
        o = controller.options
        ipopt_reference = {"tol": o.tol, "acceptable_tol": max(o.tol, 1e-4), "max_iter": o.max_iter}
        if o.warm_start == "primal_dual":
            ipopt_reference.update(
                warm_start_init_point="yes",
                mu_init=o.warm_mu_init,
                warm_start_bound_push=1e-6,
                warm_start_slack_bound_push=1e-6,
                warm_start_mult_bound_push=1e-6,
            )
    tick = time.perf_counter()
    reference_controller = ReferenceNMPC(controller, ipopt_reference, dual)
    reference_build_s = time.perf_counter() - tick
    recorder = _SideBySide(controller, reference_controller)
    evaluation = evaluate(env, params, recorder, jax.random.key(seed), episodes)
    states = list(recorder.final_states.values())
    # Step 0 of each episode is a cold solve on both sides; the table is about the steady state.
    solve_s = np.concatenate([np.asarray(s.solve_time_s[1:]) for s in states])
    iterations = np.concatenate([np.asarray(s.iterations[1:]) for s in states])
    warm = np.asarray([step > 0 for s in states for step in range(len(s.solve_time_s))])
    act_s = np.asarray(recorder.act_s)[warm]
    ref_s = np.asarray(recorder.ref_s)[warm]
    ipopt, act, ref = _ms(solve_s), _ms(act_s), _ms(ref_s)
    return {
        "setting": setting,
        "options": {"horizon": horizon, **options},
        "reference_ipopt_options": ipopt_reference,
        "build_s": build_s,
        "reference_build_s": reference_build_s,
        "steps": int(act_s.size),
        "ipopt_ms_median": ipopt["median"],
        "ipopt_ms_p95": ipopt["p95"],
        "act_ms_median": act["median"],
        "act_ms_p95": act["p95"],
        "reference_ms_median": ref["median"],
        "reference_ms_p95": ref["p95"],
        "ratio_to_reference": act["median"] / ref["median"],
        "iterations_mean": float(np.mean(iterations)),
        "reference_iterations_mean": float(np.mean(np.asarray(recorder.ref_iterations)[warm])),
        "max_input_difference": float(np.max(recorder.du)),
        "failures": int(sum(s.num_failures for s in states)),
        "rmse": float(evaluation.summary["rmse"]),
        "constraint_violation_steps": float(evaluation.summary["constraint_violation_steps"]),
        "crash_rate": float(evaluation.summary["crash_rate"]),
    }


# --------------------------------------------------------------------------------------------- linear MPC
def build_linear(env, params, horizon: int, batch: int, env_steps: int, seed: int):
    """The vmapped linear-MPC ``act`` and the scanned env step of one system, with their arguments."""
    controller = make_linear_mpc(env, params, {"horizon": horizon})
    reference = Reference(*env.reference(params))
    keys = jax.random.split(jax.random.key(seed), batch)
    obs, state = jax.jit(jax.vmap(env.reset, in_axes=(0, None)))(keys, params)
    ctrl_state = jax.vmap(controller.reset, in_axes=(0, None))(keys, reference)
    act = jax.vmap(controller.act, in_axes=(0, 0, None, None))

    def mpc_fn(ctrl_state, obs, step, reference):
        return act(ctrl_state, obs, step, reference)

    u_eq = jnp.asarray(env.system.equilibrium_input(params.physics), dtype=params.goal.dtype)
    step_fn = jax.vmap(env.step, in_axes=(0, None, None))

    def env_fn(state, action, params):
        def body(carry, _):
            state, ret = carry
            out = step_fn(state, action, params)
            return (out.state, ret + out.reward), None

        (state, ret), _ = lax.scan(body, (state, jnp.zeros(batch, u_eq.dtype)), None, length=env_steps)
        return state.x, ret

    mpc_args = (ctrl_state, obs, jnp.zeros((), jnp.int32), reference)
    env_args = (state, env.input_to_action(u_eq, params), params)
    return controller, (mpc_fn, mpc_args), (env_fn, env_args)


def measure_linear(env, params, args) -> dict:
    controller, mpc, env_step = build_linear(env, params, args.horizon, args.batch, args.env_steps, args.seed)
    result = measure_pair({"mpc": mpc, "env": env_step}, args.repeats, args.min_time, args.stat)
    u, ctrl_state = result["mpc"]["output"]
    names = controller.info["status_names"]
    statuses = np.bincount(np.asarray(ctrl_state.status), minlength=len(names))
    qp = controller.info["qp"]
    mpc_sps = args.batch / result["mpc"]["call_s"]
    env_sps = args.batch * args.env_steps / result["env"]["call_s"]
    row = {
        "solver": controller.info["solver"],
        "qp_decisions": qp.num_decisions,
        "qp_inequalities": qp.num_inequalities,
        "qp_iterations_mean": float(np.mean(np.asarray(ctrl_state.iterations))),
        "qp_iterations_max": int(np.max(np.asarray(ctrl_state.iterations))),
        "mpc_solves_per_s": mpc_sps,
        "mpc_us_per_solve": 1e6 / mpc_sps,
        "env_steps_per_s": env_sps,
        "mpc_over_env": mpc_sps / env_sps,
        "status_counts": {name: int(count) for name, count in zip(names, statuses, strict=False)},
        "u_finite": bool(np.all(np.isfinite(np.asarray(u)))),
    }
    for kind in ("mpc", "env"):
        m = result[kind]
        for key in ("compile_s", "calls_per_run", "call_s", "call_s_min", "call_s_median", "call_s_max"):
            row[f"{kind}_{key}"] = m[key]
    return row


# --------------------------------------------------------------------------------------------- solvers part
def _per_call(fn, args, repeats: int, min_time: float) -> float:
    """Seconds per call of a jitted ``fn(*args)`` (compiled first; median of ``repeats`` runs of >= min_time)."""
    jax.block_until_ready(fn(*args))
    calls, elapsed = 1, 0.0
    while elapsed < min_time:
        tick = time.perf_counter()
        for _ in range(calls):
            jax.block_until_ready(fn(*args))
        elapsed = time.perf_counter() - tick
        calls = calls if elapsed >= min_time else calls * 2
    runs = []
    for _ in range(repeats):
        tick = time.perf_counter()
        for _ in range(calls):
            jax.block_until_ready(fn(*args))
        runs.append((time.perf_counter() - tick) / calls)
    return float(np.median(runs))


def _state_errors(u, u_ref, feasible) -> np.ndarray:
    """Each state's first-input error (N, the largest over the inputs) over the states qpOASES solves
    (``feasible``)."""
    return np.abs(u - u_ref).max(axis=1)[feasible]


def _error_summary(u, u_ref, feasible) -> dict:
    """Largest and median first-input error (N) over the states qpOASES solves (``feasible``)."""
    error = _state_errors(u, u_ref, feasible)
    return {"max": float(error.max()), "median": float(np.median(error))}


def measure_qp_solvers(name: str, with_state: bool, args) -> dict:
    """QPs/s of linear MPC with admm, active_set, ipm and qpax at each batch, CasADi qpOASES and OSQP one at a time,
    the env's steps/s at each batch, and admm's, active_set's and ipm's first-input differences from qpOASES over
    ``parity_states`` states."""
    env, params = make_case_env(name, with_state)
    reference = Reference(*(np.asarray(a, np.float64) for a in env.reference(params)))
    reference32 = Reference(*(jnp.asarray(a) for a in reference))
    options = {"horizon": args.horizon}
    solvers = ("admm", "active_set", "ipm", "qpax")
    controllers = {solver: make_linear_mpc(env, params, {**options, "solver": solver}) for solver in solvers}
    # Fixed iteration counts (no copy waits for another): the throughput settings, each with its own parity error.
    for setting, overrides in THROUGHPUT.items():
        controllers[setting] = make_linear_mpc(env, params, {**options, **overrides})
    row = {"system": name, "constraints": "input and state" if with_state else "input", "batches": {}}
    count = args.parity_states
    steps, states = random_states(env, reference, CASES[name].offset, CASES[name].spread, count, args.seed)
    # Parity: one vmapped admm call against qpOASES one state at a time.
    casadi = {s: make_linear_mpc_casadi(env, params, {**options, "casadi_solver": s}) for s in ("qpoases", "osqp")}
    u_jax = {}
    for solver in ("admm", "active_set", "ipm", *THROUGHPUT):
        c = controllers[solver]
        act = jax.jit(jax.vmap(lambda x, k, c=c: c.act(c.reset(None, reference32), x, k, reference32)))
        u_jax[solver] = np.asarray(act(jnp.asarray(states, jnp.float32), jnp.asarray(steps))[0])
    u_admm = u_jax["admm"]
    u_ref, feasible, casadi_s = [], [], {}
    for solver, controller in casadi.items():
        tick = time.perf_counter()
        for step, x in zip(steps[:count], states[:count], strict=True):
            u, info = controller.act({}, x, step, reference)
            if solver == "qpoases":
                u_ref.append(u)
                feasible.append(info["success"])
        casadi_s[solver] = (time.perf_counter() - tick) / count
    u_ref, feasible = np.array(u_ref), np.array(feasible)
    error = _state_errors(u_admm, u_ref, feasible)
    ipm_error = _state_errors(u_jax["ipm"], u_ref, feasible)
    active_set_error = _state_errors(u_jax["active_set"], u_ref, feasible)
    lo, hi = controllers["admm"].info["u_low"], controllers["admm"].info["u_high"]
    at_bound = np.any((np.abs(u_ref - lo) < 1e-6) | (np.abs(u_ref - hi) < 1e-6), axis=1)[feasible]
    row.update(
        parity_states=count,
        parity_feasible=int(feasible.sum()),
        parity_at_input_bound=float(at_bound.mean()),
        parity_max_error_N=float(error.max()),
        parity_median_error_N=float(np.median(error)),
        throughput_error_N={setting: _error_summary(u_jax[setting], u_ref, feasible) for setting in THROUGHPUT},
        active_set_max_error_N=float(active_set_error.max()),
        active_set_states_beyond_1e3=int((active_set_error > 1e-3).sum()),
        ipm_max_error_N=float(ipm_error.max()),
        ipm_states_beyond_1e3=int((ipm_error > 1e-3).sum()),
        qpoases_qps=1.0 / casadi_s["qpoases"],
        osqp_qps=1.0 / casadi_s["osqp"],
    )
    u_eq = jnp.asarray(env.system.equilibrium_input(params.physics), dtype=jnp.float32)
    env_step = jax.jit(jax.vmap(env.step, in_axes=(0, None, None)))
    for batch in args.batches:
        index = np.arange(batch) % count
        x_b, k_b = jnp.asarray(states[index], jnp.float32), jnp.asarray(steps[index])
        entry = {}
        for solver, controller in controllers.items():
            if solver == "qpax" and batch > 1024:
                continue  # 0.1-0.5 s per call at 1,024 already; 4,096 adds nothing but minutes
            fn = jax.jit(jax.vmap(lambda x, k, c=controller: c.act(c.reset(None, reference32), x, k, reference32)))
            entry[f"{solver}_qps"] = batch / _per_call(fn, (x_b, k_b), args.repeats, args.min_time)
        keys = jax.random.split(jax.random.key(args.seed), batch)
        _, state = jax.jit(jax.vmap(env.reset, in_axes=(0, None)))(keys, params)
        action = env.input_to_action(u_eq, params)
        entry["env_steps_per_s"] = batch / _per_call(env_step, (state, action, params), args.repeats, args.min_time)
        row["batches"][batch] = entry
    return row


# The throughput settings of linear MPC's admm (tolerance 0: every copy runs exactly this many iterations, so none
# waits for the slowest; the step size stays the prepared one times admm_rho_scale, so prepare folds its products
# once and an iteration is one (rows x rows) product; no polish), chosen by a sweep of iterations (25-400) and step
# factors (0.3-100) against qpOASES on the parity states: "25 it.": on the cart-pole's input-bound QPs the error
# reaches float32's floor, 1.5e-6 N, from 10 iterations; "100 it., step x10": the stiffer 2D quadrotor's input-bound
# QPs within 7e-4 N (x1: 25 of 1,000 states beyond 1e-3 N; 50 iterations at x10: 8.9e-4 N); "160 it., step x25,
# relaxation 1.9": the cart-pole with its cart box within 7.7e-4 N (the ADMM's over-relaxation admm_alpha 1.9, not
# 1.6: at 1.6 it took 200 iterations at x30 for 3.1e-4 N, 150 left 5 states beyond 1e-3 N; at 1.9, 150 left one at
# 1.0e-3 N, and on two other sets of 1,000 states 160 held 5.2e-4 and 2.7e-4 N); "50 it., step x10, 1 round, 30 dual
# steps": the exact QP from a short ADMM (one polish round, then the dual active-set steps where it was not accepted,
# run only for those copies): the 2D quadrotor's position box within 5.2e-6 N, where the ADMM alone leaves 94 of its
# 787 feasible states beyond 1e-3 N.
_FIXED = {"admm_tol": 0.0, "admm_polish_rounds": 0, "admm_adaptive_rho": False}
THROUGHPUT = {
    "25 it.": {**_FIXED, "admm_max_iter": 25, "admm_check_every": 25},
    "100 it., step x10": {**_FIXED, "admm_max_iter": 100, "admm_check_every": 100, "admm_rho_scale": 10.0},
    "160 it., step x25, relaxation 1.9": {
        **_FIXED,
        "admm_max_iter": 160,
        "admm_check_every": 160,
        "admm_rho_scale": 25.0,
        "admm_alpha": 1.9,
    },
    "50 it., step x10, 1 round, 30 dual steps": {
        **_FIXED,
        "admm_max_iter": 50,
        "admm_check_every": 50,
        "admm_rho_scale": 10.0,
        "admm_polish_rounds": 1,
        "admm_dual_active_set_steps": 30,
    },
}

RTI_TASKS = {
    "cartpole": ({"system": "cartpole"}, "stabilization"),
    "quadrotor_2d": ({"system": "quadrotor_2d", "task": "tracking"}, "circle tracking"),
    "quadrotor_3d": ({"system": "quadrotor_3d"}, "stabilization"),
}


GP_MPC_CONFIG = ROOT / "configs" / "paper_cartpole_gp_mpc.yaml"
GP_PRIOR_SCALE = 1.5


def _rti_step(controller, env, params, key, batch: int = 1024):
    """``(act, args)``: one vmapped step of ``batch`` copies that have a plan (the second step: the first iterates)."""
    reference = Reference(*env.reference(params))
    keys = jax.random.split(key, batch)
    obs, _ = jax.jit(jax.vmap(env.reset, in_axes=(0, None)))(keys, params)
    act = jax.jit(jax.vmap(controller.act, in_axes=(0, 0, None, None)))
    ctrl = jax.vmap(controller.reset, in_axes=(0, None))(keys, reference)
    _, ctrl = act(ctrl, obs, jnp.zeros((), jnp.int32), reference)
    return act, (ctrl, obs, jnp.ones((), jnp.int32), reference)


def _rti_step_s(controller, env, params, key, args, batch: int = 1024) -> float:
    """Seconds per copy of ``_rti_step``."""
    return _per_call(*_rti_step(controller, env, params, key, batch), args.repeats, args.min_time) / batch


def measure_gp_rti(args) -> dict:
    """GP-MPC on SQP-RTI against the nonlinear SQP-RTI on the true model, per copy and step at 1,024 copies, on
    ``configs/paper_cartpole_gp_mpc.yaml`` (150% prior): the GP of one learning round, the config's GP-MPC and
    nonlinear MPC sections (both horizon 20); the two steps' timed runs alternate (medians)."""
    cfg = load_config(GP_MPC_CONFIG)
    env, params = make_from_config(cfg)
    prior = scg_jax.prior_params(env, params, GP_PRIOR_SCALE)
    options = {**dict(cfg.controllers["gp_mpc"]), "solver": "sqp_rti", "rounds": 1, "eval_episodes": 1}
    tick = time.perf_counter()
    result = learn(env, params, prior, options)
    learn_s = time.perf_counter() - tick
    nmpc = make_nonlinear_mpc(env, params, {**dict(cfg.controllers["nonlinear_mpc"]), "solver": "sqp_rti"})
    key = jax.random.key(args.seed)
    # Timed runs alternate (median of each), so a slower spell of the machine weighs on both steps alike.
    steps = {"gp_mpc": _rti_step(result.controller, env, params, key), "nmpc": _rti_step(nmpc, env, params, key)}
    timed = measure_pair(steps, args.repeats, args.min_time, "median")
    gp_s, nmpc_s = (timed[name]["call_s"] / 1024 for name in ("gp_mpc", "nmpc"))
    return {
        "config": str(GP_MPC_CONFIG.relative_to(ROOT)),
        "transitions": int(result.data[0].shape[0]),
        "learn_s": learn_s,
        "gp_mpc_s_per_copy_step_1024": gp_s,
        "nmpc_s_per_copy_step_1024": nmpc_s,
        "ratio": gp_s / nmpc_s,
    }


# SQP-RTI's settings: its defaults, and its QP without the active-set polish (on the cart-pole the same closed loop
# at about 0.6x the time per step; the 2D quadrotor's tracking needs the polish: RMSE 3.3x without it).
# The interior point (qp_solver: ipm, a cold start at every step): its defaults, and 4 iterations without the polish,
# the fewest that kept every RMSE within 1.005x IPOPT's in a sweep of 1-6 (2 episodes each: the 3D quadrotor took 1.033x
# with 1 iteration, 1.017x with 3), with and without iterative refinement (the same RMSEs to 5 digits without it), and
# 3 iterations without refinement.
RTI_SETTINGS = {
    "default": {},
    "qp_polish_rounds: 0": {"qp_polish_rounds": 0},
    "qp_solver: ipm": {"qp_solver": "ipm"},
    "qp_solver: ipm, ipm_max_iter: 4, ipm_polish_rounds: 0": {
        "qp_solver": "ipm", "ipm_max_iter": 4, "ipm_polish_rounds": 0,
    },
    "qp_solver: ipm, ipm_max_iter: 4, ipm_polish_rounds: 0, ipm_refinement_steps: 0": {
        "qp_solver": "ipm", "ipm_max_iter": 4, "ipm_polish_rounds": 0, "ipm_refinement_steps": 0,
    },
    "qp_solver: ipm, ipm_max_iter: 3, ipm_polish_rounds: 0, ipm_refinement_steps: 0": {
        "qp_solver": "ipm", "ipm_max_iter": 3, "ipm_polish_rounds": 0, "ipm_refinement_steps": 0,
    },
}  # fmt: skip


def measure_rti(name: str, args) -> list[dict]:
    """SQP-RTI against IPOPT: closed-loop RMSE on the same seeded episodes (5 s) and the time per copy and step
    (SQP-RTI: one vmapped step of 1,024 copies that have a plan, divided by 1,024; IPOPT: median solve time)."""
    kwargs, task = RTI_TASKS[name]
    kwargs = dict(kwargs)
    env = scg_jax.make(kwargs.pop("system"), episode_len_sec=5.0, **kwargs)
    params = env.default_params
    key = jax.random.key(args.seed)
    ipopt = make_nonlinear_mpc(env, params, {"horizon": args.horizon})
    result_ipopt = evaluate(env, params, ipopt, key, args.rti_episodes, measure_time=False)
    reference = Reference(*env.reference(params))
    ipopt_state = ipopt.reset(None, reference)
    for step in range(min(env.num_steps, 50)):
        obs_host = np.asarray(result_ipopt.trajectory["obs"])[step, 0]
        _, ipopt_state = ipopt.act(ipopt_state, obs_host, step, reference)
    ipopt_s = float(np.median(ipopt_state.solve_time_s[1:]))
    rows = []
    for setting, overrides in RTI_SETTINGS.items():
        rti = make_nonlinear_mpc(env, params, {"horizon": args.horizon, "solver": "sqp_rti", **overrides})
        result_rti = evaluate(env, params, rti, key, args.rti_episodes, measure_time=False)
        rti_s = _rti_step_s(rti, env, params, key, args)
        rows.append(
            {
                "system": name,
                "task": task,
                "setting": setting,
                "episodes": args.rti_episodes,
                "rmse_ipopt": result_ipopt.summary["rmse"],
                "rmse_sqp_rti": result_rti.summary["rmse"],
                "rmse_ratio": result_rti.summary["rmse"] / result_ipopt.summary["rmse"],
                "ipopt_s_per_step": ipopt_s,
                "sqp_rti_s_per_copy_step_1024": rti_s,
                "time_ratio": rti_s / ipopt_s,
            }
        )
    return rows


# The linear MPC's defaults: the page's "admm" columns run its ADMM ones, the "active set" columns its active-set ones.
LINEAR = LinearOptions()


def write_rti_markdown(path, rti_rows: list[dict], meta: dict) -> None:
    """The SQP-RTI page: per system and setting, the closed-loop RMSE and the time per copy and step against IPOPT."""
    columns = ["system", "task", "SQP-RTI setting", "episodes", "RMSE IPOPT", "RMSE SQP-RTI", "RMSE ratio"]
    columns += ["IPOPT s/step", "SQP-RTI s/(copy step) x1024", "time ratio"]
    rows = [
        [r["system"], r["task"], r["setting"], r["episodes"], f"{r['rmse_ipopt']:.4f}", f"{r['rmse_sqp_rti']:.4f}"]
        + [f"{r['rmse_ratio']:.4f}", f"{r['ipopt_s_per_step']:.2e}", f"{r['sqp_rti_s_per_copy_step_1024']:.2e}"]
        + [f"1/{1 / r['time_ratio']:,.0f}"]
        for r in rti_rows
    ]
    notes = f"""
Nonlinear MPC, horizon {meta["config"]["horizon"]}, on the same seeded 5 s episodes ({meta["config"]["rti_episodes"]}
per row): IPOPT (`controllers.nonlinear_mpc.solver: ipopt`, CasADi, float64, one copy on the host; its median solve
time per step over an episode's first 50 steps) against SQP-RTI (`solver: sqp_rti`, JAX, float32; one jitted,
vmapped control step of 1,024 copies that already have a plan, divided by 1,024). RMSE ratio: SQP-RTI's closed-loop
RMSE over IPOPT's; time ratio: SQP-RTI's time per copy and step over IPOPT's per step. Settings: SQP-RTI's defaults
(the structured ADMM QP solver with its active-set polish); without the polish; the interior point (`qp_solver: ipm`,
a cold start at every step) with its defaults; and the interior point's throughput settings: at most 3 or 4
iterations without the polish (`ipm_max_iter`, `ipm_polish_rounds: 0`), with and without iterative refinement
(`ipm_refinement_steps`). The machine is shared: compare the rows of one run only. Load average at the start and
end: {meta["load_average_start"]} / {meta["load_average_end"]}.
"""
    write_markdown_table(path, "SQP-RTI against IPOPT", meta, columns, rows, notes)


def write_solvers_markdown(path, qp_rows: list[dict], meta: dict, gp_row: dict) -> None:
    batches = meta["config"]["batches"]
    columns = ["system", "constraints", "u0 max error vs qpOASES (N)", "feasible / states", "u0 at a bound"]
    columns += [f"admm QPs/s x{b}" for b in batches]
    columns += ["active set u0 max error (N)", "active set states > 1e-3 N"]
    columns += [f"active set QPs/s x{b}" for b in batches]
    columns += ["ipm u0 max error (N)", "ipm states > 1e-3 N"] + [f"ipm QPs/s x{b}" for b in batches]
    columns += [f"qpax QPs/s x{b}" for b in batches if b <= 1024]
    columns += ["qpOASES QPs/s", "OSQP QPs/s"] + [f"env steps/s x{b}" for b in batches]
    rows = []
    for r in qp_rows:
        cells = [r["system"], r["constraints"], f"{r['parity_max_error_N']:.1e}"]
        cells += [f"{r['parity_feasible']} / {r['parity_states']}", f"{r['parity_at_input_bound']:.2f}"]
        cells += [r["batches"][b]["admm_qps"] for b in batches]
        cells += [f"{r['active_set_max_error_N']:.1e}", r["active_set_states_beyond_1e3"]]
        cells += [r["batches"][b]["active_set_qps"] for b in batches]
        cells += [f"{r['ipm_max_error_N']:.1e}", r["ipm_states_beyond_1e3"]] + [
            r["batches"][b]["ipm_qps"] for b in batches
        ]
        cells += [r["batches"][b]["qpax_qps"] for b in batches if b <= 1024]
        cells += [r["qpoases_qps"], r["osqp_qps"]] + [r["batches"][b]["env_steps_per_s"] for b in batches]
        rows.append(cells)
    fast_columns = ["system", "constraints", "admm setting", "u0 max error (N)", "u0 median error (N)"]
    fast_columns += [f"QPs/s x{b}" for b in batches] + [f"QPs / env steps x{b}" for b in batches]
    fast_lines = [
        "",
        "The throughput settings (tolerance 0, a fixed iteration count), against qpOASES on the same states:",
        "",
    ]
    fast_lines += markdown_table(
        fast_columns,
        [
            [r["system"], r["constraints"], setting, f"{error['max']:.1e}", f"{error['median']:.1e}"]
            + [r["batches"][b][f"{setting}_qps"] for b in batches]
            + [f"{r['batches'][b][f'{setting}_qps'] / r['batches'][b]['env_steps_per_s']:.2f}" for b in batches]
            for r in qp_rows
            for setting, error in r["throughput_error_N"].items()
        ],
    )
    settings = "; ".join(
        f'"{name}": ' + ", ".join(f"`{key}: {value}`" for key, value in options.items())
        for name, options in THROUGHPUT.items()
    )
    notes = f"""
Linear MPC, horizon {meta["config"]["horizon"]}, float32, random states around the reference (the parity tests'
sets; u0 error over the states qpOASES solves), each solved cold. admm: `scg_algorithms.mpc.structured` with linear
MPC's ADMM defaults (tolerance {LINEAR.admm_tol:g}, at most {LINEAR.admm_max_iter:,} iterations and
{LINEAR.admm_polish_rounds} rounds of active-set polish, then, where a copy stopped at the cap and no round was
accepted, at most {LINEAR.admm_dual_active_set_steps} steps of a dual active-set method; under vmap the ADMM's
passes and the polish's rounds run on the copies still running, {structured.ADMM_CHUNK} at a time, and the dual
active-set method on the copies that need it, {structured.DUAL_ACTIVE_SET_CHUNK} at a time); active set:
`solver: active_set`, Goldfarb and Idnani's dual active-set method on the condensed QP from its unconstrained
minimiser (at most {LINEAR.active_set_max_steps} steps, {LINEAR.active_set_slots} rows in the set before a copy is
solved again with {structured.ACTIVE_SET_GROWTH} times as many; under vmap
{structured.ACTIVE_SET_WHOLE_STEPS} steps over the batch, then the copies still running,
{structured.ACTIVE_SET_CHUNK} at a time); ipm:
`scg_algorithms.mpc.interior_point` with linear MPC's defaults (at most {LINEAR.ipm_max_iter} iterations,
complementarity tolerance {LINEAR.ipm_tol:g}, {LINEAR.ipm_polish_rounds} polish rounds from each of two starts);
qpax: 40 interior-point iterations; qpOASES and OSQP: `linear_mpc_casadi`, one problem at a time on the host.
env: one vmapped `env.step`. A copy whose iterate still violates a row by more than `feasibility_tol` (1e-3) after
its iterations falls back to the clipped LQR input, which is where a throughput setting's largest errors come from.
Throughput settings: {settings}. Load average at the start and end:
{meta["load_average"]} / {meta["load_average_end"]}.
""" + "\n".join(fast_lines)
    notes += (
        f"\n\nGP-MPC on SQP-RTI (`{gp_row['config']}`, 150% prior, the GP of one learning round on "
        f"{gp_row['transitions']} transitions) against the nonlinear SQP-RTI on the true model, the config's "
        f"sections, per copy and step at 1,024 copies (their timed runs alternating): "
        f"{gp_row['gp_mpc_s_per_copy_step_1024']:.2e} s against {gp_row['nmpc_s_per_copy_step_1024']:.2e} s, "
        f"{gp_row['ratio']:.1f}x.\n\nSQP-RTI against IPOPT: `python benchmarks/control.py --parts rti`, "
        "docs/benchmarks/sqp_rti.md."
    )
    write_markdown_table(path, "Structured MPC solvers", meta, columns, rows, notes)


def _table(title: str) -> Table:
    """A report table: simple header rule, title left-aligned."""
    return Table(title=title, box=box.SIMPLE_HEAD, title_justify="left")


def write_markdown(path, rows: list[dict], meta: dict) -> None:
    """The generated page: nonlinear MPC per step against the reference formulation, batched linear MPC vs env."""
    nonlinear = [
        [r["system"], n["setting"], n["act_ms_median"], n["act_ms_p95"], n["reference_ms_median"],
         n["ratio_to_reference"], f"~{ORIGINAL_NMPC_MS[r['system']]:g}", n["rmse"]]
        for r in rows for n in r.get("nonlinear", [])
    ]  # fmt: skip
    linear = [
        f"- {r['system']}: {r['linear']['mpc_solves_per_s']:,.0f} batched linear MPC solves/s at "
        f"{meta['config']['batch']:,} copies ({r['linear']['solver']}, its defaults, cold; iterations mean "
        f"{r['linear']['qp_iterations_mean']:.0f}, max {r['linear']['qp_iterations_max']}), env "
        f"{r['linear']['env_steps_per_s']:,.0f} steps/s, ratio {r['linear']['mpc_over_env']:.4f}"
        for r in rows
        if "linear" in r
    ]
    write_markdown_table(
        path,
        f"MPC cost (CasADi {cs.__version__}, horizon {meta['config']['horizon']})",
        meta,
        ["system", "setting", "act ms median", "act ms p95", "reference ms median", "ours / reference",
         "original ms (quoted)", "RMSE"],
        nonlinear,
        notes="reference: the original suite's Opti formulation, built in the same run with the same model, weights "
        "and constraints, solved from the same states. Warm steps only.\n\n" + "\n".join(linear),
    )  # fmt: skip


def print_report(console: Console, rows: list[dict], meta: dict) -> None:
    cfg = meta["config"]
    where = f"{meta['device']['platform']} ({meta['device']['device_kind']}), {meta['cpu_count']} CPU cores"
    nonlinear = [r for r in rows if "nonlinear" in r]
    if nonlinear:
        table = _table(
            f"Nonlinear MPC (CasADi {cs.__version__} + IPOPT), horizon {cfg['horizon']}, ms per control step "
            f"(median / p95), against the reference formulation on the same states; {where}"
        )
        headers = ("system", "setting", "steps", "IPOPT ms", "act ms", "reference ms", "ours / reference")
        headers += ("iterations ours / ref", "max |du| N", "original ms", "failures", "rmse")
        for header in headers:
            table.add_column(header, justify="left" if header in ("system", "setting") else "right")
        for r in nonlinear:
            for n in r["nonlinear"]:
                table.add_row(
                    r["system"],
                    n["setting"],
                    f"{n['steps']}",
                    f"{n['ipopt_ms_median']:.2f} / {n['ipopt_ms_p95']:.2f}",
                    f"{n['act_ms_median']:.2f} / {n['act_ms_p95']:.2f}",
                    f"{n['reference_ms_median']:.2f} / {n['reference_ms_p95']:.2f}",
                    f"{n['ratio_to_reference']:.2f}",
                    f"{n['iterations_mean']:.1f} / {n['reference_iterations_mean']:.1f}",
                    f"{n['max_input_difference']:.1e}",
                    f"~{ORIGINAL_NMPC_MS[r['system']]:g}",
                    f"{n['failures']}",
                    f"{n['rmse']:.3f}",
                )
        console.print(table)
        console.print(
            "IPOPT = our solver call alone; act = our whole controller call (parameters, warm start, solver, "
            "fallbacks); reference = the Opti formulation of the original suite (set_value, set_initial, solve, "
            "read-back), built in this run with the same model, weights and constraints; ours / reference = ratio "
            "of the act and reference medians. Warm steps only (step 0 of each episode is cold on both sides). "
            "original = the original suite's figure as reported for it (machine unknown), for scale.\n"
        )
    linear = [r for r in rows if "linear" in r]
    if linear:
        table = _table(
            f"Batched linear MPC (its default solver), horizon {cfg['horizon']}, {cfg['batch']:,} copies, one jitted "
            f"vmapped act per call, {cfg['dtype']}; {where}"
        )
        for header in ("system", "QP size", "MPC solves/s", "us/solve", "env steps/s", "MPC/env", "MPC compile s",
                       "iterations mean / max"):  # fmt: skip
            table.add_column(header, justify="left" if header == "system" else "right")
        for r in linear:
            m = r["linear"]
            table.add_row(
                r["system"],
                f"{m['qp_decisions']} x {m['qp_inequalities']}",
                f"{m['mpc_solves_per_s']:,.0f}",
                f"{m['mpc_us_per_solve']:.1f}",
                f"{m['env_steps_per_s']:,.0f}",
                f"{m['mpc_over_env']:.4f}",
                f"{m['mpc_compile_s']:.2f}",
                f"{m['qp_iterations_mean']:.0f} / {m['qp_iterations_max']}",
            )
        console.print(table)
        console.print(
            f"MPC solves/s = batch / time per vmapped act call; env steps/s = batch * {cfg['env_steps']} / time per "
            f"call of vmap(env.step) scanned over {cfg['env_steps']} steps (constant equilibrium input). "
            f"{cfg['stat']} of {cfg['repeats']} alternating timed runs of at least {cfg['min_time']:g} s. QP size = "
            "decisions x inequality rows of the dense QP; each batch runs until its slowest copy converges."
        )


# --------------------------------------------------------------------------------------------- main
def main(argv=None) -> int:
    args = parse_args(argv)
    console = Console()
    if not console.is_terminal:
        console = Console(width=max(console.width, 170))
    started = time.perf_counter()
    meta = {
        **run_record("control"),
        "config": {
            "systems": args.systems,
            "parts": args.parts,
            "configs": {name: str(CONFIGS[name].relative_to(ROOT)) for name in args.systems},
            "horizon": args.horizon,
            "settings": args.settings,
            "casadi": cs.__version__,
            "episodes": args.episodes,
            "batch": args.batch,
            "env_steps": args.env_steps,
            "repeats": args.repeats,
            "min_time": args.min_time,
            "stat": args.stat,
            "seed": args.seed,
            "dtype": str(jnp.zeros(()).dtype),
            "quick": args.quick,
        },
        "reference": {
            "original_nmpc_ms_per_step": ORIGINAL_NMPC_MS,
            "description": "original safe-control-gym IPOPT MPC per control step, as reported for it",
        },
    }
    print_machine(console, meta)

    rows = []
    for name in args.systems:
        env, params = make_from_config(load_config(CONFIGS[name]))
        row = {"system": name, "config": CONFIGS[name].stem, "ctrl_freq": 1.0 / env.dt}
        if "nonlinear" in args.parts:
            row["nonlinear"] = []
            for setting in args.settings:
                n = measure_nonlinear(env, params, args.horizon, args.episodes, args.seed, setting)
                row["nonlinear"].append(n)
                console.print(
                    f"{name:<13} nonlinear MPC ({setting}): {n['steps']} steps, act {n['act_ms_median']:.2f} ms "
                    f"median, reference {n['reference_ms_median']:.2f} ms, ratio {n['ratio_to_reference']:.2f}, "
                    f"{n['failures']} failed solves",
                    highlight=False,
                )
        if "linear" in args.parts:
            row["linear"] = m = measure_linear(env, params, args)
            console.print(
                f"{name:<13} linear MPC x{args.batch}: {m['mpc_solves_per_s']:,.0f} solves/s, env "
                f"{m['env_steps_per_s']:,.0f} steps/s, ratio {m['mpc_over_env']:.4f}, compile "
                f"{m['mpc_compile_s']:.2f} s",
                highlight=False,
            )
        rows.append(row)

    if "rti" in args.parts:
        meta["config"].update(rti_episodes=args.rti_episodes, rti_systems=args.solver_systems)
        rti_rows = [r for name in args.solver_systems if name in RTI_TASKS for r in measure_rti(name, args)]
        for r in rti_rows:
            console.print(
                f"{r['system']:<13} SQP-RTI ({r['setting']}): RMSE {r['rmse_ratio']:.4f}x IPOPT's, time per copy and "
                f"step 1/{1 / r['time_ratio']:.0f} of IPOPT's ({r['sqp_rti_s_per_copy_step_1024']:.2e} s against "
                f"{r['ipopt_s_per_step']:.2e} s)",
                highlight=False,
            )
        meta["load_average_end"] = load_average()
        write_json(args.json.with_name("sqp_rti.json"), {**meta, "rti": rti_rows})
        write_rti_markdown(args.rti_markdown, rti_rows, meta)
        console.print(f"SQP-RTI page written to {args.rti_markdown}", highlight=False)
        if set(args.parts) == {"rti"}:
            return 0

    if "solvers" in args.parts:
        meta["config"].update(batches=args.batches, parity_states=args.parity_states)
        meta["load_average"] = load_average()
        qp_rows = []
        for name in args.solver_systems:
            for with_state in (False, True):
                r = measure_qp_solvers(name, with_state, args)
                qp_rows.append(r)
                console.print(f"{name} ({r['constraints']}): {r}", highlight=False)
        gp_row = measure_gp_rti(args)
        console.print(f"GP-MPC SQP-RTI: {gp_row}", highlight=False)
        meta["load_average_end"] = load_average()
        write_json(args.json.with_name("mpc_solvers.json"), {**meta, "qp": qp_rows, "gp": gp_row})
        write_solvers_markdown(args.solvers_markdown, qp_rows, meta, gp_row)
        console.print(f"solvers page written to {args.solvers_markdown}", highlight=False)
        if set(args.parts) == {"solvers"}:
            return 0

    meta["load_average_end"] = load_average()
    meta["total_runtime_s"] = time.perf_counter() - started
    console.print()
    print_report(console, rows, meta)
    write_json(args.json, {**meta, "rows": rows})
    markdown = args.markdown or (None if args.quick else DEFAULT_MARKDOWN)
    if markdown is not None:
        write_markdown(markdown, rows, meta)
        console.print(f"table written to {markdown}", highlight=False)
    console.print(f"\ntotal runtime {meta['total_runtime_s']:.1f} s; results written to {args.json}", highlight=False)
    return 0


if __name__ == "__main__":
    sys.exit(main())
