"""The learners the suite trains, by name: what builds each one, trains it into a folder and loads it back.

Everything that lists learners derives from ``LEARNERS``: ``scg-jax train --algo`` (choices and help),
``scg_algorithms.train_run``, ``scg_algorithms.rl.policy.load_policy`` (the learner a saved ``policy.json`` names)
and the reproduction's availability check. A new JAX learner is one line here: a package (or module) exporting
``Config`` (its ``training.<name>`` options) and ``make_learner(config, env) -> Learner`` (optionally
``make_policy_learner``, what loads its saved policy); ``train_run`` then trains it with the shared host driver.
Nothing is imported until a learner is used.
"""

from __future__ import annotations

import dataclasses
import importlib.util

from scg_algorithms.registry import check_name, resolve

JAX, GP_MPC, LEARNED_CBF = "jax", "gp_mpc", "learned_cbf"


@dataclasses.dataclass(frozen=True)
class LearnerSpec:
    """One learner.

    Attributes:
        name: the ``--algo`` name. module: where it lives (imported on first use). summary: one line for help texts.
        kind: how ``train_run`` trains it: ``"jax"`` (a ``Learner`` of pure functions driven by
            ``scg_algorithms.rl.training.run_training``; resumable), ``"gp_mpc"`` (GP-MPC's learning rounds) or
            ``"learned_cbf"`` (the learned CBF's blending episodes); the last two learn on a prior model.
        unit: what its progress counts (``iteration``, ``round``, ``episode``).
        section: the config section holding its options (``training.ppo``, ``controllers.gp_mpc``, ...).
        loads_as: what its folder is used as afterwards: ``"controller"`` (``scg-jax eval --controller DIR``) or
            ``"filter"`` (``--filter DIR``).
    """

    name: str
    module: str
    summary: str
    kind: str = JAX
    unit: str = "iteration"
    section: str = ""
    loads_as: str = "controller"

    @property
    def is_jax(self) -> bool:
        return self.kind == JAX


def _jax(name: str, module: str, summary: str) -> LearnerSpec:
    return LearnerSpec(name, module, summary, section=f"training.{name}")


def _on_prior(name: str, module: str, summary: str, unit: str, loads_as: str = "controller") -> LearnerSpec:
    """A learner on a prior model with a learning loop of its own (its kind is its name); its options are in
    ``controllers.<name>`` (a controller) or ``safety_filters.<name>`` (a filter)."""
    section = f"{'controllers' if loads_as == 'controller' else 'safety_filters'}.{name}"
    return LearnerSpec(name, module, summary, kind=name, unit=unit, section=section, loads_as=loads_as)


LEARNERS: dict[str, LearnerSpec] = {
    spec.name: spec
    for spec in (
        _jax("ppo", "scg_algorithms.ppo", "PPO, clipped policy gradient"),
        _jax("sac", "scg_algorithms.sac", "soft actor-critic"),
        _on_prior("gp_mpc", "scg_algorithms.gp_mpc.controller", "GP-MPC, a GP of the prior's error", "round"),
        _on_prior(
            "learned_cbf", "scg_algorithms.safety_filters.learned_cbf", "a learned CBF filter", "episode", "filter"
        ),
        _jax("safe_ppo", "scg_algorithms.safe_ppo", "PPO with a safety layer"),
        _jax("ppo_lagrangian", "scg_algorithms.ppo_lagrangian", "PPO-Lagrangian, a constrained MDP"),
        _jax("rarl", "scg_algorithms.robust.rarl", "PPO against one adversary"),
        _jax("rap", "scg_algorithms.robust.rap", "PPO against a population of adversaries"),
    )
}


def learner_spec(name: str) -> LearnerSpec:
    """The registered learner ``name``; ``ValueError`` naming the allowed names otherwise."""
    check_name(LEARNERS, name, "algo")
    return LEARNERS[name]


def available(name: str) -> bool:
    """Whether ``name`` is registered and its module is part of this build."""
    if name not in LEARNERS:
        return False
    try:
        return importlib.util.find_spec(LEARNERS[name].module) is not None
    except ImportError:  # a parent package missing from the build
        return False


def prior_learners() -> list[str]:
    """The learners that learn on a prior model (they take ``prior_scale``)."""
    return [name for name, spec in LEARNERS.items() if not spec.is_jax]


def learner_part(name: str, part: str):
    """``Config``, ``make_learner`` or ``make_policy_learner`` of the JAX learner ``name``. ``make_policy_learner``
    (what loads a saved policy) is ``make_learner`` unless the learner defines its own (an adversarial learner's
    protagonist loads on an env without the adversary input it trained against)."""
    spec = learner_spec(name)
    if not spec.is_jax:
        jax_learners = ", ".join(n for n, s in LEARNERS.items() if s.is_jax)
        raise ValueError(f"algo: {name} is not a JAX learner (no {part}); the JAX learners are {jax_learners}")
    module = resolve(spec.module)
    if part == "make_policy_learner" and not hasattr(module, part):
        part = "make_learner"
    return getattr(module, part)


def build_learner(name: str, options, env):
    """``(config, learner)``: the JAX learner ``name`` with ``options`` (its ``training.<name>`` mapping, a
    ``Config`` or None for the defaults) for ``env``. ``ValueError`` naming the option at fault."""
    from scg_algorithms.base import parse_options

    config = parse_options(learner_part(name, "Config"), options, learner_spec(name).section)
    return config, learner_part(name, "make_learner")(config, env)
