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

``alpha`` (``slope``, 1/s) the linear class-K function's slope, ``k`` the ``slack_weight``. A step whose slack
exceeds ``slack_tolerance`` is infeasible (``feasible = False``): inside the safe set (every ``h >= 0``) the
barrier's backup controller is applied where it has one (the backup barrier's LQR), else the QP's best effort.

Solvers (``solver`` option): ``closed_form`` for one barrier (exact, vmappable; the piecewise-affine multiplier
equation solved segment by segment, see ``solve_single``), ``qpax`` for several (interior point in float64 when
``jax_enable_x64`` is on, status checked), ``casadi`` (qpOASES through ``casadi.conic``, a host filter, the
parity reference). Where ``u_L`` already satisfies every constraint it is returned unchanged, bit for bit.

Barriers (``barrier`` option), built from the env's bounded and linear state constraints, one unit-norm row
``a^T x <= b`` each (``state_rows``):

- ``braking``: per row, the distance left after braking, ``h = b - margin - a^T x - v^2 / (2 a_b)`` with ``v`` a
  smooth approach speed ``approach_speed(a^T x_dot)``. For a row on positions of the world axes in
  ``BRAKING_AXES`` (a quadrotor's altitude: collective thrust brakes it without a torque, so the attitude stays
  under control). ``a_b`` is 0.9 times the smallest deceleration the input box gives over sampled states; a row
  the plant cannot always decelerate along (a floor under a tilted quadrotor) has none.
- ``backup``: one barrier for all rows, from a backup controller (Gurriet et al. 2018; Chen et al. 2021): the
  prior's LQR about ``backup_state`` is rolled out for ``backup_horizon`` seconds from ``x``, and ``h`` is a smooth
  minimum (``softmin_temperature``) over the rollout of every row's distance ``b - margin - a^T x_j`` and of the
  system's failure bounds. ``h >= 0`` where the backup keeps the plant inside, so the filter keeps the plant where
  it can still be saved: the cart-pole's position with the pole still recoverable. Valid for any row the backup
  respects, at the price of the rollout in every step.
- ``ellipsoid``: the original's cart-pole candidate ``h = 1 - sum_i (x_i / x_i,max)^2`` over the state box, a CBF
  *candidate*: ``is_valid_cbf`` finds states in its safe set where no input satisfies the condition.
- ``auto``: ``braking`` when every row has one, else ``backup``.

