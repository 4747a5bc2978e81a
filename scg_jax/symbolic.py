"""The CasADi mirror of an environment, built by calling the system's one ``dynamics`` on ``SX`` symbols.

Controllers (LQR, iLQR, MPC, GP-MPC, CBF, safety filters) are given a ``SymbolicModel`` built from *prior*
parameters, which may deliberately differ from the simulated plant; pass the prior you want in ``params``.
"""

from __future__ import annotations

import dataclasses

import casadi as cs
import jax
import numpy as np

from scg_jax import constraints as constraints_lib
from scg_jax.backends import casadi_backend
from scg_jax.caching import CompileCache, jitted_method
from scg_jax.integrators import make_discrete_dynamics

DISCRETIZATIONS = ("env", "rk4")


@dataclasses.dataclass(frozen=True)
class Linearization:
    """``x_dot ~ A (x - x0) + B (u - u0) + f(x0, u0)`` and ``x_next ~ Ad (x - x0) + Bd (u - u0) + fd(x0, u0)``."""

    A: np.ndarray
    B: np.ndarray
    Ad: np.ndarray
    Bd: np.ndarray


@dataclasses.dataclass(frozen=True)
class SymbolicModel:
    """CasADi functions of the dynamics and cost for one set of (prior) parameters.

    Attributes:
        nx, nu: state and input sizes. dt: control period (s).
        x, u: the ``SX`` symbols (nx, 1) and (nu, 1) the functions are built from.
        fc: ``fc(x, u) -> x_dot``, continuous dynamics, for *one* point: ``x`` (nx,) or (nx, 1), ``u`` (nu,) or
            (nu, 1) (numbers or CasADi symbols), result a (nx, 1) ``DM``/``SX``/``MX``. CasADi reads an (N, nx)
            array as a matrix, not as N points, so for trajectories use ``evaluate_fc`` (numpy, any leading
            axes) or ``fc.map(N)(xs.T, us.T)`` (columns are points).
        fd: ``fd(x, u) -> x_next`` over one control period: the env's integrator and substeps
            (``discretization="env"``) or one RK4 step of length dt (``"rk4"``); shapes as ``fc``, batched
            with ``evaluate_fd``.
        df: ``df(x, u) -> (A, B)``, Jacobians of ``fc``.
        dfd: ``dfd(x, u) -> (Ad, Bd)``, Jacobians of ``fd``.
        cost: ``cost(x, u, x_ref, u_ref) -> (l, l_x, l_u, l_xx, l_uu, l_xu)``, the stage cost
            ``l = 1/2 (x - x_ref)^T Q (x - x_ref) + 1/2 (u - u_ref)^T R (u - u_ref)`` with its gradients (column
            vectors) and Hessians (``l_xu`` is (nx, nu)).
        Q, R: the cost weights (numpy).
        x_ref: (num_steps + 1, nx) state reference; u_ref: (num_steps, nu) input reference.
        discretization: ``"env"`` or ``"rk4"``.
        constraints: one ``g_i(x, u) -> rows`` CasADi function per env constraint (``g <= 0`` satisfied), built
            from the same values as the env's (those in ``params``).
        g: ``g(x, u)``, all constraint rows concatenated in order (0 rows when there are none).
        constraint_specs: the env's static ``ConstraintSpec`` tuple (type, variable, active dims, strictness).
        constraint_tolerances: tolerance of each constraint.
    """

    nx: int
    nu: int
    dt: float
    x: cs.SX
    u: cs.SX
    fc: cs.Function
    fd: cs.Function
    df: cs.Function
    dfd: cs.Function
    cost: cs.Function
    Q: np.ndarray
    R: np.ndarray
    x_ref: np.ndarray
    u_ref: np.ndarray
    discretization: str
    constraints: tuple = ()
    g: cs.Function | None = None
    constraint_specs: tuple = ()
    constraint_tolerances: tuple = ()

    def evaluate_fc(self, x, u) -> np.ndarray:
        """``fc`` on numpy arrays of points: ``x (..., nx)``, ``u (..., nu)`` -> ``x_dot (..., nx)``.

        The leading axes broadcast against each other (e.g. a trajectory ``(T, nx)`` with ``(T, nu)``, a rollout
        ``(T, N, nx)`` with ``(T, N, nu)``, or many states with one input ``(nu,)``). One ``fc.map`` call.
        """
        return _evaluate_mapped(self.fc, "evaluate_fc", self.nx, self.nu, x, u)

    def evaluate_fd(self, x, u) -> np.ndarray:
        """``fd`` on numpy arrays of points: ``x (..., nx)``, ``u (..., nu)`` -> ``x_next (..., nx)`` (as
        ``evaluate_fc``)."""
        return _evaluate_mapped(self.fd, "evaluate_fd", self.nx, self.nu, x, u)

    def linearize(self, x0, u0) -> Linearization:
        """Continuous and discrete Jacobians about ``(x0 (nx,), u0 (nu,))``."""
        A, B = self.df(np.asarray(x0, float), np.asarray(u0, float))
        Ad, Bd = self.dfd(np.asarray(x0, float), np.asarray(u0, float))
        return Linearization(A=np.array(A), B=np.array(B), Ad=np.array(Ad), Bd=np.array(Bd))


