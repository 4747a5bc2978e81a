"""The one lookup behind every name registry of the suite (controllers, learners, the reproduction's results):
a name maps to ``"module"`` or ``"module:attribute"``, imported on first use so that listing names stays cheap."""

from __future__ import annotations

import importlib
from collections.abc import Mapping


def check_name(registry: Mapping[str, object], name: str, what: str) -> None:
    """``ValueError`` ``"<what>: unknown name 'x'; allowed values are a, b, c"`` unless ``name`` is registered."""
    if name not in registry:
        raise ValueError(f"{what}: unknown name {name!r}; allowed values are {', '.join(registry)}")


def resolve(target: str):
    """The module ``"package.module"``, or the attribute of ``"package.module:attribute"``, imported now."""
    module, _, attribute = target.partition(":")
    loaded = importlib.import_module(module)
    return getattr(loaded, attribute) if attribute else loaded


def lookup(registry: Mapping[str, str], name: str, what: str):
    """What ``registry[name]`` (``"module"`` or ``"module:attribute"``) points to, imported; ``ValueError`` naming
    ``what`` and the allowed names when ``name`` is not registered."""
    check_name(registry, name, what)
    return resolve(registry[name])
