"""The GP-MPC prediction model: the prior's discrete model plus the GP's mean, and its uncertainty along a plan.

``learned_model(fd_prior, posterior)`` is the CasADi function ``f(x, u) = f_prior(x, u) + μ([x; u])`` the NLP
predicts with (the GP posterior expressed through the ``xp`` backends, so it is the same function the JAX side
evaluates). ``plan_tightening`` propagates the state covariance along a plan with that model's Jacobians and the
GP's variance, and returns the margins of every linear constraint row at every stage (``tightening``).
"""

from __future__ import annotations

import casadi as cs
import jax
import numpy as np

from scg_algorithms import gp
from scg_algorithms.gp_mpc import tightening


def fit_model_error(
    inputs,
    targets,
    *,
    num_inducing: int,
    kernel: str = "rbf",
    iterations: int = 50,
    max_fit_points: int = 200,
    key,
    path: str = "controllers.gp_mpc",
) -> tuple[gp.GPPosterior, dict]:
    """Fit one GP per target dimension and return its FITC posterior on ``num_inducing`` inducing points.

    The hyperparameters are fit on at most ``max_fit_points`` transitions (a uniform random subset drawn with
    ``key``; the exact marginal likelihood costs O(n³)); the posterior uses every transition. The inducing points
    follow ``gp.select_inducing`` (k-means centroids snapped to data points).

    Returns:
        ``(posterior, info)``: ``info`` holds ``num_points``, ``nll_initial``, ``nll_final``, ``inducing_indices``.
    """
    inputs, targets = np.asarray(inputs, float), np.asarray(targets, float)
    n = len(inputs)
    if not isinstance(num_inducing, int) or not 1 <= num_inducing <= n:
        raise ValueError(
            f"{path}.num_inducing: must be an integer from 1 to the number of transitions collected ({n}), "
            f"got {num_inducing!r}"
        )
    fit_key, inducing_key = jax.random.split(key)
    subset = np.arange(n)
    if n > max_fit_points:
        subset = np.sort(np.asarray(jax.random.choice(fit_key, n, (max_fit_points,), replace=False)))
    hyper, fit_info = gp.fit_hyperparams(inputs[subset], targets[subset], kernel=kernel, iterations=iterations)
    chosen = gp.select_inducing(inputs, num_inducing, inducing_key)
    posterior = gp.fitc_posterior(inputs, targets, hyper, inputs[chosen], kernel)
    return posterior, {"num_points": n, **fit_info, "inducing_indices": chosen.tolist()}


def learned_model(fd_prior: cs.Function, posterior: gp.GPPosterior | None, name: str = "f_learned") -> cs.Function:
    """``f(x, u) = fd_prior(x, u) + μ([x; u])`` as a CasADi ``Function`` (SX); the prior alone without a GP."""
    nx, nu = fd_prior.size1_in(0), fd_prior.size1_in(1)
    x, u = cs.SX.sym("x", nx), cs.SX.sym("u", nu)
    nominal = fd_prior(x, u)
    if posterior is None:
        return cs.Function(name, [x, u], [nominal], ["x", "u"], ["x_next"])
    if posterior.num_inputs != nx + nu or posterior.num_outputs != nx:
        raise ValueError(
            f"gp: expected a GP from [x; u] ({nx + nu} inputs) to the state ({nx} outputs), got "
            f"{posterior.num_inputs} inputs and {posterior.num_outputs} outputs"
        )
    mean, _ = gp.predict(gp.to_numpy(posterior), cs.vertcat(x, u), gp.casadi_backend)
    return cs.Function(name, [x, u], [nominal + mean], ["x", "u"], ["x_next"])


class PlanUncertainty:
    """Covariance propagation along a plan for one learned model (functions built once).

    Args:
        model: ``learned_model(...)``. posterior: the GP (``None``: no model uncertainty). K: (nu, nx) ancillary
            gain. prob: chance level of each constraint. sigma0: (nx, nx) initial-state covariance.
        constraints: optional CasADi ``Function`` ``g(x, u) -> (ng,)`` (``SymbolicModel.g``); its Jacobians at
            ``(x_{i+1}, u_i)`` give each stage's rows for ``plan_margins`` (exact for linear constraints, the
            linearisation for quadratic ones).
    """

    def __init__(self, model: cs.Function, posterior: gp.GPPosterior | None, K, prob: float, sigma0,
                 constraints: cs.Function | None = None):  # fmt: skip
        nx, nu = model.size1_in(0), model.size1_in(1)
        x, u = cs.SX.sym("x", nx), cs.SX.sym("u", nu)
        self.jacobians = cs.Function("AB", [x, u], [cs.jacobian(model(x, u), x), cs.jacobian(model(x, u), u)])
        self.constraint_jacobians = None
        if constraints is not None and constraints.size1_out(0):
            g = constraints(x, u)
            self.constraint_jacobians = cs.Function("G", [x, u], [cs.jacobian(g, x), cs.jacobian(g, u)])
            self.ng = int(constraints.size1_out(0))
        self.posterior = None if posterior is None else gp.to_numpy(posterior)
        self.variance = None if posterior is None else gp.casadi_function(self.posterior).map
        self.K = np.asarray(K, float)
        self.z_q = tightening.quantile(prob, nx)
        self.sigma0 = np.asarray(sigma0, float)
        self.nx, self.nu = nx, nu

    def covariances(self, x_plan, u_plan) -> np.ndarray:
        """(H + 1, nx, nx) covariances along ``x_plan`` (H + 1, nx), ``u_plan`` (H, nu)."""
        x_plan, u_plan = np.asarray(x_plan, float), np.asarray(u_plan, float)
        H = len(u_plan)
        jac = self.jacobians.map(H)(x_plan[:H].T, u_plan.T)
        # map stacks the stages' Jacobians side by side: (nx, H * nx) = [A_0 | A_1 | ...].
        A = np.asarray(jac[0]).reshape(self.nx, self.nx, H, order="F").transpose(2, 0, 1)
        B = np.asarray(jac[1]).reshape(self.nx, self.nu, H, order="F").transpose(2, 0, 1)
        if self.variance is None:
            var = np.zeros((H, self.nx))
        else:
            _, v = self.variance(H)(np.concatenate([x_plan[:H], u_plan], axis=1).T)
            var = np.maximum(np.asarray(v).T, 0.0)
        return tightening.propagate_covariance(A, B, self.K, var, self.sigma0)

    def margins(self, x_plan, u_plan, rows_x, rows_u) -> np.ndarray:
        """(H, ng) margins of the rows ``a_x x_{i+1} + a_u u_i <= b`` at each stage ``i`` of the plan."""
        return tightening.margins(rows_x, rows_u, self.covariances(x_plan, u_plan), self.K, self.z_q)

    def plan_margins(self, x_plan, u_plan) -> np.ndarray:
        """(H, ng) margins of the ``constraints`` given at construction, rows from their Jacobians along the plan."""
        x_plan, u_plan = np.asarray(x_plan, float), np.asarray(u_plan, float)
        H = len(u_plan)
        gx, gu = self.constraint_jacobians.map(H)(x_plan[1:].T, u_plan.T)
        rows_x = np.asarray(gx).reshape(self.ng, self.nx, H, order="F").transpose(2, 0, 1)
        rows_u = np.asarray(gu).reshape(self.ng, self.nu, H, order="F").transpose(2, 0, 1)
        return self.margins(x_plan, u_plan, rows_x, rows_u)