def _evaluate_mapped(function: cs.Function, name: str, nx: int, nu: int, x, u) -> np.ndarray:
    """``function(x, u)`` over the broadcast leading axes of ``x (..., nx)`` and ``u (..., nu)``."""
    x, u = np.asarray(x, dtype=float), np.asarray(u, dtype=float)
    if x.ndim == 0 or x.shape[-1] != nx:
        raise ValueError(f"{name}: x must have shape (..., nx) with nx = {nx}, got {x.shape}")
    if u.ndim == 0 or u.shape[-1] != nu:
        raise ValueError(f"{name}: u must have shape (..., nu) with nu = {nu}, got {u.shape}")
    try:
        lead = np.broadcast_shapes(x.shape[:-1], u.shape[:-1])
    except ValueError:
        raise ValueError(
            f"{name}: the leading axes of x {x.shape[:-1]} and u {u.shape[:-1]} do not broadcast"
        ) from None
    xs = np.broadcast_to(x, lead + (nx,)).reshape(-1, nx)
    us = np.broadcast_to(u, lead + (nu,)).reshape(-1, nu)
    if xs.shape[0] == 0:
        return np.zeros(lead + (nx,))
    out = function.map(xs.shape[0])(xs.T, us.T)  # CasADi's map takes one point per column
    return np.asarray(out.full()).T.reshape(lead + (nx,))


def _to_float(name: str, value) -> float:
    array = np.asarray(value, dtype=float)
    if array.shape != ():
        raise ValueError(
            f"symbolic_model: params.physics.{name} must be a scalar (unbatched params), got shape {array.shape}"
        )
    return float(array)


_PLANT_STEPS = CompileCache(maxsize=16)


def plant_step(env) -> cs.Function:
    """``fd(x (nx,), u (nu,), p (np,)) -> x_next (nx, 1)``: one control period with the env's integrator and
    substeps, the plant's physics as the parameter vector ``p`` (``physics_vector``). Built once per env, so a
    sweep over plants evaluates one CasADi function instead of building a ``SymbolicModel`` per plant; it equals
    ``env.symbolic_model(params).fd`` at ``p = physics_vector(params)``."""
    return _PLANT_STEPS.get("fd", lambda: _build_plant_step(env), owners=(env,))


def physics_vector(params) -> np.ndarray:
    """The plant's physics ``params.physics`` as ``plant_step``'s parameter vector (fields in declaration order)."""
    physics = params.physics
    return np.array([_to_float(f.name, getattr(physics, f.name)) for f in dataclasses.fields(physics)])


def _build_plant_step(env) -> cs.Function:
    system = env.system
    names = [f.name for f in dataclasses.fields(system.params_cls)]
    p = cs.SX.sym("p", len(names))
    physics = system.params_cls(**{name: p[i] for i, name in enumerate(names)})
    x, u = cs.SX.sym("x", system.nx), cs.SX.sym("u", system.nu)
    x_next = env.discrete_dynamics()(x, u, physics, casadi_backend)
    return cs.Function("fd", [x, u, p], [x_next], ["x", "u", "p"], ["x_next"])


