"""The safety filters' contract over systems x constraints (issue 24), shared by ``tests/test_filter_contract.py`` and
``benchmarks/safety_filters.py``: each filter, built with its defaults from the configured constraint, either cuts
LQR's violating steps to at most ``MAX_VIOLATION_SHARE`` of LQR's own with an RMSE at most ``MAX_RMSE_RATIO`` times
LQR's, or refuses when it is built with a message that says why.

A case is a config of ``configs/`` with a state constraint added (``--set`` overrides, as a user writes them):
LQR alone crosses it on most episodes. ``run_case`` evaluates LQR alone and filtered on the same episodes (same
key, so the same initial states and physics draws).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import jax
import numpy as np

MAX_VIOLATION_SHARE = 0.1  # filtered violating steps / LQR's violating steps, at most
MAX_RMSE_RATIO = 1.5  # filtered RMSE / LQR's RMSE, at most
FILTER_NAMES = ("cbf", "linear_mpsc", "nonlinear_mpsc")
CONFIGS = Path(__file__).resolve().parents[2] / "configs"


def _bound(dim: int, low: float, high: float) -> str:
    return (
        "env.constraints=[{type: default, on: input}, "
        f"{{type: bounded, on: state, active_dims: [{dim}], low: [{low}], high: [{high}]}}]"
    )


@dataclasses.dataclass(frozen=True)
class Case:
    """A system and a state constraint: ``config`` (a file of ``configs/``) with the ``overrides`` (``--set``
    strings); ``label`` names it in tables."""

    label: str
    config: str
    overrides: tuple[str, ...]

    def make(self, episode_len_sec: float | None = None):
        """``(env, params)`` of the case; ``episode_len_sec`` (s) cuts the episodes short and keeps the reference:
        the trajectory's period stays the config's (``num_cycles`` scaled with the length), so a shorter episode is
        the first part of the full one (the same initial states, reference and constraint)."""
        import scg_jax

        overrides = list(self.overrides)
        if episode_len_sec is not None:
            if not episode_len_sec > 0:
                raise ValueError(f"episode_len_sec: must be positive, got {episode_len_sec!r}")
            full = scg_jax.load_config(CONFIGS / self.config, overrides).env
            overrides.append(f"env.episode_len_sec={episode_len_sec}")
            if full.trajectory is not None:  # the period episode_len_sec / num_cycles stays the full episode's
                overrides.append(
                    f"env.trajectory.num_cycles={full.trajectory.num_cycles * episode_len_sec / full.episode_len_sec}"
                )
        return scg_jax.make_from_config(scg_jax.load_config(CONFIGS / self.config, overrides))


CASES = (
    # The cart-pole case: stabilisation with the cart held within +-0.1 m (LQR overshoots it).
    Case("cart-pole |x| <= 0.1 m", "cartpole_stabilization.yaml", (_bound(0, -0.1, 0.1),)),
    # Tracking the 1 m sinusoid tilts the pole beyond 0.1 rad.
    Case("cart-pole |theta| <= 0.1 rad", "cartpole_tracking.yaml", (_bound(2, -0.1, 0.1),)),
    # The 1 +- 0.5 m sinusoid under a 1.48 m ceiling: LQR tracks it within 2 cm, so a lower ceiling would make any
    # safe filter's RMSE a multiple of LQR's (the reference itself crosses it).
    Case("quadrotor 1D z <= 1.48 m", "quadrotor_1d_tracking.yaml", (_bound(0, -10.0, 1.48),)),
    # The 2D case: the circle around z = 1 m of radius 0.5 m under a 1.3 m ceiling, starting below 1.2 m.
    Case(
        "quadrotor 2D z <= 1.3 m",
        "quadrotor_2d_tracking.yaml",
        (_bound(2, -10.0, 1.3), "env.init_state.high=[0.5, 0.01, 1.2, 0.01, 0.3, 0.01]"),
    ),
    # The same circle (x within +-0.5 m) in a box |x| <= 0.4 m, starting inside it.
    Case(
        "quadrotor 2D |x| <= 0.4 m",
        "quadrotor_2d_tracking.yaml",
        (
            _bound(0, -0.4, 0.4),
            "env.init_state.low=[-0.3, -0.01, 0.1, -0.01, -0.3, -0.01]",
            "env.init_state.high=[0.3, 0.01, 1.5, 0.01, 0.3, 0.01]",
        ),
    ),
    Case(
        "quadrotor 3D z <= 1.3 m",
        "quadrotor_3d_tracking.yaml",
        (
            _bound(4, -10.0, 1.3),
            "env.init_state.high=[0.5, 0.01, 0.5, 0.01, 1.2, 0.01, 0.3, 0.3, 0.3, 0.01, 0.01, 0.01]",
        ),
    ),
)


def floor_and_ceiling_env(floor: float = 0.1, ceiling: float = 1.5):
    """The 1D quadrotor between a floor and a ceiling (m), flying on out of bounds: two braking barriers, the
    qpax CBF's parity and speed case (tests and ``benchmarks/safety_filters.py``)."""
    import scg_jax

    return scg_jax.make(
        "quadrotor_1d",
        init_state={"type": "uniform", "low": [floor + 0.1, -0.01], "high": [ceiling - 0.1, 0.01]},
        done_on_out_of_bounds=False,
        constraints=[{"type": "bounded", "on": "state", "active_dims": [0], "low": [floor], "high": [ceiling]}],
    )


