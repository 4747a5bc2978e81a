"""Small fully connected networks (flax.linen) for the RL learners."""

from __future__ import annotations

from collections.abc import Callable, Sequence

import flax.linen as nn
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
