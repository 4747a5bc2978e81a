"""The search spaces of ``scg-jax tune``, as data: for each method, the options tried and their ranges.

Each ``Param`` names an option of the method's config section (``training.<algo>`` for a learner,
``controllers.<name>`` for an MPC) and the range a trial draws it from. ``traced`` marks the options a population
(``--population P``) may hold as traced values, different for each member of one vmapped program (learning rates,
discounts, coefficients, noise scales); the others are structural (network widths, batch sizes, epochs, horizons)
and are the same for every member of a population (they still differ between populations).

The ranges are centred on each learner's defaults (tuned for cart-pole stabilisation) and wide enough to reach
what a harder task needs; a range is what a user would change first, not every option there is. The original
suite's spaces (``safe_control_gym/hyperparameters``) search the same kinds of options for PPO, SAC and GP-MPC.
"""

from __future__ import annotations

import dataclasses


@dataclasses.dataclass(frozen=True)
class Param:
    """One searched option.

    Attributes:
        name: the option's field name in the method's section.
        low, high: the range of a number (``integer``: both ends included). log: drawn log-uniformly.
        choices: the values of a categorical option (instead of a range).
        integer: an integer range. layers: the value is a hidden-layer width repeated this many times (a hidden
            sizes option, e.g. ``[64, 64]``).
        size: ``"nx"`` or ``"nu"``: a diagonal weight, one value per state or input entry (searched as
            ``<name>_0``, ``<name>_1``, ...).
        traced: a population may hold it as a traced value (module docstring).
    """

    name: str
    low: float | None = None
    high: float | None = None
    log: bool = False
    choices: tuple = ()
    integer: bool = False
    layers: int = 0
    size: str | None = None
    traced: bool = False


def _rate(name: str, low: float = 1e-4, high: float = 3e-3) -> Param:
    return Param(name, low, high, log=True, traced=True)


def _unit(name: str, low: float, high: float) -> Param:
    return Param(name, low, high, traced=True)


def _width(name: str) -> Param:
    return Param(name, choices=(32, 64, 128), layers=2)


_PPO = (
    _rate("learning_rate"),
    _unit("clip_eps", 0.1, 0.3),
    _unit("ent_coef", 0.0, 0.01),
    _unit("vf_coef", 0.25, 1.0),
    _unit("gamma", 0.95, 0.999),
    _unit("gae_lambda", 0.9, 0.99),
    _unit("max_grad_norm", 0.3, 1.0),
    _unit("init_log_std", -2.0, 0.0),
    Param("num_epochs", 2, 8, integer=True),
    Param("num_minibatches", choices=(4, 8, 16)),
    _width("actor_hidden"),
    _width("critic_hidden"),
)

_OFF_POLICY = (
    _rate("actor_lr"),
    _rate("critic_lr"),
    _unit("gamma", 0.95, 0.995),
    Param("tau", 1e-3, 5e-2, log=True, traced=True),
    Param("batch_size", choices=(64, 128, 256)),
    Param("utd", choices=(0.125, 0.25, 0.5)),
    _width("hidden_sizes"),
)

_DDPG = (*_OFF_POLICY, _unit("exploration_noise", 0.05, 0.5))

_MPC = (
    Param("horizon", 5, 40, integer=True),
    Param("q_diag", 1e-2, 1e2, log=True, size="nx"),
    Param("r_diag", 1e-3, 1e1, log=True, size="nu"),
)

SEARCH_SPACES: dict[str, tuple[Param, ...]] = {
    "ppo": _PPO,
    "safe_ppo": _PPO,
    "ppo_lagrangian": (*_PPO, Param("lambda_lr", 5e-3, 0.1, log=True, traced=True)),
    "sac": (*_OFF_POLICY, _rate("alpha_lr"), Param("init_alpha", 0.01, 1.0, log=True)),
    "ddpg": _DDPG,
    "td3": (
        *_DDPG,
        _unit("target_noise", 0.05, 0.4),
        _unit("target_noise_clip", 0.2, 0.6),
        Param("policy_delay", 1, 3, integer=True),
    ),
    "gp_mpc": _MPC,
    "linear_mpc": _MPC,
    "nonlinear_mpc": _MPC,
}
"""Method name -> the options ``scg-jax tune`` searches (the learners of ``scg_algorithms.learners`` and the MPC
controllers of ``scg_algorithms.CONTROLLERS`` named here)."""