def build_symbolic_model(env, params, discretization: str = "env") -> SymbolicModel:
    """Build the ``SymbolicModel`` of ``env`` for ``params`` (see ``Env.symbolic_model``)."""
    if discretization not in DISCRETIZATIONS:
        raise ValueError(
            f"discretization: unknown value {discretization!r}; allowed values are {', '.join(DISCRETIZATIONS)}"
        )
    system = env.system
    physics = system.params_cls(
        **{f.name: _to_float(f.name, getattr(params.physics, f.name)) for f in dataclasses.fields(params.physics)}
    )
    nx, nu = system.nx, system.nu
    x = cs.SX.sym("x", nx)
    u = cs.SX.sym("u", nu)

    x_dot = system.dynamics(x, u, physics, casadi_backend)
    if discretization == "env":
        step = env.discrete_dynamics()
    else:
        step = make_discrete_dynamics(system.dynamics, "rk4", env.dt, 1, system.velocity_mask)
    x_next = step(x, u, physics, casadi_backend)

    fc = cs.Function("fc", [x, u], [x_dot], ["x", "u"], ["x_dot"])
    fd = cs.Function("fd", [x, u], [x_next], ["x", "u"], ["x_next"])
    df = cs.Function("df", [x, u], [cs.jacobian(x_dot, x), cs.jacobian(x_dot, u)], ["x", "u"], ["A", "B"])
    dfd = cs.Function("dfd", [x, u], [cs.jacobian(x_next, x), cs.jacobian(x_next, u)], ["x", "u"], ["Ad", "Bd"])

    Q = np.asarray(params.Q, dtype=float)
    R = np.asarray(params.R, dtype=float)
    x_ref_sym = cs.SX.sym("x_ref", nx)
    u_ref_sym = cs.SX.sym("u_ref", nu)
    dx, du = x - x_ref_sym, u - u_ref_sym
    stage = 0.5 * cs.mtimes([dx.T, Q, dx]) + 0.5 * cs.mtimes([du.T, R, du])
    l_x, l_u = cs.gradient(stage, x), cs.gradient(stage, u)
    cost = cs.Function(
        "cost",
        [x, u, x_ref_sym, u_ref_sym],
        [stage, l_x, l_u, cs.jacobian(l_x, x), cs.jacobian(l_u, u), cs.jacobian(l_x, u)],
        ["x", "u", "x_ref", "u_ref"],
        ["l", "l_x", "l_u", "l_xx", "l_uu", "l_xu"],
    )

    constraint_functions, rows = [], []
    for i, (spec, values) in enumerate(zip(env.constraint_specs, params.constraints, strict=True)):
        numeric = jax.tree.map(lambda v: np.asarray(v, dtype=float), values)
        g_i = constraints_lib.evaluate(spec, numeric, x, u, casadi_backend)
        constraint_functions.append(cs.Function(f"g{i}", [x, u], [g_i], ["x", "u"], ["g"]))
        rows.append(g_i)
    g = cs.Function("g", [x, u], [cs.vertcat(*rows) if rows else cs.SX(0, 1)], ["x", "u"], ["g"])
    tolerances = tuple(float(np.asarray(c.tolerance)) for c in params.constraints)

    x_ref, u_ref = jitted_method(env, "reference")(params)
    return SymbolicModel(
        nx=nx,
        nu=nu,
        dt=env.dt,
        x=x,
        u=u,
        fc=fc,
        fd=fd,
        df=df,
        dfd=dfd,
        cost=cost,
        Q=Q,
        R=R,
        x_ref=np.asarray(x_ref, dtype=float),
        u_ref=np.asarray(u_ref, dtype=float),
        discretization=discretization,
        constraints=tuple(constraint_functions),
        g=g,
        constraint_specs=env.constraint_specs,
        constraint_tolerances=tolerances,
    )
