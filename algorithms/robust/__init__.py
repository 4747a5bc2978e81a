"""Robust RL: RARL (``scg_algorithms.robust.rarl``, one adversary) and RAP (``scg_algorithms.robust.rap``, a
population), adversarial PPO against the env's adversary input (``scg_algorithms.robust.adversarial``).

PPO with domain randomisation (PPO^DR) is plain ``scg_algorithms.ppo`` on a config with ``physics_randomization``
(``configs/paper_cartpole_ppo_dr_*.yaml``); see ``docs/robust-rl.md``.
"""

from scg_algorithms.robust import adversarial, rap, rarl

__all__ = ["adversarial", "rap", "rarl"]