@dataclasses.dataclass(frozen=True)
class Outcome:
    """One filter on one case: ``refusal`` (the build's message) or the filtered ``violations`` (violating steps per
    episode), ``rmse``, ``infeasible_fraction`` and ``mean_correction`` (N) next to LQR's ``lqr_violations`` and
    ``lqr_rmse`` on the same episodes."""

    case: str
    filter: str
    lqr_violations: float
    lqr_rmse: float
    refusal: str | None = None
    violations: float = float("nan")
    rmse: float = float("nan")
    infeasible_fraction: float = float("nan")
    mean_correction: float = float("nan")

    @property
    def holds(self) -> bool:
        """The contract: refused with a reason, or at most 10 % of LQR's violations at most 1.5x its RMSE."""
        if self.refusal is not None:
            return bool(self.refusal.strip())
        return (
            self.violations <= MAX_VIOLATION_SHARE * self.lqr_violations and self.rmse <= MAX_RMSE_RATIO * self.lqr_rmse
        )


def lqr_baseline(env, params, episodes: int, seed: int = 0):
    """``(controller, evaluation)``: LQR with its defaults on ``episodes`` episodes from ``key(seed)``."""
    from scg_algorithms import make_controller
    from scg_algorithms.evaluation import evaluate

    controller = make_controller("lqr", env, params)
    return controller, evaluate(env, params, controller, jax.random.key(seed), episodes, measure_time=False)


def run_filter(case: Case, name: str, env, params, controller, baseline, episodes: int, seed: int = 0) -> Outcome:
    """The ``Outcome`` of the filter ``name`` (its defaults) behind ``controller`` on ``env``; a ``ValueError`` from
    its build is the refusal."""
    from scg_algorithms.evaluation import evaluate
    from scg_algorithms.safety_filters import filtered, make_filter

    lqr = {
        "case": case.label,
        "filter": name,
        "lqr_violations": float(baseline.summary["constraint_violation_steps"]),
        "lqr_rmse": float(baseline.summary["rmse"]),
    }
    try:
        safety_filter = make_filter(name, env, params)
    except ValueError as error:
        return Outcome(**lqr, refusal=str(error))
    guarded = filtered(controller, safety_filter, env)
    run = evaluate(env, params, guarded, jax.random.key(seed), episodes, measure_time=False)
    summary = run.summary
    return Outcome(
        **lqr,
        violations=float(summary["constraint_violation_steps"]),
        rmse=float(summary["rmse"]),
        infeasible_fraction=float(summary["infeasible_fraction"]),
        mean_correction=float(summary["mean_correction"]),
    )


def outcome_row(outcome: Outcome) -> dict:
    """``outcome`` as a plain dict (a JSON record), with the two ratios the contract bounds."""
    record = dataclasses.asdict(outcome)
    if outcome.refusal is None:
        record["violation_share"] = outcome.violations / max(outcome.lqr_violations, 1e-12)
        record["rmse_ratio"] = outcome.rmse / outcome.lqr_rmse
    record["holds"] = outcome.holds
    return {key: (None if isinstance(value, float) and np.isnan(value) else value) for key, value in record.items()}


__all__ = [
    "CASES",
    "FILTER_NAMES",
    "MAX_RMSE_RATIO",
    "MAX_VIOLATION_SHARE",
    "Case",
    "Outcome",
    "floor_and_ceiling_env",
    "lqr_baseline",
    "outcome_row",
    "run_filter",
]
