"""CBF-QP safety filter (Ames et al.): the input closest to the controller's that keeps a barrier ``h >= 0``.

Model: the prior's continuous-time dynamics in control-affine form ``x_dot = f(x) + g(x) u``, read off the
system's one ``dynamics`` function: ``f(x) = dynamics(x, 0)`` and ``g(x) = d dynamics / d u`` at ``u = 0`` (exact
for a control-affine model; ``make_cbf`` checks ``d^2 dynamics / d u^2 = 0`` at random points and refuses other
models). A barrier is any function ``h(x, barrier_params, xp=jax_backend) -> scalar`` written with the ``xp``
backend namespace (``scg_jax.backends``), so the same function builds the JAX filter (Lie derivatives
``Lf h = grad h . f``, ``Lg h = grad h . g`` by ``jax.grad``) and its CasADi mirror (``casadi.jacobian``).

QP per step, with ``u_L`` the controller's input clipped to the input box (the original's convention)::

    min_{u, s}  1/2 |u - u_L|^2 + k s^2
    s.t.        Lf h_i(x) + Lg h_i(x) u + alpha h_i(x) + s_i >= 0,   s_i >= 0 (soft; s_i = 0 when hard),
                u_low <= u <= u_high,

``alpha`` (``slope``, 1/s) the linear class-K function's slope, ``k`` the ``slack_weight``.

Solvers (``solver`` option): ``closed_form`` for one barrier (exact, vmappable; the piecewise-affine multiplier
equation solved segment by segment, see ``solve_single``), ``qpax`` for several (interior point in float64 when
``jax_enable_x64`` is on, status checked), ``casadi`` (qpOASES through ``casadi.conic``, a host filter, the
parity reference). Where ``u_L`` already satisfies every constraint it is returned unchanged, bit for bit.

Barriers shipped (``barrier`` option): ``ellipsoid`` (the original's cart-pole candidate
``h = 1 - sum_i (x_i / x_i,max)^2``, a CBF *candidate*: ``is_valid_cbf`` finds states in its safe set where no
input satisfies the condition), ``ceiling`` (1D quadrotor altitude ceiling, braking distance
``h = z_max - z - v^2 / (2 a_b)`` with ``v`` a smooth ``max(z_dot, 0)``) and ``cartpole_position`` (two
braking-distance barriers on the cart position, ``|x| <= x_max``; both braking barriers use a smooth approach
speed, see ``approach_speed``).
"""

from __future__ import annotations

import dataclasses
import inspect
from collections.abc import Callable, Sequence
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from scg_algorithms.base import option, parse_options
from scg_algorithms.controller_setup import input_limits
from scg_algorithms.safety_filters.base import FilterInfo, HostFilter, JaxFilter
from scg_jax.backends import casadi_backend, jax_backend
from scg_jax.validation import FieldError

PATH = "safety_filters.cbf"
BARRIERS = ("auto", "ellipsoid", "ceiling", "cartpole_position")
SOLVERS = ("auto", "closed_form", "qpax", "casadi")
# Which barriers each system may use, and its "auto" choice (the first).
SYSTEM_BARRIERS = {
    "cartpole": ("ellipsoid", "cartpole_position"),
    "quadrotor_1d": ("ceiling", "ellipsoid"),
    "quadrotor_2d": ("ellipsoid",),
    "quadrotor_3d": ("ellipsoid",),
}


@dataclasses.dataclass(frozen=True)
class Options:
    """Options of ``make_cbf`` (a config's ``safety_filters.cbf`` section); errors name ``safety_filters.cbf.KEY``."""

    barrier: str = option("auto", "barrier: ellipsoid, ceiling (quadrotor_1d), cartpole_position", BARRIERS)
    solver: str = option("auto", "closed_form (one barrier), qpax, casadi (host); auto: closed form if one", SOLVERS)
    slope: float = option(0.1, "alpha, slope of the linear class-K function alpha h, 1/s")
    soft_constrained: bool = option(True, "soft barrier constraint with a slack variable")
    slack_weight: float = option(1e4, "k, weight of the slack in the cost k s^2")
    slack_tolerance: float = option(1e-3, "slack above this reports feasible = False")
    ellipsoid_axes: tuple | None = option(
        None, "(nx,) semi-axes x_i,max of the ellipsoid (inf: unbounded); default min(|low|, |high|) of the state box"
    )
    position_max: tuple | None = option(
        None, "ceiling z_max or cart limit x_max, m; default the upper position bound of the env's state constraints"
    )
    braking_deceleration: tuple | None = option(
        None, "a_b of the braking barriers, m/s^2; default 0.9 (g - T_min/m) (ceiling), 0.5 F_max/(m_c+m_p) (cart)"
    )
    velocity_smoothing: float = option(0.5, "epsilon of the braking barriers' smooth approach speed, m/s")

    def _check(self, path: str) -> None:
        for name in ("slope", "slack_weight", "velocity_smoothing"):
            if not getattr(self, name) > 0:
                raise FieldError(f"{path}.{name}", f"must be > 0, got {getattr(self, name)!r}")
        if not self.slack_tolerance >= 0:
            raise FieldError(f"{path}.slack_tolerance", f"must be >= 0, got {self.slack_tolerance!r}")
        for name in ("position_max", "braking_deceleration"):
            value = getattr(self, name)
            if value is not None and (len(value) != 1 or not value[0] > 0):
                raise FieldError(f"{path}.{name}", f"expected one positive number, got {list(value)}")


