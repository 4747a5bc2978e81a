"""SAC hyperparameters: one frozen dataclass, parsed from a config file's ``training.sac`` section.

The defaults are tuned for cart-pole stabilization (``configs/cartpole_stabilization.yaml``: 50 Hz, 250-step
episodes) with ``reward_type: exponential`` (or ``upright``): a per-step reward in (0, 1] makes staying up worth
more than falling. With the default ``quadratic`` reward (negative at every step) and ``done_on_out_of_bounds``
an early termination *ends* the negative stream, so a learner can prefer falling quickly. The default budget,
150 k transitions on 64 copies and 37.5 k gradient steps, gives a deterministic policy with an RMSE of 1.4-3.1x
LQR's (seeds 0-2, and seed 0 on machines whose rounding differs) in about 30-50 s on 2 CPU cores, compilation included.

Budget: ``total_env_steps`` transitions (summed over the ``num_envs`` copies) and ``utd * total_env_steps``
gradient steps; each iteration collects ``num_envs * rollout_steps`` transitions, then takes
``utd * num_envs * rollout_steps`` gradient steps (an integer, checked).
"""

from __future__ import annotations

import dataclasses
import math

from scg_algorithms.base import option, parse_options
from scg_algorithms.rl.config import check_budget, hidden_sizes_option, learner_option


@dataclasses.dataclass(frozen=True)
class Config:
    """SAC hyperparameters (``training.sac``). Steps count transitions summed over the parallel copies."""

    total_env_steps: int = learner_option("total_env_steps", 150_000)
    num_envs: int = learner_option("num_envs", 64)
    rollout_steps: int = option(1, "control steps per copy collected per iteration", check="positive")
    utd: float = option(0.25, "gradient steps per environment transition (update-to-data ratio)", check="positive")
    warmup_steps: int = option(
        5_000, "transitions collected with uniform random actions before learning starts", check="non_negative"
    )
    buffer_size: int = option(100_000, "replay capacity in transitions (clipped to total_env_steps)", check="positive")
    batch_size: int = option(256, "transitions per gradient step", check="positive")
    gamma: float = option(0.99, "discount factor per control step")
    tau: float = option(0.005, "Polyak factor of the target critics: target <- (1 - tau) target + tau online")
    actor_lr: float = option(1e-3, "Adam learning rate of the actor", check="positive")
    critic_lr: float = option(1e-3, "Adam learning rate of the twin critics", check="positive")
    alpha_lr: float = option(1e-3, "Adam learning rate of log(temperature)", check="positive")
    init_alpha: float = option(0.1, "initial entropy temperature", check="positive")
    autotune_alpha: bool = option(True, "learn the temperature towards the entropy target")
    target_entropy_per_action: float = option(-1.0, "entropy target per action dimension (-1: -nu in total)")
    hidden_sizes: tuple = hidden_sizes_option((64, 64), "hidden layer widths of the actor and of each critic")
    activation: str = learner_option("activation", "relu")
    log_std_min: float = option(-5.0, "lower clip of the actor's log standard deviation")
    log_std_max: float = option(2.0, "upper clip of the actor's log standard deviation")
    reward_scale: float = learner_option("reward_scale", 1.0)
    normalize_observations: bool = learner_option("normalize_observations", True)
    max_grad_norm: float = option(0.0, "global gradient-norm clip of every optimiser (0: off)", check="non_negative")
    action_scale: float = learner_option("action_scale", 1.0)

    def _check(self, path: str) -> None:
        if not 0.0 < self.gamma < 1.0:
            raise ValueError(f"{path}.gamma: must be in (0, 1), got {self.gamma}")
        if not 0.0 < self.tau <= 1.0:
            raise ValueError(f"{path}.tau: must be in (0, 1], got {self.tau}")
        if not self.log_std_min < self.log_std_max:
            raise ValueError(
                f"{path}.log_std_min: must be below log_std_max ({self.log_std_max}), got {self.log_std_min}"
            )
        per_iteration = self.utd * self.transitions_per_iteration
        if not math.isclose(per_iteration, round(per_iteration)) or round(per_iteration) < 1:
            raise ValueError(
                f"{path}.utd: utd * num_envs * rollout_steps must be a positive integer (gradient steps per "
                f"iteration), got {self.utd} * {self.num_envs} * {self.rollout_steps} = {per_iteration:g}"
            )
        check_budget(path, self.total_env_steps, self.transitions_per_iteration, "num_envs * rollout_steps")
        if self.transitions_per_iteration > self.capacity:
            raise ValueError(
                f"{path}.buffer_size: must hold one iteration's {self.transitions_per_iteration} transitions, "
                f"got {self.buffer_size}"
            )

    # ------------------------------------------------------------------------------------------ derived
    @property
    def transitions_per_iteration(self) -> int:
        return self.num_envs * self.rollout_steps

    @property
    def grad_steps_per_iteration(self) -> int:
        return round(self.utd * self.transitions_per_iteration)

    @property
    def num_iterations(self) -> int:
        """Iterations of the whole budget (rounded down to whole iterations)."""
        return self.total_env_steps // self.transitions_per_iteration

    @property
    def warmup_iterations(self) -> int:
        """Iterations that act randomly and do not learn (at least ``warmup_steps`` transitions, whole
        iterations, and at least one batch in the buffer), at most ``num_iterations``."""
        needed = max(self.warmup_steps, self.batch_size)
        return min(-(-needed // self.transitions_per_iteration), self.num_iterations)

    @property
    def capacity(self) -> int:
        """Replay capacity: ``buffer_size`` clipped to the budget (a larger buffer would never fill)."""
        return min(self.buffer_size, max(self.total_env_steps, 1))

    def to_dict(self) -> dict:
        """Plain JSON-able mapping that ``parse_config`` turns back into an equal ``Config``."""
        values = {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}
        return {name: list(value) if isinstance(value, tuple) else value for name, value in values.items()}


def parse_config(options=None, path: str = "training.sac") -> Config:
    """``Config`` from a mapping (``None``: the defaults); ValueError naming ``<path>.<key>`` on bad input."""
    return parse_options(Config, options, path)
