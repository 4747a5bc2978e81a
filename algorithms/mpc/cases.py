"""Standard MPC check problems, one per system: what the linear-MPC parity tests and ``benchmarks/control.py``
solve, so that a test and a benchmark figure speak of the same problems.

Each case names the ``scg_jax.make`` arguments, the state constraints of its "input and state" variant and where
its random states lie: ``x_ref[step] + offset + U(-spread, spread)`` for a random step of the reference (step 0
for stabilization). What presses: the cart-pole's 0.3 m cart box; the 1D quadrotor's goal at 1.8 m above its
1.5 m ceiling; the 2D quadrotor's position box around its circle; the 3D quadrotor's position box.
"""

import dataclasses

import numpy as np

import scg_jax
from scg_algorithms.base import Reference

INPUT_LIMITS = ({"type": "default", "on": "input"},)


@dataclasses.dataclass(frozen=True)
class Case:
    """One check problem.

    Attributes:
        make_kwargs: ``scg_jax.make`` arguments, ``system`` included, constraints excluded.
        state_constraints: the constraint dicts added to the actuator limits in the "input and state" variant.
        offset: (nx,) or scalar, centre of the random states relative to the reference point.
        spread: (nx,) half-widths of the random states, in the state's units.
    """

    make_kwargs: dict
    state_constraints: tuple
    offset: object
    spread: tuple


CASES = {
    "cartpole": Case(
        {"system": "cartpole"},
        ({"type": "bounded", "on": "state", "active_dims": [0], "low": [-0.3], "high": [0.3]},),
        0.0,
        (0.25, 0.5, 0.3, 0.5),
    ),
    "quadrotor_1d": Case(
        {"system": "quadrotor_1d", "goal": [1.8, 0.0]},
        ({"type": "bounded", "on": "state", "active_dims": [0], "low": [-10.0], "high": [1.5]},),
        (-0.6, 0.0),
        (0.3, 1.0),
    ),
    "quadrotor_2d": Case(
        {"system": "quadrotor_2d", "task": "tracking"},
        (
            {"type": "default", "on": "state"},
            {"type": "bounded", "on": "state", "active_dims": [0, 2], "low": [-0.52, 0.48], "high": [0.52, 1.52]},
        ),
        0.0,
        (0.1, 0.3, 0.1, 0.3, 0.3, 0.5),
    ),
    "quadrotor_3d": Case(
        {"system": "quadrotor_3d", "goal": [0, 0, 0, 0, 1, 0, 0, 0, 0, 0, 0, 0]},
        (
            {
                "type": "bounded",
                "on": "state",
                "active_dims": [0, 2, 4],
                "low": [-0.3, -0.3, 0.7],
                "high": [0.3, 0.3, 1.3],
            },
        ),
        0.0,
        (0.3, 0.5) * 3 + (0.2,) * 3 + (0.5,) * 3,
    ),
}


def case_constraints(name: str, with_state: bool = True, extra=()) -> list:
    """The constraint dicts of case ``name``: the actuator limits, its state rows when ``with_state``, then
    ``extra``."""
    case = CASES[name]
    return [*INPUT_LIMITS, *(case.state_constraints if with_state else ()), *extra]


def random_states(env, reference: Reference, offset, spread, count: int, seed: int = 0):
    """``count`` random (step, state) pairs: steps uniform over the reference (0 for stabilization) and states
    ``x_ref[step] + offset + U(-spread, spread)``.

    Returns:
        ``(steps, states)``: (count,) int and (count, nx) float64.
    """
    rng = np.random.default_rng(seed)
    n = np.asarray(reference.x_ref).shape[0]
    steps = rng.integers(0, n - 1, count) if env.task == "tracking" else np.zeros(count, int)
    states = (
        np.asarray(reference.x_ref)[steps]
        + np.asarray(offset)
        + rng.uniform(-1.0, 1.0, (count, env.nx)) * (np.asarray(spread, np.float64))
    )
    return steps, states


def make_case_env(name: str, with_state: bool = True, extra=()):
    """The env of case ``name`` with :func:`case_constraints` and its default params."""
    kwargs = dict(CASES[name].make_kwargs)
    env = scg_jax.make(kwargs.pop("system"), constraints=case_constraints(name, with_state, extra), **kwargs)
    return env, env.default_params