# --------------------------------------------------------------------------------------------- barriers
def ellipsoid_barrier(x, params, xp=jax_backend):
    """``h = 1 - sum_i (x_i * inv_axes_i)^2``; ``params["inv_axes"]`` (nx,) holds ``1 / x_i,max`` (0: unbounded)."""
    inv = params["inv_axes"]
    return 1.0 - sum((x[i] * inv[i]) ** 2 for i in range(len(inv)))


def approach_speed(v, smoothing, xp=jax_backend):
    """A smooth ``max(v, 0)``: ``(v + sqrt(v^2 + smoothing^2)) / 2`` (m/s), >= ``max(v, 0)`` and strictly increasing,
    so a braking barrier built on it keeps input authority (``Lg h != 0``) when the plant moves away from the limit
    too; with the exact ``max`` the QP cannot act at ``v <= 0`` and the sampled loop creeps over the limit."""
    return 0.5 * (v + xp.sqrt(v * v + smoothing * smoothing))


def ceiling_barrier(x, params, xp=jax_backend):
    """1D quadrotor ceiling: ``h = z_max - z - v^2 / (2 a_b)``, ``v = approach_speed(z_dot)`` (m): the height left
    after braking at ``a_b`` (m/s^2). A valid CBF when the thrust can decelerate by ``a_b``: full braking gives
    ``h_dot = -z_dot + v v' a / a_b >= 0`` for any ``a >= a_b`` (since ``v v' >= z_dot``)."""
    v = approach_speed(x[1], params["smoothing"], xp)
    return params["position_max"] - x[0] - v * v / (2.0 * params["deceleration"])


def cart_upper_barrier(x, params, xp=jax_backend):
    """Cart position below ``x_max`` after braking at ``a_b``: ``x_max - x - v^2 / (2 a_b)``, ``v`` the smooth
    approach speed ``approach_speed(x_dot)`` (m)."""
    v = approach_speed(x[1], params["smoothing"], xp)
    return params["position_max"] - x[0] - v * v / (2.0 * params["deceleration"])


def cart_lower_barrier(x, params, xp=jax_backend):
    """Cart position above ``-x_max`` after braking: ``x_max + x - v^2 / (2 a_b)``, ``v = approach_speed(-x_dot)``."""
    v = approach_speed(-x[1], params["smoothing"], xp)
    return params["position_max"] + x[0] - v * v / (2.0 * params["deceleration"])


class Terms(NamedTuple):
    """The barrier values and Lie derivatives at one state: ``h`` (m,), ``Lf`` (m,) 1/s, ``Lg`` (m, nu) 1/(s N)."""

    h: Any
    Lf: Any
    Lg: Any


