"""SAC hyperparameters: one frozen dataclass, parsed from a config file's ``training.sac`` section.

The defaults are tuned for cart-pole stabilization (``configs/cartpole_stabilization.yaml``: 50 Hz, 250-step
episodes) with ``reward_type: exponential`` (or ``upright``): a per-step reward in (0, 1] makes staying up worth
more than falling. With the default ``quadratic`` reward (negative at every step) and ``done_on_out_of_bounds``
an early termination *ends* the negative stream, so a learner can prefer falling quickly. The default budget,
150 k transitions on 64 copies and 37.5 k gradient steps, gives a deterministic policy with an RMSE of 1.4-3.1x
LQR's (seeds 0-2, and seed 0 on machines whose rounding differs) in about 30-50 s on 2 CPU cores, compilation included.

The options every off-policy learner has (budget, replay, discount, Polyak factor, learning rates, networks) and
their checks are ``scg_algorithms.rl.off_policy.Config``'s; SAC adds the temperature and the actor's log-std clip.
A shared option whose SAC default should differ is redeclared here.
"""

from __future__ import annotations

import dataclasses

from scg_algorithms.base import option, parse_options
from scg_algorithms.rl import off_policy


@dataclasses.dataclass(frozen=True)
class Config(off_policy.Config):
    """SAC hyperparameters (``training.sac``): the off-policy options and the temperature's."""

    alpha_lr: float = option(1e-3, "Adam learning rate of log(temperature)", check="positive")
    init_alpha: float = option(0.1, "initial entropy temperature", check="positive")
    autotune_alpha: bool = option(True, "learn the temperature towards the entropy target")
    target_entropy_per_action: float = option(-1.0, "entropy target per action dimension (-1: -nu in total)")
    log_std_min: float = option(-5.0, "lower clip of the actor's log standard deviation")
    log_std_max: float = option(2.0, "upper clip of the actor's log standard deviation")

    def _check(self, path: str) -> None:
        super()._check(path)
        if not self.log_std_min < self.log_std_max:
            raise ValueError(
                f"{path}.log_std_min: must be below log_std_max ({self.log_std_max}), got {self.log_std_min}"
            )


def parse_config(options=None, path: str = "training.sac") -> Config:
    """``Config`` from a mapping (``None``: the defaults); ValueError naming ``<path>.<key>`` on bad input."""
    return parse_options(Config, options, path)
