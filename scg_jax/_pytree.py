"""Frozen dataclasses that are JAX pytrees.

Fields are pytree leaves (traced, vmappable) unless declared with ``static_field()``, which makes them part of
the tree structure (hashable, decided in Python, never traced).
"""

from __future__ import annotations

import dataclasses

import jax


def pytree_dataclass(cls):
    """Decorate ``cls`` as a frozen dataclass registered as a JAX pytree, with a ``replace(**changes)`` method."""
    cls.replace = lambda self, **changes: dataclasses.replace(self, **changes)
    return jax.tree_util.register_dataclass(dataclasses.dataclass(frozen=True)(cls))


def static_field(**kwargs):
    """A dataclass field that belongs to the pytree structure instead of its leaves."""
    return dataclasses.field(metadata={"static": True}, **kwargs)