# --------------------------------------------------------------------------------------------- QP solvers
def solve_single(u_l, a, c, u_low, u_high, inv_two_k):
    """Exact solution of ``min 1/2 |u - u_l|^2 + k s^2 s.t. c + a.u + s >= 0, u_low <= u <= u_high``.

    KKT: ``u(lam) = clip(u_l + lam a)``, ``s = lam / (2k)``, and ``lam = 0`` if ``phi(0) >= 0`` else the root of
    ``phi(lam) = c + a.u(lam) + lam / (2k)``. ``phi`` is nondecreasing and affine between the ``2 nu`` multipliers
    where an input enters or leaves the box, so the root is found by evaluating ``phi`` at those breakpoints and
    solving the one affine piece that brackets it; no iteration.

    Args:
        u_l: (nu,) the target input, inside the box. a: (nu,) ``Lg h``. c: scalar ``Lf h + alpha h``.
        u_low, u_high: (nu,) the box. inv_two_k: ``1 / (2 k)``; 0 for a hard constraint.

    Returns:
        ``(u (nu,), s, solved)``; ``solved`` is False only for a hard constraint no box input satisfies (then ``u`` is
        the box input that comes closest, ``s`` the remaining shortfall).
    """
    phi0 = c + jnp.dot(a, u_l)
    nonzero = a != 0
    safe_a = jnp.where(nonzero, a, 1.0)
    breaks = jnp.concatenate([(u_low - u_l) / safe_a, (u_high - u_l) / safe_a])
    breaks = jnp.where(jnp.concatenate([nonzero, nonzero]) & (breaks > 0), breaks, 0.0)
    lams = jnp.concatenate([jnp.zeros(1, breaks.dtype), breaks])

    def phi(lam):
        return c + jnp.dot(a, jnp.clip(u_l + lam * a, u_low, u_high)) + lam * inv_two_k

    phis = jax.vmap(phi)(lams)
    lam_k = jnp.max(jnp.where(phis <= 0, lams, 0.0))
    phi_k = phi(lam_k)
    above = jnp.where(lams > lam_k, lams, jnp.inf)
    lam_next = jnp.min(above)
    probe = jnp.where(jnp.isfinite(lam_next), 0.5 * (lam_k + lam_next), lam_k + 1.0)
    u_probe = u_l + probe * a
    free = (u_probe > u_low) & (u_probe < u_high)
    slope = jnp.sum(jnp.where(free, a * a, 0.0)) + inv_two_k
    solvable = slope > 0
    lam_star = lam_k - phi_k / jnp.where(solvable, slope, 1.0)
    u_star = jnp.clip(u_l + lam_star * a, u_low, u_high)
    # A hard constraint with every input saturated and phi still < 0: no box input satisfies it.
    u_best = jnp.where(a > 0, u_high, jnp.where(a < 0, u_low, u_l))
    u_active = jnp.where(solvable, u_star, u_best)
    s_active = jnp.where(solvable, lam_star * inv_two_k, -(c + jnp.dot(a, u_best)))
    safe = phi0 >= 0
    u = jnp.where(safe, u_l, u_active)
    s = jnp.where(safe, jnp.zeros_like(s_active), jnp.maximum(s_active, 0.0))
    return u, s, safe | solvable


def qpax_dtype():
    """float64 when ``jax_enable_x64`` is on (qpax is reliable there), else float32."""
    return jnp.float64 if jax.config.read("jax_enable_x64") else jnp.float32


def solve_qpax(u_l, Lg, c, u_low, u_high, slack_weight, soft: bool, tolerance: float = 1e-6):
    """The CBF-QP with ``m`` barriers by qpax (interior point), status checked.

    Args:
        u_l: (nu,) target input inside the box. Lg: (m, nu). c: (m,) ``Lf h + alpha h``. u_low, u_high: (nu,).
        slack_weight: ``k``. soft: one slack per barrier. tolerance: accepted constraint residual.

    Returns:
        ``(u, s, solved)``: ``s`` the largest slack; when qpax does not converge or returns a non-finite or
        infeasible point, ``u = u_l`` (the closest box input), ``s`` the largest shortfall there, ``solved`` False.
    """
    dtype = qpax_dtype()
    import qpax

    m, nu = Lg.shape
    u_l, Lg, c = u_l.astype(dtype), Lg.astype(dtype), c.astype(dtype)
    lo, hi = jnp.asarray(u_low, dtype), jnp.asarray(u_high, dtype)
    eye_u = jnp.eye(nu, dtype=dtype)
    if soft:
        n = nu + m
        Q = jnp.diag(jnp.concatenate([jnp.ones(nu, dtype), 2.0 * slack_weight * jnp.ones(m, dtype)]))
        q = jnp.concatenate([-u_l, jnp.zeros(m, dtype)])
        zeros_um = jnp.zeros((nu, m), dtype)
        G = jnp.concatenate(
            [
                jnp.concatenate([-Lg, -jnp.eye(m, dtype=dtype)], axis=1),
                jnp.concatenate([eye_u, zeros_um], axis=1),
                jnp.concatenate([-eye_u, zeros_um], axis=1),
                jnp.concatenate([jnp.zeros((m, nu), dtype), -jnp.eye(m, dtype=dtype)], axis=1),
            ]
        )
        h = jnp.concatenate([c, hi, -lo, jnp.zeros(m, dtype)])
    else:
        n = nu
        Q, q = eye_u, -u_l
        G = jnp.concatenate([-Lg, eye_u, -eye_u])
        h = jnp.concatenate([c, hi, -lo])
    # qpax's own flag needs |s_i z_i| < tol with s floored at sqrt(eps); with the large multipliers a slack weight
    # of 1e4 gives it is never raised although the iterate is optimal. The status is checked here instead, on the
    # KKT conditions of the returned primal-dual pair, relative to the problem's scale.
    tol = 1e-8 if dtype == jnp.float64 else 1e-4
    z, _, dual, _, _, _ = qpax.solve_qp(
        Q, q, jnp.zeros((0, n), dtype), jnp.zeros(0, dtype), G, h, solver_tol=tol, max_iter=50
    )
    gap = h - G @ z
    scale = 1.0 + jnp.max(jnp.abs(h)) + jnp.max(jnp.abs(q))
    stationarity = jnp.max(jnp.abs(Q @ z + q + G.T @ dual)) / (1.0 + jnp.max(jnp.abs(dual)))
    complementarity = jnp.max(jnp.abs(dual * gap)) / (1.0 + jnp.max(jnp.abs(dual)))
    kkt_ok = (
        (stationarity <= 10 * tol * scale)
        & (complementarity <= 10 * tol * scale)
        & (jnp.min(gap) >= -10 * tol * scale)
        & (jnp.min(dual) >= -10 * tol * scale)
    )
    u = jnp.clip(z[:nu], lo, hi)
    s = jnp.maximum(z[nu:], 0.0) if soft else jnp.zeros(m, dtype)
    residual = jnp.min(c + Lg @ u + s)
    ok = kkt_ok & jnp.all(jnp.isfinite(z)) & (residual >= -tolerance * (1.0 + jnp.max(jnp.abs(c))))
    shortfall = jnp.maximum(-jnp.min(c + Lg @ u_l), 0.0)
    safe = jnp.all(c + Lg @ u_l >= 0)
    u_out = jnp.where(safe, u_l, jnp.where(ok, u, u_l))
    s_out = jnp.where(safe, 0.0, jnp.where(ok, jnp.max(s), shortfall))
    return u_out, s_out, safe | ok


