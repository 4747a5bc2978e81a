"""The systems of the suite, one module each; ``SYSTEMS`` maps a name to its static ``System`` description."""

from scg_jax.systems import cartpole, quadrotor_1d, quadrotor_2d, quadrotor_3d
from scg_jax.systems.base import System

SYSTEMS: dict[str, System] = {
    module.SYSTEM.name: module.SYSTEM for module in (cartpole, quadrotor_1d, quadrotor_2d, quadrotor_3d)
}


def get_system(name: str) -> System:
    """Return the system called ``name``; raise a ValueError naming the allowed values otherwise."""
    if name not in SYSTEMS:
        raise ValueError(f"system: unknown value {name!r}; allowed values are {', '.join(SYSTEMS)}")
    return SYSTEMS[name]


__all__ = ["SYSTEMS", "System", "get_system"]