Every filter is checked when built: ``is_valid_cbf`` samples ``validation_samples`` states and the filter is refused
(``ValueError`` naming ``safety_filters.cbf.barrier``) when more than ``max_infeasible_fraction`` of those in the
safe set have no admissible input; the fraction is in ``info["validity"]``.
"""

from __future__ import annotations

import dataclasses
import inspect
import math
from collections.abc import Callable, Sequence
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from scg_algorithms.base import option, parse_options
from scg_algorithms.controller_setup import equilibrium_input, input_limits, prior_model
from scg_algorithms.safety_filters.backup import (
    backup_weights,
    diagonal_weight,
    failure_rows,
    sample_states,
    state_box,
    validation_box,
    validation_states,
)
from scg_algorithms.safety_filters.base import (
    BACKUP_CONTROLLER,
    BEST_EFFORT,
    CERTIFIED,
    Filter,
    FilterInfo,
    applied_correction,
)
from scg_jax.backends import casadi_backend, jax_backend
from scg_jax.validation import FieldError

PATH = "safety_filters.cbf"
BARRIERS = ("auto", "braking", "backup", "ellipsoid")
SOLVERS = ("auto", "closed_form", "qpax", "casadi")
# World axes (0 x, 1 y, 2 z) along which braking leaves the rest of the state under control: a quadrotor's
# collective thrust brakes its altitude without a torque. The cart's force that would brake the cart also tips the
# pole (the cart-pole is underactuated), and a quadrotor brakes horizontally only by tilting, so those rows get the
# backup barrier.
BRAKING_AXES = {"quadrotor_1d": (2,), "quadrotor_2d": (2,), "quadrotor_3d": (2,)}
# 1/s. The ellipsoid's is the original's. Braking at 15: a slower approach holds a quadrotor tracking a circle
# through a ceiling further below it (RMSE 1.7x LQR's on the 3D quadrotor at 5, 1.49x at 15; the 2D one 1.48x/1.49x).
DEFAULT_SLOPE = {"braking": 15.0, "backup": 5.0, "ellipsoid": 0.1}


@dataclasses.dataclass(frozen=True)
class Options:
    """Options of ``make_cbf`` (a config's ``safety_filters.cbf`` section); errors name ``safety_filters.cbf.KEY``."""

    barrier: str = option("auto", "barrier: braking, backup or ellipsoid; auto: braking if every row has one", BARRIERS)
    solver: str = option("auto", "closed_form (one barrier), qpax, casadi (host); auto: closed form if one", SOLVERS)
    slope: tuple | None = option(
        None, "alpha, slope of the class-K function alpha h, 1/s; default 15 braking, 5 backup, 0.1 ellipsoid"
    )
    soft_constrained: bool = option(True, "soft barrier constraint with a slack variable")
    slack_weight: float = option(1e4, "k, weight of the slack in the cost k s^2")
    slack_tolerance: float = option(1e-3, "slack above this reports feasible = False")
    margin: float = option(0.0, "distance kept from every state row (braking, backup), the row's units (m, rad)")
    ellipsoid_axes: tuple | None = option(
        None, "(nx,) semi-axes x_i,max of the ellipsoid (inf: unbounded); default min(|low|, |high|) of the state box"
    )
    braking_deceleration: tuple | None = option(
        None, "a_b of every braking row, m/s^2; default 0.9 x the smallest deceleration over sampled states"
    )
    velocity_smoothing: float = option(0.5, "epsilon of the braking barrier's smooth approach speed, m/s")
    backup_horizon: float = option(2.0, "seconds the backup barrier rolls its backup controller out")
    backup_q: tuple | None = option(None, "(nx,) diagonal state weight of the backup LQR; default see backup_weights")
    backup_r: tuple | None = option(None, "(nu,) diagonal input weight of the backup LQR; default see backup_weights")
    backup_state: tuple | None = option(None, "(nx,) the state the backup LQR holds; default the goal")
    softmin_temperature: float = option(1e-3, "temperature of the backup barrier's smooth minimum, row units")
    validation_samples: int = option(4000, "states is_valid_cbf samples when the filter is built")
    max_infeasible_fraction: float = option(
        0.01, "refuse the barrier when more of the sampled safe states than this have no admissible input"
    )

    def _check(self, path: str) -> None:
        for name in ("slack_weight", "velocity_smoothing", "backup_horizon", "softmin_temperature"):
            if not getattr(self, name) > 0:
                raise FieldError(f"{path}.{name}", f"must be > 0, got {getattr(self, name)!r}")
        for name in ("slack_tolerance", "margin"):
            if not getattr(self, name) >= 0:
                raise FieldError(f"{path}.{name}", f"must be >= 0, got {getattr(self, name)!r}")
        for name in ("slope", "braking_deceleration"):
            value = getattr(self, name)
            if value is not None and (len(value) != 1 or not value[0] > 0):
                raise FieldError(f"{path}.{name}", f"expected one positive number, got {list(value)}")
        if self.validation_samples < 100:
            raise FieldError(f"{path}.validation_samples", f"must be >= 100, got {self.validation_samples!r}")
        if not 0.0 <= self.max_infeasible_fraction <= 1.0:
            raise FieldError(
                f"{path}.max_infeasible_fraction", f"must be in [0, 1], got {self.max_infeasible_fraction!r}"
            )


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


def braking_barrier(row: int) -> Callable:
    """The braking barrier of row ``row`` of ``params``: ``h = b - a^T x - v^2 / (2 a_b)`` (m), ``v`` the smooth
    approach speed of ``a_v^T x`` (``a_v``: ``a`` moved onto the velocities of its positions).

    Params: ``A`` (m, nx), ``A_velocity`` (m, nx), ``b`` (m,) already lowered by the margin, ``deceleration`` (m,)
    ``a_b`` (m/s^2), ``smoothing`` (m/s). A valid CBF when the input can decelerate the plant along ``a`` by
    ``a_b``: full braking gives ``h_dot = -y_dot + v v' a / a_b >= 0`` for any deceleration ``a >= a_b`` (since
    ``v v' >= y_dot``)."""

    def h(x, params, xp=jax_backend):
        a, a_v = params["A"][row], params["A_velocity"][row]
        position = sum(x[i] * a[i] for i in range(len(a)))
        v = approach_speed(sum(x[i] * a_v[i] for i in range(len(a_v))), params["smoothing"], xp)
        return params["b"][row] - position - v * v / (2.0 * params["deceleration"][row])

    h.__name__ = f"braking_barrier_{row}"
    return h


def backup_rollout(step_fn: Callable, num_steps: int) -> Callable:
    """``rollout(x (nx,), params) -> (num_steps + 1, nx)``: the states of the backup controller
    ``u = clip(u_backup - K (x - x_backup), u_low, u_high)`` held over each control period of ``step_fn(x, u,
    physics)``, from ``x``. Params: ``physics``, ``K`` (nu, nx), ``x_backup`` (nx,), ``u_backup``, ``u_low``,
    ``u_high`` (nu,)."""

    def rollout(x, params):
        # The physics in the state's dtype: float64 physics (x64 on) would promote a float32 state mid-scan.
        physics = jax.tree.map(lambda v: jnp.asarray(v).astype(x.dtype), params["physics"])

        def step(state, _):
            u = backup_input(state, params)
            nxt = step_fn(state, u, physics).astype(state.dtype)
            return nxt, nxt

        _, states = jax.lax.scan(step, x, None, length=num_steps)
        return jnp.concatenate([x[None], states])

    return rollout


def backup_input(x, params):
    """The backup controller's input at ``x``: ``clip(u_backup - K (x - x_backup), u_low, u_high)`` (nu,), N."""
    x_backup = jnp.asarray(params["x_backup"]).astype(x.dtype)
    u = jnp.asarray(params["u_backup"]).astype(x.dtype) - jnp.asarray(params["K"]).astype(x.dtype) @ (x - x_backup)
    return jnp.clip(u, jnp.asarray(params["u_low"]).astype(x.dtype), jnp.asarray(params["u_high"]).astype(x.dtype))


def make_backup_barrier(rollout: Callable) -> Callable:
    """The backup barrier of ``rollout`` (``backup_rollout``): ``h(x) = -tau log sum_{r, j} exp(-d_rj / tau)`` (row
    units), a smooth minimum below ``min d_rj`` by at most ``tau log(count)``, of every row's distance
    ``d_rj = b_r - a_r^T x_j`` over the rollout's states ``x_j``. Params (besides the rollout's): ``A`` (m, nx),
    ``b`` (m,) (margin and failure bounds included), ``temperature`` ``tau``. JAX only (it runs a ``lax.scan``)."""

    def h(x, params, xp=jax_backend):
        states = rollout(x, params)
        distances = params["b"][None, :] - states @ jnp.asarray(params["A"]).T
        tau = params["temperature"]
        return -tau * jax.nn.logsumexp(-distances.reshape(-1) / tau)

    return h


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
class CBFFilter(Filter):
    """A ``Filter`` that also exposes its barrier terms (for ``is_valid_cbf``).

    Attributes (besides ``Filter``'s): terms_fn: ``terms_fn(x, params) -> Terms`` (one state; numpy ``terms_fn(x)``
    for the host filter).
    """

    terms_fn: Callable = None


def _barrier_accepts_xp(h) -> bool:
    try:
        return "xp" in inspect.signature(h).parameters
    except (TypeError, ValueError):
        return False


def _state_sample_box(system, n: int = 8, seed: int = 0):
    low = np.where(np.isfinite(system.state_low), system.state_low, -2.0)
    high = np.where(np.isfinite(system.state_high), system.state_high, 2.0)
    return sample_states(low, high, n, seed)


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
    fallback: Callable | None = None,
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
            derivatives (the learned CBF); ``correction_params`` traced.
        fallback: optional ``fallback(x, barrier_params) -> u`` (nu,), the backup controller applied on infeasible
            steps inside the safe set (JAX only); other infeasible steps apply the QP's best effort (the input that
            raises ``h`` fastest against the slack's cost). name, info: the filter's name and report.

    Returns:
        a ``CBFFilter``: JAX, or for ``solver="casadi"`` host.

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
        if fallback is not None:
            raise ValueError(f"{path}.solver: the casadi filter has no backup controller; use closed_form or qpax")
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
        s = s.astype(u_unc.dtype)
        feasible = solved & (s <= slack_tolerance)
        if fallback is None:
            applied = jnp.where(feasible, CERTIFIED, BEST_EFFORT)
        else:
            # Inside the safe set the backup controller keeps the plant safe (that is what h >= 0 says); outside,
            # its own rollout leaves the constraint, and the QP's best effort (the fastest growth of h) is better.
            backup = jnp.logical_not(feasible) & (jnp.min(terms.h) >= 0)
            u = jnp.where(backup, fallback(x, p["barrier"]).astype(u.dtype), u)
            applied = jnp.where(feasible, CERTIFIED, jnp.where(backup, BACKUP_CONTROLLER, BEST_EFFORT))
        info_ = FilterInfo(feasible=feasible, slack=s, correction=applied_correction(u, u_unc, lo, hi), applied=applied)
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
            return u_l, filter_state, _host_info(True, 0.0, u_l, u_unc)
        A = np.concatenate([t.Lg, np.eye(m)], axis=1) if soft else t.Lg
        sol = qp(h=H, g=np.concatenate([-u_l, np.zeros(m if soft else 0)]), a=A, lba=-c, uba=np.inf, lbx=lbx, ubx=ubx)
        solved = bool(qp.stats()["success"])
        z = np.asarray(sol["x"]).reshape(n)
        if not solved or not np.all(np.isfinite(z)):
            shortfall = max(-float(np.min(c + t.Lg @ u_l)), 0.0)
            return u_l, filter_state, _host_info(False, shortfall, u_l, u_unc)
        u_out = np.clip(z[:nu], u_low, u_high)
        s = float(np.max(np.maximum(z[nu:], 0.0))) if soft else 0.0
        return u_out, filter_state, _host_info(s <= slack_tolerance, s, u_out, u_unc)

    def _host_info(feasible, slack, u, u_unc):
        return FilterInfo(
            feasible=np.asarray(bool(feasible)),
            slack=np.asarray(float(slack)),
            correction=applied_correction(u, u_unc, u_low, u_high, np),
            applied=np.asarray(CERTIFIED if feasible else BEST_EFFORT),
        )

    return CBFFilter(
        name=name,
        system=system.name,
        params={"physics": physics, "barrier": barrier_params, "slope": slope},
        reset_fn=lambda key: (),
        certify_fn=certify_fn,
        is_jax=False,
        info={**report, "solver": "casadi"},
        terms_fn=terms_fn,
    )


# --------------------------------------------------------------------------------------------- from an env
def state_rows(env, prior_params, path: str = PATH) -> tuple[np.ndarray, np.ndarray]:
    """``(A (m, nx), b (m,))``: the env's bounded and linear state constraints as unit-norm rows ``a^T x <= b``
    (duplicates merged, rows the system's failure bounds imply left out; the actuator limits are the QP's input
    box).

    Raises:
        ValueError: naming ``constraints[i]`` for a quadratic constraint or a row on the input and the state, which
            no barrier here is built from; naming ``path`` when there is no state row at all.
    """
    from scg_algorithms.mpc.linear import _constraint_rows

    for i, spec in enumerate(env.constraint_specs):
        if spec.form == "quadratic" and spec.on != "input":
            raise ValueError(
                f"constraints[{i}]: {path} builds barriers from bounded and linear state constraints; a quadratic "
                "constraint has none here (write it as linear rows, or use nonlinear_mpsc)"
            )
    rows = _constraint_rows(env, prior_params, True)[0]
    mixed = rows.soft & np.any(rows.Au != 0.0, axis=1)
    if np.any(mixed):
        raise ValueError(
            f"{path}: a constraint row on both the input and the state ({rows.Ax[mixed][0].tolist()} x + "
            f"{rows.Au[mixed][0].tolist()} u <= {rows.b[mixed][0]:.4g}) has no barrier here; constrain the state alone"
        )
    A, b = rows.Ax[rows.soft], rows.b[rows.soft]
    # A row the failure bounds imply (a floor at z >= -10 m under the ground at -0.05 m) cannot become active before
    # the plant fails: it needs no barrier.
    low, high = env.system.state_low, env.system.state_high
    with np.errstate(invalid="ignore"):
        reach = np.where(A > 0, A * high, np.where(A < 0, A * low, 0.0)).sum(axis=1)
    keep = ~(reach <= b)
    if not np.any(keep):
        raise ValueError(
            f"{path}: the env has no bounded or linear state constraint tighter than the system's failure bounds, so "
            "there is nothing to certify; make the env with constraints (e.g. {'type': 'bounded', 'on': 'state', ...})"
        )
    A, b = A[keep], b[keep]
    norms = np.linalg.norm(A, axis=1)
    return A / norms[:, None], b / norms


def braking_setup(env, prior_params, A, b, opts: Options, path: str = PATH):
    """The braking barriers' params for the rows ``A``, ``b`` (``state_rows``), or a reason why there are none.

    A row gets a braking barrier when it acts only on positions of the world axes in ``BRAKING_AXES`` and the input
    box decelerates the plant along it at every sampled state of ``validation_box``; ``a_b`` is 0.9 times the
    smallest such deceleration (or ``braking_deceleration``).

    Returns:
        ``(params, None)`` with ``A``, ``A_velocity``, ``b`` (lowered by ``margin``), ``deceleration`` (m,) and
        ``smoothing``; or ``(None, reason)``.
    """
    system = env.system
    axes = BRAKING_AXES.get(system.name, ())
    velocity_of = {position: velocity for axis, position, velocity in system.tracking_axes if axis in axes}
    A_velocity = np.zeros_like(A)
    for r, row in enumerate(A):
        support = np.flatnonzero(row)
        if not set(support) <= set(velocity_of):
            names = ", ".join(system.state_names[i] for i in support)
            return None, (
                f"row {r} bounds {names}: a braking barrier needs a position the input brakes directly without "
                f"losing the rest of the state ({system.name}: "
                f"{', '.join(system.state_names[p] for p in velocity_of) or 'none'})"
            )
        for i in support:
            A_velocity[r, velocity_of[i]] = row[i]
    low, high = validation_box(env, prior_params)
    u_low, u_high = input_limits(env, prior_params)
    physics = prior_params.physics
    xs = jnp.asarray(sample_states(low, high, opts.validation_samples))

    def acceleration_terms(x):
        u0 = jnp.zeros(system.nu, x.dtype)
        f = system.dynamics(x, u0, physics, jax_backend)
        g = jax.jacfwd(lambda u: system.dynamics(x, u, physics, jax_backend))(u0)
        return f, g

    f, g = (np.asarray(v, dtype=np.float64) for v in jax.jit(jax.vmap(acceleration_terms))(xs))
    # The largest deceleration along each row at each sample: -(a_v . f) + sum_j max over the box of -(a_v . g_j) u_j.
    drift = -np.einsum("ri,ni->nr", A_velocity, f)
    gain = -np.einsum("ri,nij->nrj", A_velocity, g)
    available = drift + np.maximum(gain * u_low, gain * u_high).sum(axis=-1)
    worst = available.min(axis=0)
    if opts.braking_deceleration is not None:
        deceleration = np.full(A.shape[0], float(opts.braking_deceleration[0]))
    else:
        deceleration = 0.9 * worst
    if np.any(worst <= 0) and opts.braking_deceleration is None:
        r = int(np.argmin(worst))
        i = int(np.argmin(available[:, r]))
        return None, (
            f"row {r} ({A[r].tolist()} x <= {b[r]:.4g}): the inputs cannot decelerate the plant along it at every "
            f"state (at most {worst[r]:.3g} m/s^2 at x = {np.round(np.asarray(xs[i]), 3).tolist()})"
        )
    params = {
        "A": A,
        "A_velocity": A_velocity,
        "b": b - opts.margin,
        "deceleration": deceleration,
        "smoothing": np.float64(opts.velocity_smoothing),
    }
    return params, None


def backup_setup(env, prior_params, A, b, opts: Options, path: str = PATH):
    """The backup barrier and its params for the rows ``A``, ``b`` (``state_rows``).

    Returns:
        ``(h, params, info)``: the barrier (``make_backup_barrier``), its params (the rollout's, the rows with the
        system's finite failure bounds appended, ``temperature``) and a report (weights, set-point, steps).

    Raises:
        FieldError: ``backup_state`` outside the rows, bad weights, or a backup LQR with no stabilising solution.
    """
    from scg_algorithms.lqr import discrete_lqr_gain
    from scg_jax.integrators import make_discrete_dynamics

    nx, nu = env.nx, env.nu
    if opts.backup_state is not None and len(opts.backup_state) != nx:
        raise FieldError(f"{path}.backup_state", f"expected {nx} values, got {len(opts.backup_state)}")
    goal = np.asarray(prior_params.goal, dtype=np.float64).reshape(nx)
    x_backup = goal if opts.backup_state is None else np.asarray(opts.backup_state, dtype=np.float64)
    room = b - opts.margin - A @ x_backup
    if np.any(room <= 0):
        r = int(np.argmin(room))
        raise FieldError(
            f"{path}.backup_state",
            f"the backup controller's set-point {np.round(x_backup, 4).tolist()} (default: the goal) is not inside "
            f"row {r} ({A[r].tolist()} x <= {b[r]:.4g} - margin {opts.margin}); give a backup_state inside",
        )
    u_backup = equilibrium_input(env, prior_params)
    lin = prior_model(env, prior_params, "rk4").linearize(x_backup, u_backup)
    candidates = []
    for default_q, default_r in backup_weights(env, prior_params, A, b - opts.margin, x_backup):
        q = diagonal_weight(opts.backup_q, f"{path}.backup_q", default_q, nx)
        r = diagonal_weight(opts.backup_r, f"{path}.backup_r", default_r, nu)
        if min(r) <= 0:
            raise FieldError(f"{path}.backup_r", f"the backup LQR's input weight must be positive, got {list(r)}")
        try:
            K, _ = discrete_lqr_gain(lin.Ad, lin.Bd, np.diag(q), np.diag(r))
        except ValueError as error:
            raise FieldError(f"{path}.backup_q", f"the backup LQR has no stabilising solution ({error})") from None
        candidates.append((q, r, K))
        if opts.backup_q is not None and opts.backup_r is not None:
            break
    failure_A, failure_b = failure_rows(env.system)
    u_low, u_high = input_limits(env, prior_params)
    num_steps = max(1, math.ceil(opts.backup_horizon / env.dt - 1e-9))
    # One RK4 step per control period, with the physics traced (the filter's params).
    discrete = make_discrete_dynamics(env.system.dynamics, "rk4", env.dt, 1, env.system.velocity_mask)
    params = {
        "physics": jax.tree.map(lambda v: np.asarray(v, dtype=np.float64), prior_params.physics),
        "K": candidates[0][2],
        "x_backup": x_backup,
        "u_backup": u_backup,
        "u_low": u_low,
        "u_high": u_high,
        "A": np.concatenate([A, failure_A]),
        "b": np.concatenate([b - opts.margin, failure_b]),
        "temperature": np.float64(opts.softmin_temperature),
    }
    rollout = backup_rollout(lambda x, u, physics: discrete(x, u, physics, jax_backend), num_steps)
    h = make_backup_barrier(rollout)
    safe_fraction = [1.0]
    if len(candidates) > 1:  # keep the backup whose barrier holds the most sampled states safe (one compilation)
        states = jnp.asarray(validation_states(env, prior_params, opts.validation_samples, jax.random.key(1)))
        values = jax.jit(jax.vmap(h, in_axes=(0, None)))
        safe_fraction = [float(np.mean(np.asarray(values(states, {**params, "K": K})) >= 0)) for _, _, K in candidates]
    q, r, K = candidates[int(np.argmax(safe_fraction))]
    info = {
        "backup_q": q.tolist(),
        "backup_r": r.tolist(),
        "backup_state": x_backup.tolist(),
        "backup_steps": num_steps,
        "backup_safe_fraction": max(safe_fraction),
    }
    return h, {**params, "K": K}, info


class BarrierSetup(NamedTuple):
    """A barrier built from an env: ``name``; ``functions``, the barriers ``h(x, params, xp)``; ``params`` (their
    parameters); ``fallback`` (``fallback(x, params) -> u``, the backup controller, or ``None``); ``info``."""

    name: str
    functions: tuple
    params: Any
    fallback: Callable | None
    info: dict


def build_barrier(env, prior_params, opts: Options, barrier: str, path: str = PATH) -> BarrierSetup | str:
    """The barrier ``barrier`` (not ``auto``) for ``env``'s state constraints on the prior, or the reason (a string)
    why a braking barrier does not exist for them.

    Raises:
        FieldError: a bound or option that cannot make the barrier (a bad ``backup_state``, ellipsoid axes).
    """
    if barrier == "ellipsoid":
        x_low, x_high = state_box(env, prior_params)
        if opts.ellipsoid_axes is not None:
            if len(opts.ellipsoid_axes) != env.nx:
                raise FieldError(f"{path}.ellipsoid_axes", f"expected {env.nx} values, got {len(opts.ellipsoid_axes)}")
            axes = np.asarray(opts.ellipsoid_axes, dtype=np.float64)
        else:
            axes = np.minimum(np.abs(x_low), np.abs(x_high))
        if np.any(axes <= 0):
            raise FieldError(f"{path}.ellipsoid_axes", f"semi-axes must be > 0 (inf: unbounded), got {axes.tolist()}")
        if not np.any(np.isfinite(axes)):
            raise FieldError(f"{path}.ellipsoid_axes", "the env's state constraint bounds no coordinate; give the axes")
        inv = np.where(np.isfinite(axes), 1.0 / axes, 0.0)
        return BarrierSetup(barrier, (ellipsoid_barrier,), {"inv_axes": inv}, None, {"inv_axes": inv.tolist()})
    A, b = state_rows(env, prior_params, path)
    if barrier == "braking":
        params, reason = braking_setup(env, prior_params, A, b, opts, path)
        if params is None:
            return reason
        functions = tuple(braking_barrier(r) for r in range(A.shape[0]))
        info = {"deceleration": params["deceleration"].tolist(), "rows": A.tolist(), "bounds": b.tolist()}
        return BarrierSetup(barrier, functions, params, None, info)
    h, params, info = backup_setup(env, prior_params, A, b, opts, path)
    return BarrierSetup(barrier, (h,), params, backup_input, {**info, "rows": A.tolist(), "bounds": b.tolist()})


def barrier_setup(env, prior_params, opts: Options, path: str = PATH):
    """``(barrier name, barrier functions, barrier params)`` of ``opts`` for ``env`` with the prior physics (for
    ``auto``: the first of braking and backup that exists; ``make_cbf`` also checks that it is valid).

    Raises:
        FieldError: ``<path>.barrier`` when the barrier does not exist for the env's constraints, or a bad option.
    """
    for barrier in ("braking", "backup") if opts.barrier == "auto" else (opts.barrier,):
        built = build_barrier(env, prior_params, opts, barrier, path)
        if isinstance(built, BarrierSetup):
            return built.name, built.functions, built.params
    raise FieldError(f"{path}.barrier", f"no braking barrier for {env.system.name}: {built}; use auto or backup")


def make_cbf(env, prior_params, options=None, *, correction=None, correction_params=None, name: str = "cbf",
             path: str = PATH):  # fmt: skip
    """The CBF-QP filter for ``env`` from the prior model ``prior_params`` (options: ``Options``), checked.

    The model is ``env.system.dynamics`` with ``prior_params.physics``; the input box is the prior's actuator
    limits; the barriers come from the env's state constraints (see the module docstring). ``auto`` takes the
    braking barrier where every row has one, else the backup barrier. Before it is returned, ``is_valid_cbf``
    samples ``validation_samples`` states; a barrier with more than ``max_infeasible_fraction`` of its sampled safe
    states without an admissible input is refused (``auto`` then tries the backup barrier). ``info["validity"]``
    holds the check. ``correction``/``correction_params``: see ``cbf_filter`` (the learned CBF passes its network).

    Raises:
        ValueError: naming ``<path>.<field>`` for a bad option, or ``<path>.barrier`` when no valid barrier exists
            for the env's constraints, saying why.
    """
    opts = parse_options(Options, options, path)
    reasons = []
    for barrier in ("braking", "backup") if opts.barrier == "auto" else (opts.barrier,):
        built = build_barrier(env, prior_params, opts, barrier, path)
        if not isinstance(built, BarrierSetup):
            reasons.append(f"{barrier}: {built}")
            continue
        slope = float(opts.slope[0]) if opts.slope is not None else DEFAULT_SLOPE[barrier]
        u_low, u_high = input_limits(env, prior_params)
        info = {"barrier": barrier, **built.info}
        common = dict(
            slope=slope, slack_weight=opts.slack_weight, soft_constrained=opts.soft_constrained,
            slack_tolerance=opts.slack_tolerance, correction=correction, correction_params=correction_params,
            fallback=built.fallback, name=name, info=info, path=path,
        )  # fmt: skip
        system, physics = env.system, prior_params.physics
        flt = cbf_filter(system, physics, u_low, u_high, built.functions, built.params, solver=opts.solver, **common)
        # The check runs on the JAX filter (the casadi one is its mirror, the parity tests hold them equal).
        checked = (
            flt if flt.is_jax else cbf_filter(system, physics, u_low, u_high, built.functions, built.params, **common)
        )
        report = is_valid_cbf(checked, env, opts.validation_samples, jax.random.key(0), prior_params=prior_params)
        validity = {
            "samples": report.num_points,
            "inside": report.num_inside,
            "infeasible": report.num_infeasible,
            "infeasible_fraction": report.infeasible_fraction,
        }
        if report.num_inside == 0 or report.infeasible_fraction > opts.max_infeasible_fraction:
            worst = np.round(report.worst_states[0], 3).tolist() if report.num_inside else None
            reasons.append(
                f"{barrier}: {report.num_infeasible} of the {report.num_inside} sampled states in its safe set have no "
                f"admissible input ({100 * report.infeasible_fraction:.1f} % > max_infeasible_fraction "
                f"{100 * opts.max_infeasible_fraction:g} %; worst at x = {worst})"
                if report.num_inside
                else f"{barrier}: none of {report.num_points} sampled states is in its safe set"
            )
            continue
        return flt.replace(info={**flt.info, "validity": validity})
    raise FieldError(
        f"{path}.barrier",
        f"no valid barrier for the constraints of this {env.system.name} env ({'; '.join(reasons)})",
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
    num_worst: int = 5, prior_params=None,
) -> ValidityReport:  # fmt: skip
    """Randomised check of the CBF condition: sample states uniformly in a box, keep those in the safe set, and
    report where no input in the box satisfies ``Lf h + Lg h u + alpha h >= -tolerance`` (where the QP is
    infeasible without slack). A valid CBF has none.

    Args:
        safety_filter: a JAX ``CBFFilter`` from ``make_cbf``. env: its env.
        num_points: states to sample. key: PRNG key (default ``key(0)``). low, high: (nx,) a box to sample
            uniformly; default ``validation_states`` (half in ``validation_box``, the env's state-constraint bounds
            within the failure bounds, 2.0 where unbounded; half in the initial-state box).
        tolerance: margin accepted. num_worst: how many worst states to return. prior_params: the params whose
            constraint bounds make the default box (default ``env.default_params``).
    """
    from scg_algorithms.safety_filters.base import check_system

    check_system(safety_filter, env)
    if not safety_filter.is_jax:
        raise ValueError("is_valid_cbf: pass the JAX filter (solver closed_form or qpax), not the casadi one")
    key = jax.random.key(0) if key is None else key
    params = safety_filter.params
    prior_params = env.default_params if prior_params is None else prior_params
    if low is None and high is None:
        low, high = validation_box(env, prior_params)
        xs = validation_states(env, prior_params, num_points, key)
    else:
        box_low, box_high = validation_box(env, prior_params)
        low = box_low if low is None else np.asarray(low, dtype=np.float64)
        high = box_high if high is None else np.asarray(high, dtype=np.float64)
        xs = np.asarray(jax.random.uniform(key, (num_points, env.nx)), dtype=np.float64) * (high - low) + low
    u_low, u_high = jnp.asarray(params["u_low"]), jnp.asarray(params["u_high"])
    slope = params["slope"]

    def one(x):
        t = safety_filter.terms_fn(x, params)
        return jnp.min(t.h), _best_margin(t.Lf + slope * t.h, t.Lg, u_low, u_high)

    h_min, margin = (np.asarray(v, dtype=np.float64) for v in jax.jit(jax.vmap(one))(jnp.asarray(xs)))
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
    "BRAKING_AXES",
    "PATH",
    "SOLVERS",
    "BarrierSetup",
    "CBFFilter",
    "Options",
    "Terms",
    "ValidityReport",
    "approach_speed",
    "backup_input",
    "backup_rollout",
    "backup_setup",
    "backup_weights",
    "barrier_setup",
    "braking_barrier",
    "braking_setup",
    "build_barrier",
    "cbf_filter",
    "check_control_affine",
    "check_scalar_barriers",
    "ellipsoid_barrier",
    "is_valid_cbf",
    "make_backup_barrier",
    "make_cbf",
    "solve_qpax",
    "solve_single",
    "state_rows",
    "validation_box",
    "validation_states",
]