# --------------------------------------------------------------------------------------------- the filter
@dataclasses.dataclass(frozen=True, eq=False)
class CBFFilter(JaxFilter):
    """A ``JaxFilter`` that also exposes its barrier terms (for ``is_valid_cbf``).

    Attributes (besides ``JaxFilter``'s): terms_fn: ``terms_fn(x, params) -> Terms`` (one state).
    """

    terms_fn: Callable = None


@dataclasses.dataclass(frozen=True, eq=False)
class CasadiCBFFilter(HostFilter):
    """The CasADi/qpOASES CBF-QP, one copy on the host; ``terms_fn(x (nx,)) -> Terms`` (numpy)."""

    terms_fn: Callable = None


def _barrier_accepts_xp(h) -> bool:
    try:
        return "xp" in inspect.signature(h).parameters
    except (TypeError, ValueError):
        return False


def _state_sample_box(system, n: int = 8, seed: int = 0):
    low = np.where(np.isfinite(system.state_low), system.state_low, -2.0)
    high = np.where(np.isfinite(system.state_high), system.state_high, 2.0)
    return np.random.default_rng(seed).uniform(low, high, size=(n, system.nx))


def check_control_affine(system, physics, u_low, u_high, path: str, num_points: int = 8, seed: int = 0) -> None:
    """Raise ``ValueError`` naming ``path`` unless ``d^2 dynamics / d u^2 = 0`` at random states and inputs."""
    rng = np.random.default_rng(seed)
    xs = _state_sample_box(system, num_points, seed)
    us = rng.uniform(u_low, u_high, size=(num_points, system.nu))

    def second(x, u):
        return jax.hessian(lambda v: system.dynamics(x, v, physics, jax_backend))(u)

    hessians = np.asarray(jax.jit(jax.vmap(second))(jnp.asarray(xs), jnp.asarray(us)))
    worst = np.abs(hessians).reshape(num_points, -1).max(axis=1)
    scale = 1.0 + np.abs(np.asarray(jax.vmap(lambda x, u: system.dynamics(x, u, physics, jax_backend))(xs, us))).max()
    if worst.max() > 1e-6 * scale:
        i = int(np.argmax(worst))
        raise ValueError(
            f"{path}: the {system.name} model is not control-affine (|d2f/du2| = {worst[i]:.3g} at x = "
            f"{np.round(xs[i], 4).tolist()}, u = {np.round(us[i], 4).tolist()}); the CBF-QP needs x_dot = f(x) + "
            "g(x) u"
        )


def check_scalar_barriers(barriers: Sequence[Callable], barrier_params, nx: int, path: str) -> None:
    """Raise ``ValueError`` naming ``path[i]`` unless every barrier returns a scalar for an (nx,) state."""
    for i, h in enumerate(barriers):
        try:
            shape = jax.eval_shape(h, jax.ShapeDtypeStruct((nx,), jnp.float32), barrier_params).shape
        except Exception as error:  # noqa: BLE001 - any failure to trace is a bad barrier; say which
            raise ValueError(f"{path}[{i}]: h(x, barrier_params) fails on an ({nx},) state: {error}") from None
        if shape != ():
            raise ValueError(f"{path}[{i}]: a barrier h(x, barrier_params) must return a scalar, got shape {shape}")


