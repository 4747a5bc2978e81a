"""The suite's one cache for things built once and reused: compiled functions, jitted closures, drawing scenes.

Policy (the only one): a bounded least-recently-used cache whose entries never keep their owners alive.

- An entry is found by a key of plain data and by the identity of its *owners* (the objects it was built for:
  an env, a controller, a safety filter), never by their equality or hash.
- The cache holds each owner through a weak reference: when an owner is collected, its entries go with it, and a
  new object that happens to get the same ``id`` never finds them.
- At most ``maxsize`` entries are kept; a new entry beyond that evicts the least recently used one. A value that
  itself refers to its owner (a ``jax.jit`` of a bound method) keeps the owner alive until it is evicted, so the
  bound holds there too.

The jitted functions of JAX have their own cache keyed by the Python function; this one is for what a new closure
per call would otherwise compile again.
"""

from __future__ import annotations

import threading
import weakref
from collections import OrderedDict
from collections.abc import Callable, Hashable, Sequence
from typing import Any

import jax


class CompileCache:
    """A bounded LRU cache of values built per ``(owners, key)``; see the module docstring for the policy.

    Args:
        maxsize: how many entries are kept (>= 1).
    """

    def __init__(self, maxsize: int):
        if not isinstance(maxsize, int) or maxsize < 1:
            raise ValueError(f"maxsize: must be a positive integer, got {maxsize!r}")
        self.maxsize = maxsize
        self._entries: OrderedDict = OrderedDict()  # (owner ids, key) -> (weak refs to the owners, value)
        # Entries whose owner died, appended by the weak-reference callbacks and dropped under the lock by the next
        # call: a callback can run inside any allocation (the garbage collector), even one made under the lock.
        self._dead: list = []
        self._lock = threading.Lock()

    def get(self, key: Hashable, build: Callable[[], Any], owners: Sequence = ()) -> Any:
        """The value cached for ``owners`` (matched by identity) and ``key``; ``build()`` makes it on a miss.

        ``build`` runs outside the lock (compiling can take seconds); when two threads miss together, the first
        value stored is the one both get.
        """
        owners = tuple(owners)
        entry_key = (tuple(id(owner) for owner in owners), key)
        with self._lock:
            self._drop_dead()
            entry = self._entries.get(entry_key)
            if entry is not None and all(ref() is owner for ref, owner in zip(entry[0], owners, strict=True)):
                self._entries.move_to_end(entry_key)
                return entry[1]
        value = build()
        with self._lock:
            entry = self._entries.get(entry_key)
            if entry is not None and all(ref() is owner for ref, owner in zip(entry[0], owners, strict=True)):
                self._entries.move_to_end(entry_key)
                return entry[1]
            refs = tuple(weakref.ref(owner, self._forget(entry_key)) for owner in owners)
            self._entries[entry_key] = (refs, value)
            while len(self._entries) > self.maxsize:
                self._entries.popitem(last=False)
        return value

    def _forget(self, entry_key) -> Callable:
        """The weak-reference callback that marks the entry of ``entry_key`` dead when one of its owners dies."""

        def forget(dead_ref) -> None:
            self._dead.append((entry_key, dead_ref))  # list.append is atomic; no lock in a callback

        return forget

    def _drop_dead(self) -> None:
        """Drop the entries whose owner died (call with the lock held)."""
        while self._dead:
            entry_key, dead_ref = self._dead.pop()
            entry = self._entries.get(entry_key)
            # Only the entry that holds this very reference: the key may have been stored again since.
            if entry is not None and any(ref is dead_ref for ref in entry[0]):
                del self._entries[entry_key]

    def __len__(self) -> int:
        with self._lock:
            self._drop_dead()
            return len(self._entries)

    def clear(self) -> None:
        """Drop every entry."""
        with self._lock:
            self._entries.clear()
            self._dead.clear()


_METHODS = CompileCache(maxsize=32)


def jitted_method(owner, name: str) -> Callable:
    """``jax.jit(getattr(owner, name))``, made once per ``owner`` (an env's ``reference``, say): a new bound method
    each call is a new function to ``jax.jit``, which would trace and compile it again."""
    return _METHODS.get(name, lambda: jax.jit(getattr(owner, name)), owners=(owner,))


__all__ = ["CompileCache", "jitted_method"]
