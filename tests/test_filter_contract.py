"""The safety filters' contract over systems x constraints x filters (issue 24): each filter, built with its
defaults from the configured constraint, either cuts LQR's violating steps to at most 10 % of LQR's with an RMSE
at most 1.5x LQR's on the same episodes, or refuses when it is built with a message that says why
(``scg_algorithms.safety_filters.contract``; the measured table is docs/benchmarks/filter_contract.md).

The CBF on the issue's two cases runs in every test run; the other cells are ``slow`` (CI runs them too)."""

from __future__ import annotations

import functools

import pytest

from scg_algorithms.safety_filters import contract as C

EPISODES = 16  # as the benchmark table and `scg-jax eval --episodes 16` (JAX filters: compile time dominates)
# The nonlinear MPSC runs IPOPT per copy and step on the host: one episode per cell (the benchmark's table has more),
# two on the cart-pole within +-0.1 m, where LQR's first episode of one stays inside (of two: 14 violating steps each).
HOST_EPISODES = 1

CART_X, CART_THETA, QUAD_1D, QUAD_2D_Z, QUAD_2D_X, QUAD_3D_Z = range(len(C.CASES))


def _cell(case: int, name: str, slow: bool = True, optimized: bool = False):
    marks = [pytest.mark.slow] if slow else []
    if (case, name) == (QUAD_3D_Z, "nonlinear_mpsc"):  # the table's one miss: 0 violating steps but 3.16x LQR's RMSE
        marks.append(pytest.mark.xfail(strict=True, reason="the nonlinear MPSC's RMSE under the 3D ceiling (open)"))
    if optimized:  # within a violating step or 0.01x of a bound: compiled as the benchmark that measured it
        marks.append(pytest.mark.optimized)
    return pytest.param(case, name, marks=marks, id=f"{C.CASES[case].label}-{name}")


# Every cell of the matrix (6 cases x 3 filters), as benchmarks/filter_contract.py's table in docs/safety-filters.md;
# the CBF on the issue's two cases runs in every test run, the rest are ``slow`` (CI runs them too). Measured margins
# (share of LQR's violating steps, bound 10 %; RMSE ratio, bound 1.5x), JAX filters on these 16 episodes:
#   cbf:         cart |x| 7.6 %, 1.08x; cart |theta| 0 %, 0.89x; 1D 0 %, 1.06x; 2D z 0 %, 1.49x; 2D |x| 0 %, 0.92x;
#                3D z 0 %, 1.49x
#   linear_mpsc: cart |x| 9.6 % (15 steps in all, 15.7 allowed), 1.44x; cart |theta| 3.1 %, 0.83x; 1D 2.2 %, 1.05x;
#                2D z 3.4 %, 1.18x; 2D |x| 0 %, 0.97x; 3D z 2.3 %, 1.489x
#   nonlinear_mpsc (the benchmark's 16 episodes on cart |x|, 2 elsewhere): cart |x| 8.9 %, 1.28x; cart |theta| 0 %,
#                0.83x; 1D 0 %, 1.16x; 2D z 0 %, 1.14x; 2D |x| 0 %, 1.42x
THIN = {(CART_X, "linear_mpsc"), (QUAD_3D_Z, "linear_mpsc")}
CELLS = [
    _cell(case, name, slow=not (name == "cbf" and case in (CART_X, QUAD_2D_Z)), optimized=(case, name) in THIN)
    for case in range(len(C.CASES))
    for name in C.FILTER_NAMES
]


@functools.cache
def _baseline(case: int, episodes: int):
    """``(env, params, controller, evaluation)`` of LQR on the case, shared by its filters."""
    env, params = C.CASES[case].make()
    controller, evaluation = C.lqr_baseline(env, params, episodes)
    return env, params, controller, evaluation


@pytest.mark.parametrize(("case", "name"), CELLS)
def test_filter_keeps_the_constraint_or_refuses(case, name):
    episodes = (2 if case == CART_X else HOST_EPISODES) if name == "nonlinear_mpsc" else EPISODES
    env, params, controller, baseline = _baseline(case, episodes)
    assert baseline.summary["constraint_violation_steps"] >= 2.0  # LQR alone crosses the constraint
    outcome = C.run_filter(C.CASES[case], name, env, params, controller, baseline, episodes)
    if outcome.refusal is not None:
        # A refusal names the filter's option path and says why (after the field, a reason of some words).
        assert f"safety_filters.{name}" in outcome.refusal and len(outcome.refusal.split(": ", 1)[-1]) > 20
        return
    assert outcome.violations <= C.MAX_VIOLATION_SHARE * outcome.lqr_violations, outcome
    assert outcome.rmse <= C.MAX_RMSE_RATIO * outcome.lqr_rmse, outcome


def test_refusal_says_why():
    """A barrier the constraint has none of is refused when built, naming the option and the reason."""
    from scg_algorithms.safety_filters import make_filter

    env, params = C.CASES[CART_X].make()
    with pytest.raises(ValueError, match=r"safety_filters\.cbf\.barrier: no valid barrier .*braking: row 0 bounds x"):
        make_filter("cbf", env, params, {"barrier": "braking"})