def cbf_filter(
    system,
    physics,
    u_low,
    u_high,
    barriers: Sequence[Callable],
    barrier_params,
    *,
    slope: float = 0.1,
    slack_weight: float = 1e4,
    soft_constrained: bool = True,
    slack_tolerance: float = 1e-3,
    solver: str = "auto",
    correction: Callable | None = None,
    correction_params=None,
    name: str = "cbf",
    info: dict | None = None,
    path: str = PATH,
):
    """The CBF-QP filter for ``system`` with the prior ``physics`` and any barrier functions.

    Args:
        system: an ``scg_jax`` ``System`` (its ``dynamics`` is the model). physics: the prior's physics pytree.
        u_low, u_high: (nu,) the input box, N. barriers: functions ``h(x, barrier_params, xp=jax_backend) ->
            scalar`` (m of them). barrier_params: their parameters (a pytree of arrays, traced).
        slope: alpha, 1/s. slack_weight: k. soft_constrained: slack variables (else hard constraints).
        slack_tolerance: slack above it reports ``feasible = False``.
        solver: ``closed_form`` (one barrier), ``qpax``, ``casadi`` (host filter; needs barriers taking ``xp``),
            ``auto`` (closed form for one barrier, qpax for several).
        correction: optional ``correction(x, correction_params) -> (a (m, nu), b (m,))`` added to the Lie
            derivatives (the learned CBF); ``correction_params`` traced. name, info: the filter's name and report.

    Returns:
        a ``CBFFilter`` (JAX) or, for ``solver="casadi"``, a ``CasadiCBFFilter`` (host).

    Raises:
        ValueError: a barrier not scalar, a non-control-affine model, closed_form with several barriers.
    """
    barriers = tuple(barriers)
    m, nx, nu = len(barriers), system.nx, system.nu
    if m == 0:
        raise ValueError(f"{path}.barrier: at least one barrier function is needed")
    u_low = np.asarray(u_low, dtype=np.float64).reshape(nu)
    u_high = np.asarray(u_high, dtype=np.float64).reshape(nu)
    barrier_params = jax.tree.map(lambda v: np.asarray(v, dtype=np.float64), barrier_params)
    physics = jax.tree.map(lambda v: np.asarray(v, dtype=np.float64), physics)
    check_scalar_barriers(barriers, barrier_params, nx, f"{path}.barrier")
    check_control_affine(system, physics, u_low, u_high, path)
    if solver == "auto":
        solver = "closed_form" if m == 1 else "qpax"
    if solver not in SOLVERS[1:]:
        raise FieldError(f"{path}.solver", f"unknown value {solver!r}; allowed values are {', '.join(SOLVERS)}")
    if solver == "closed_form" and m != 1:
        raise FieldError(
            f"{path}.solver", f"closed_form solves one barrier, this filter has {m}; allowed values are qpax, casadi"
        )
    report = {
        "nu": nu,
        "solver": solver,
        "num_barriers": m,
        "slope": slope,
        "slack_weight": slack_weight,
        "soft_constrained": soft_constrained,
        **(info or {}),
    }
    if solver == "casadi":
        if correction is not None:
            raise ValueError(f"{path}.solver: the casadi filter has no learned correction; use closed_form or qpax")
        for i, h in enumerate(barriers):
            if not _barrier_accepts_xp(h):
                raise ValueError(f"{path}.barrier[{i}]: the casadi filter needs a barrier h(x, params, xp)")
        return _casadi_filter(
            system, physics, u_low, u_high, barriers, barrier_params, slope, slack_weight, soft_constrained,
            slack_tolerance, name, report,
        )  # fmt: skip

    params = {
        "physics": physics,
        "barrier": barrier_params,
        "slope": np.float64(slope),
        "slack_weight": np.float64(slack_weight),
        "u_low": u_low,
        "u_high": u_high,
    }
    if correction is not None:
        params["correction"] = correction_params

    def terms_fn(x, p) -> Terms:
        u0 = jnp.zeros(nu, x.dtype)
        f = system.dynamics(x, u0, p["physics"], jax_backend)
        g = jax.jacfwd(lambda u: system.dynamics(x, u, p["physics"], jax_backend))(u0)
        hs, Lf, Lg = [], [], []
        for h in barriers:
            value, grad = jax.value_and_grad(h)(x, p["barrier"])
            hs.append(value)
            Lf.append(jnp.dot(grad, f))
            Lg.append(grad @ g)
        terms = Terms(jnp.stack(hs), jnp.stack(Lf), jnp.stack(Lg))
        if correction is not None:
            a, b = correction(x, p["correction"])
            terms = Terms(terms.h, terms.Lf + b, terms.Lg + a)
        return terms

    def reset_fn(key):
        return ()

    def certify_fn(obs, u_uncertified, p, filter_state):
        x = obs[:nx]  # the state part of the observation (scg_algorithms.base.state_from_obs)
        u_unc = jnp.asarray(u_uncertified).reshape(nu)
        lo, hi = jnp.asarray(p["u_low"]), jnp.asarray(p["u_high"])
        lo, hi = lo.astype(u_unc.dtype), hi.astype(u_unc.dtype)
        u_l = jnp.clip(u_unc, lo, hi)
        terms = terms_fn(x, p)
        c = terms.Lf + p["slope"] * terms.h
        if solver == "closed_form":
            inv_two_k = 0.5 / p["slack_weight"] if soft_constrained else 0.0
            u, s, solved = solve_single(u_l, terms.Lg[0].astype(u_l.dtype), c[0], lo, hi, inv_two_k)
        else:
            u, s, solved = solve_qpax(u_l, terms.Lg, c, lo, hi, p["slack_weight"], soft_constrained)
            u = u.astype(u_unc.dtype)
        u = u.astype(u_unc.dtype)
        s = s.astype(u_unc.dtype)
        info_ = FilterInfo(feasible=solved & (s <= slack_tolerance), slack=s, correction=u - u_unc)
        return u, filter_state, info_

    return CBFFilter(
        name=name,
        system=system.name,
        params=params,
        reset_fn=reset_fn,
        certify_fn=certify_fn,
        info=report,
        terms_fn=terms_fn,
    )


