"""Checkpoints of any JAX pytree: ``<name>.msgpack`` (the arrays) and ``<name>.json`` (metadata), written atomically.

The msgpack file holds a flat mapping from each leaf's path (``jax.tree_util.keystr``, e.g.
``"['params']['actor']['Dense_0']['kernel']"``) to its array, so it works for flax parameter dicts, NamedTuples and
the env's pytree dataclasses alike, and a reader can inspect it without the code that wrote it. Typed PRNG keys are
stored as their raw ``uint32`` data.

Each file is written whole or not at all (``scg_jax.files.write_atomic``: a temporary file, then a rename). The
arrays go first and the JSON, which records the SHA-256 of the arrays file, last; ``load_checkpoint`` checks it, so a
crash between the two renames is reported instead of silently pairing new arrays with old metadata.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import Any

import jax
import numpy as np
from flax import serialization

from scg_jax.files import write_atomic, write_json

FORMAT = "scg-jax-pytree-v1"


def _is_typed_key(leaf) -> bool:
    return hasattr(leaf, "dtype") and jax.dtypes.issubdtype(leaf.dtype, jax.dtypes.prng_key)


def _flat(pytree) -> dict[str, np.ndarray]:
    leaves, _ = jax.tree_util.tree_flatten_with_path(pytree)
    flat = {}
    for path, leaf in leaves:
        if _is_typed_key(leaf):
            leaf = jax.random.key_data(leaf)
        flat[jax.tree_util.keystr(path)] = np.asarray(leaf)
    return flat


def save_checkpoint(directory, name: str, pytree, metadata: dict) -> None:
    """Write ``directory/<name>.msgpack`` (the leaves of ``pytree``) and ``directory/<name>.json``.

    Args:
        directory: folder (created if missing). name: file stem, e.g. ``"checkpoint"`` or ``"policy"``.
        pytree: any pytree of arrays (device arrays are copied to the host). metadata: JSON-serialisable dict;
            ``format``, ``leaves`` and ``sha256`` are added to it in the file.
    """
    directory = Path(directory)
    data = serialization.msgpack_serialize(_flat(pytree))
    meta = dict(metadata)
    meta["checkpoint"] = {"format": FORMAT, "sha256": hashlib.sha256(data).hexdigest()}
    json.dumps(meta)  # fail before touching any file if the metadata cannot be written
    write_atomic(directory / f"{name}.msgpack", lambda file: file.write(data))
    write_json(directory / f"{name}.json", meta)


def load_metadata(directory, name: str) -> dict:
    """The metadata dict of a checkpoint (``<name>.json``)."""
    return json.loads((Path(directory) / f"{name}.json").read_text())


def load_checkpoint(directory, name: str, target) -> tuple[Any, dict]:
    """Read a checkpoint written by ``save_checkpoint``.

    Args:
        directory, name: as for ``save_checkpoint``. target: a pytree with the structure to restore (its leaves may
            be arrays or ``jax.ShapeDtypeStruct``); shapes and dtypes must match, values are taken from the file (as
            numpy arrays; typed PRNG keys are rebuilt as typed keys).

    Returns:
        ``(pytree, metadata)``.

    Raises:
        FileNotFoundError: a file is missing. ValueError: the arrays file does not match its JSON (an interrupted
            write), or the stored leaves do not match ``target`` in names, shapes or dtypes (names the first
            differing leaf).
    """
    directory = Path(directory)
    meta = load_metadata(directory, name)
    data = (directory / f"{name}.msgpack").read_bytes()
    stored_hash = meta.get("checkpoint", {}).get("sha256")
    if stored_hash is not None and stored_hash != hashlib.sha256(data).hexdigest():
        raise ValueError(
            f"{directory / name}.msgpack: does not match {name}.json (an interrupted write?); delete both and start "
            "again"
        )
    stored = serialization.msgpack_restore(data)
    leaves, treedef = jax.tree_util.tree_flatten_with_path(target)
    names = [jax.tree_util.keystr(path) for path, _ in leaves]
    missing = [n for n in names if n not in stored]
    extra = [n for n in stored if n not in set(names)]
    if missing or extra:
        detail = f"missing {missing[0]}" if missing else f"unexpected {extra[0]}"
        raise ValueError(f"{directory / name}.msgpack: leaves do not match the target structure ({detail})")
    restored = []
    for (_, leaf), key in zip(leaves, names, strict=True):
        value = np.asarray(stored[key])
        if _is_typed_key(leaf):
            restored.append(jax.random.wrap_key_data(value))
            continue
        shape = tuple(getattr(leaf, "shape", np.shape(leaf)))
        if value.shape != shape:
            raise ValueError(f"{directory / name}.msgpack: {key} has shape {value.shape}, expected {shape}")
        # A silently different dtype would retrace (or break) the compiled functions the state is fed to.
        if hasattr(leaf, "dtype") and value.dtype != np.dtype(leaf.dtype):
            raise ValueError(f"{directory / name}.msgpack: {key} has dtype {value.dtype}, expected {leaf.dtype}")
        restored.append(value)
    return jax.tree_util.tree_unflatten(treedef, restored), meta
