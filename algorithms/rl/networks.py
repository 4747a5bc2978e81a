"""The RL learners' networks (flax.linen), in one module: PPO, SAC and the safe variants build from these.

- ``MLP``: dense layers with orthogonal initialisation; ``value_network`` (PPO's critic, or a cost critic) is one.
- ``TanhGaussianActor``: SAC's policy head, ``obs -> (mean, log_std)`` of the pre-squash Gaussian.
- ``DeterministicActor``: DDPG's and TD3's policy, ``obs -> tanh(net(obs))``.
- ``QNetwork`` and ``twin_q``: the off-policy learners' Q critics, K parameter sets stacked on a leading axis (two
  for SAC's and TD3's twin critics, one for DDPG's).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import flax.linen as nn
import jax
import jax.numpy as jnp

ACTIVATIONS: dict[str, Callable] = {
    "tanh": jnp.tanh,
    "relu": nn.relu,
    "elu": nn.elu,
    "gelu": nn.gelu,
    "silu": nn.silu,
    "swish": nn.silu,
}


def activation(name: str) -> Callable:
    """The activation function called ``name``; ``ValueError`` naming the allowed names otherwise."""
    if name not in ACTIVATIONS:
        raise ValueError(f"activation: unknown value {name!r}; allowed values are {', '.join(ACTIVATIONS)}")
    return ACTIVATIONS[name]


class MLP(nn.Module):
    """Dense layers of ``features`` units, ``activation`` between them, the last layer linear.

    Weights are orthogonal with gain ``sqrt(2)`` (``final_scale`` for the last layer, e.g. 0.01 for a policy mean
    that starts near zero, 1.0 for a value), biases zero: the usual initialisation for PPO and SAC.

    Attributes:
        features: output sizes of the layers, e.g. ``(64, 64, 1)``. activation: a name from ``ACTIVATIONS``.
        final_scale: gain of the last layer's orthogonal initialisation. activate_final: apply the activation after
            the last layer too.

    Input (..., in) -> output (..., features[-1]).
    """

    features: Sequence[int]
    activation: str = "tanh"
    final_scale: float = 1.0
    activate_final: bool = False

    @nn.compact
    def __call__(self, x):
        act = activation(self.activation)
        last = len(self.features) - 1
        for i, size in enumerate(self.features):
            scale = self.final_scale if i == last else jnp.sqrt(2.0)
            x = nn.Dense(int(size), kernel_init=nn.initializers.orthogonal(scale), bias_init=nn.initializers.zeros)(x)
            if i < last or self.activate_final:
                x = act(x)
        return x


def value_network(hidden: Sequence[int], activation: str = "tanh") -> MLP:
    """A state-value network ``obs (..., obs_size) -> (..., 1)`` (read ``[..., 0]``): PPO's critic, and the shape of
    a cost critic ``V_c`` for constrained learners."""
    return MLP((*hidden, 1), activation, final_scale=1.0)


class TanhGaussianActor(nn.Module):
    """Tanh-squashed Gaussian policy head: ``obs (..., obs_size) -> (mean, log_std)``, each (..., action_size).

    ``log_std`` depends on the observation and is clipped to ``[log_std_min, log_std_max]``; the action is
    ``tanh(mean + exp(log_std) eps)`` (deterministic: ``tanh(mean)``).
    """

    hidden: tuple[int, ...]
    action_size: int
    activation: str = "relu"
    log_std_min: float = -5.0
    log_std_max: float = 2.0

    @nn.compact
    def __call__(self, obs):
        # A small final layer starts every copy near mean 0, std 1: broad exploration and no saturated tanh.
        out = MLP((*self.hidden, 2 * self.action_size), self.activation, final_scale=0.01)(obs)
        mean, log_std = jnp.split(out, 2, axis=-1)
        return mean, jnp.clip(log_std, self.log_std_min, self.log_std_max)


class DeterministicActor(nn.Module):
    """Deterministic policy ``obs (..., obs_size) -> a = tanh(net(obs)) (..., action_size)`` in [-1, 1].

    The last layer starts small (as ``TanhGaussianActor``'s): every copy starts near ``a = 0``, far from the
    saturated tanh.
    """

    hidden: tuple[int, ...]
    action_size: int
    activation: str = "relu"

    @nn.compact
    def __call__(self, obs):
        return jnp.tanh(MLP((*self.hidden, self.action_size), self.activation, final_scale=0.01)(obs))


class QNetwork(nn.Module):
    """One Q network: ``(obs (..., obs_size), action (..., action_size)) -> Q (...)``."""

    hidden: tuple[int, ...]
    activation: str = "relu"

    @nn.compact
    def __call__(self, obs, action):
        return MLP((*self.hidden, 1), self.activation)(jnp.concatenate([obs, action], axis=-1))[..., 0]


def twin_q(critic: QNetwork, critic_params, obs, action):
    """Every critic: ``critic_params`` holds K parameter sets stacked on a leading axis (two for twin critics).
    Returns (K, ...)."""
    return jax.vmap(critic.apply, in_axes=(0, None, None))(critic_params, obs, action)