def _casadi_filter(
    system, physics, u_low, u_high, barriers, barrier_params, slope, slack_weight, soft, slack_tolerance, name, report
):
    """The same QP built from the same ``h`` on CasADi symbols and solved by qpOASES (``casadi.conic``)."""
    import casadi as cs

    nx, nu, m = system.nx, system.nu, len(barriers)
    physics_values = system.params_cls(**{k: float(v) for k, v in dataclasses.asdict(physics).items()})
    x = cs.SX.sym("x", nx)
    u = cs.SX.sym("u", nu)
    x_dot = system.dynamics(x, u, physics_values, casadi_backend)
    f = cs.substitute(x_dot, u, cs.DM.zeros(nu))
    g = cs.substitute(cs.jacobian(x_dot, u), u, cs.DM.zeros(nu))
    hs = [h(x, barrier_params, xp=casadi_backend) for h in barriers]
    h_all = cs.vertcat(*hs)
    grad = cs.jacobian(h_all, x)  # (m, nx)
    terms = cs.Function("cbf_terms", [x], [h_all, cs.mtimes(grad, f), cs.mtimes(grad, g)])

    n = nu + (m if soft else 0)
    H = np.diag(np.concatenate([np.ones(nu), 2.0 * slack_weight * np.ones(m if soft else 0)]))
    A_pattern = cs.DM.ones(m, n)
    qp = cs.conic(
        "cbf_qp",
        "qpoases",
        {"h": cs.DM(H).sparsity(), "a": A_pattern.sparsity()},
        {"printLevel": "none", "error_on_fail": False},
    )
    lbx = np.concatenate([u_low, np.zeros(m if soft else 0)])
    ubx = np.concatenate([u_high, np.full(m if soft else 0, np.inf)])

    def terms_fn(x_value):
        h_v, lf_v, lg_v = terms(np.asarray(x_value, dtype=np.float64))
        return Terms(np.asarray(h_v).reshape(m), np.asarray(lf_v).reshape(m), np.asarray(lg_v).reshape(m, nu))

    def certify_fn(obs, u_uncertified, params, filter_state):
        u_unc = np.asarray(u_uncertified, dtype=np.float64).reshape(nu)
        u_l = np.clip(u_unc, u_low, u_high)
        t = terms_fn(np.asarray(obs, dtype=np.float64)[:nx])
        c = t.Lf + slope * t.h
        if np.all(c + t.Lg @ u_l >= 0):
            return u_l, filter_state, FilterInfo(np.asarray(True), np.asarray(0.0), u_l - u_unc)
        A = np.concatenate([t.Lg, np.eye(m)], axis=1) if soft else t.Lg
        sol = qp(h=H, g=np.concatenate([-u_l, np.zeros(m if soft else 0)]), a=A, lba=-c, uba=np.inf, lbx=lbx, ubx=ubx)
        solved = bool(qp.stats()["success"])
        z = np.asarray(sol["x"]).reshape(n)
        if not solved or not np.all(np.isfinite(z)):
            shortfall = max(-float(np.min(c + t.Lg @ u_l)), 0.0)
            return u_l, filter_state, FilterInfo(np.asarray(False), np.asarray(shortfall), u_l - u_unc)
        u_out = np.clip(z[:nu], u_low, u_high)
        s = float(np.max(np.maximum(z[nu:], 0.0))) if soft else 0.0
        return u_out, filter_state, FilterInfo(np.asarray(s <= slack_tolerance), np.asarray(s), u_out - u_unc)

    return CasadiCBFFilter(
        name=name,
        system=system.name,
        params={"physics": physics, "barrier": barrier_params, "slope": slope},
        reset_fn=lambda key: (),
        certify_fn=certify_fn,
        info={**report, "solver": "casadi"},
        terms_fn=terms_fn,
    )


# --------------------------------------------------------------------------------------------- from an env
def _state_box(env, prior_params):
    from scg_jax.constraints import box_bounds

    x_low, x_high, _, _ = box_bounds(env.constraint_specs, prior_params.constraints, env.nx, env.nu)
    return x_low, x_high


def barrier_setup(env, prior_params, opts: Options, path: str = PATH):
    """``(barrier name, barrier functions, barrier params)`` of ``opts`` for ``env`` with the prior physics.

    Raises:
        FieldError: ``<path>.barrier`` not available for the system, or a bound with no default.
    """
    system = env.system.name
    allowed = SYSTEM_BARRIERS.get(system, ())
    barrier = allowed[0] if opts.barrier == "auto" and allowed else opts.barrier
    if barrier not in allowed:
        raise FieldError(
            f"{path}.barrier",
            f"{opts.barrier!r} is not available for {system}; allowed values are auto, {', '.join(allowed)}",
        )
    physics = prior_params.physics
    x_low, x_high = _state_box(env, prior_params)
    u_low, _ = input_limits(env, prior_params)
    if barrier == "ellipsoid":
        if opts.ellipsoid_axes is not None:
            if len(opts.ellipsoid_axes) != env.nx:
                raise FieldError(f"{path}.ellipsoid_axes", f"expected {env.nx} values, got {len(opts.ellipsoid_axes)}")
            axes = np.asarray(opts.ellipsoid_axes, dtype=np.float64)
        else:
            axes = np.minimum(np.abs(x_low), np.abs(x_high))
        if np.any(axes <= 0):
            raise FieldError(f"{path}.ellipsoid_axes", f"semi-axes must be > 0 (inf: unbounded), got {axes.tolist()}")
        inv = np.where(np.isfinite(axes), 1.0 / axes, 0.0)
        return barrier, (ellipsoid_barrier,), {"inv_axes": inv}
    if opts.position_max is not None:
        position_max = float(opts.position_max[0])
    else:
        position_max = float(x_high[0]) if barrier == "ceiling" else float(min(abs(x_low[0]), abs(x_high[0])))
        if not np.isfinite(position_max):
            raise FieldError(f"{path}.position_max", "the env has no finite position bound; give position_max (m)")
    if opts.braking_deceleration is not None:
        deceleration = float(opts.braking_deceleration[0])
    elif barrier == "ceiling":
        deceleration = 0.9 * (float(physics.gravity) - float(u_low[0]) / float(physics.mass))
    else:
        deceleration = 0.5 * float(physics.force_max) / (float(physics.cart_mass) + float(physics.pole_mass))
    if not deceleration > 0:
        raise FieldError(f"{path}.braking_deceleration", f"must be > 0, got {deceleration!r}")
    params = {
        "position_max": np.float64(position_max),
        "deceleration": np.float64(deceleration),
        "smoothing": np.float64(opts.velocity_smoothing),
    }
    functions = (ceiling_barrier,) if barrier == "ceiling" else (cart_upper_barrier, cart_lower_barrier)
    return barrier, functions, params


def make_cbf(env, prior_params, options=None, *, correction=None, correction_params=None, name: str = "cbf"):
    """The CBF-QP filter for ``env`` from the prior model ``prior_params`` (options: ``Options``).

    The model is ``env.system.dynamics`` with ``prior_params.physics``; the input box is the prior's actuator
    limits. ``correction``/``correction_params``: see ``cbf_filter`` (the learned CBF passes its network).
    """
    opts = parse_options(Options, options, PATH)
    barrier, functions, barrier_params = barrier_setup(env, prior_params, opts)
    u_low, u_high = input_limits(env, prior_params)
    info = {"barrier": barrier, **{k: np.asarray(v).tolist() for k, v in barrier_params.items()}}
    return cbf_filter(
        env.system,
        prior_params.physics,
        u_low,
        u_high,
        functions,
        barrier_params,
        slope=opts.slope,
        slack_weight=opts.slack_weight,
        soft_constrained=opts.soft_constrained,
        slack_tolerance=opts.slack_tolerance,
        solver=opts.solver,
        correction=correction,
        correction_params=correction_params,
        name=name,
        info=info,
    )


# --------------------------------------------------------------------------------------------- validity check
class ValidityReport(NamedTuple):
    """What ``is_valid_cbf`` found.

    Attributes:
        num_points: states sampled. num_inside: of them inside the safe set (every ``h >= 0``).
        num_infeasible: inside states where no box input satisfies every ``Lf h + Lg h u + alpha h >= -tolerance``.
        infeasible_fraction: ``num_infeasible / num_inside``. worst_states: (k, nx) the inside states with the
            most negative margin. worst_margins: (k,) their margins ``max_u min_i (Lf h_i + Lg h_i u + alpha h_i)``.
        low, high: (nx,) the sampled box.
    """

    num_points: int
    num_inside: int
    num_infeasible: int
    infeasible_fraction: float
    worst_states: np.ndarray
    worst_margins: np.ndarray
    low: np.ndarray
    high: np.ndarray


def _best_margin(c, Lg, u_low, u_high):
    """``max_{u in box} min_i (c_i + Lg_i u)`` for one state: exact for one barrier (a box vertex) or one input
    (the candidates are the box ends and the pairwise crossings); for several barriers and inputs, the smallest
    per-barrier maximum (an upper bound: a point it flags is infeasible for certain)."""
    per_barrier = c + jnp.sum(jnp.maximum(Lg * u_low, Lg * u_high), axis=1)
    m, nu = Lg.shape
    if m == 1 or nu > 1:
        return jnp.min(per_barrier)
    a, lo, hi = Lg[:, 0], u_low[0], u_high[0]
    da = a[:, None] - a[None, :]
    cross = jnp.where(da != 0, (c[None, :] - c[:, None]) / jnp.where(da != 0, da, 1.0), lo)
    candidates = jnp.concatenate([jnp.stack([lo, hi]), jnp.clip(cross.reshape(-1), lo, hi)])
    values = jnp.min(c[None, :] + candidates[:, None] * a[None, :], axis=1)
    return jnp.max(values)


def is_valid_cbf(
    safety_filter, env, num_points: int = 10_000, key=None, *, low=None, high=None, tolerance: float = 0.0,
    num_worst: int = 5,
) -> ValidityReport:  # fmt: skip
    """Randomised check of the CBF condition: sample states uniformly in a box, keep those in the safe set, and
    report where no input in the box satisfies ``Lf h + Lg h u + alpha h >= -tolerance`` (where the QP is
    infeasible without slack). A valid CBF has none.

    Args:
        safety_filter: a ``CBFFilter`` (or ``CasadiCBFFilter``) from ``make_cbf``. env: its env.
        num_points: states to sample. key: PRNG key (default ``key(0)``). low, high: (nx,) the box; default the
            env's state-constraint bounds, 2.0 where unbounded. tolerance: margin accepted. num_worst: how many
            worst states to return.
    """
    from scg_algorithms.safety_filters.base import check_system

    check_system(safety_filter, env)
    key = jax.random.key(0) if key is None else key
    params = safety_filter.params
    box_low, box_high = _state_box(env, env.default_params)
    low = np.where(np.isfinite(box_low), box_low, -2.0) if low is None else np.asarray(low, dtype=np.float64)
    high = np.where(np.isfinite(box_high), box_high, 2.0) if high is None else np.asarray(high, dtype=np.float64)
    xs = np.asarray(jax.random.uniform(key, (num_points, env.nx)), dtype=np.float64) * (high - low) + low
    if safety_filter.is_jax:
        u_low, u_high = jnp.asarray(params["u_low"]), jnp.asarray(params["u_high"])
        slope = params["slope"]

        def one(x):
            t = safety_filter.terms_fn(x, params)
            return jnp.min(t.h), _best_margin(t.Lf + slope * t.h, t.Lg, u_low, u_high)

        h_min, margin = (np.asarray(v, dtype=np.float64) for v in jax.jit(jax.vmap(one))(jnp.asarray(xs)))
    else:
        raise ValueError("is_valid_cbf: pass the JAX filter (solver closed_form or qpax), not the casadi one")
    inside = h_min >= 0
    bad = inside & (margin < -tolerance)
    order = np.argsort(np.where(inside, margin, np.inf))[: min(num_worst, int(inside.sum()))]
    num_inside = int(inside.sum())
    return ValidityReport(
        num_points=int(num_points),
        num_inside=num_inside,
        num_infeasible=int(bad.sum()),
        infeasible_fraction=float(bad.sum() / max(num_inside, 1)),
        worst_states=xs[order],
        worst_margins=margin[order],
        low=low,
        high=high,
    )


__all__ = [
    "BARRIERS",
    "PATH",
    "SOLVERS",
    "CBFFilter",
    "CasadiCBFFilter",
    "Options",
    "Terms",
    "ValidityReport",
    "barrier_setup",
    "cart_lower_barrier",
    "cart_upper_barrier",
    "cbf_filter",
    "ceiling_barrier",
    "check_control_affine",
    "check_scalar_barriers",
    "ellipsoid_barrier",
    "is_valid_cbf",
    "make_cbf",
    "solve_qpax",
    "solve_single",
]
