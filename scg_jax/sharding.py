"""One job over many devices and hosts: the env batch axis laid out over a 1-D device mesh with ``jax.sharding``.

Everything batched in the suite (rollouts, evaluation, a learner's collection and updates) is a ``jit`` of a
``vmap`` over env copies. To spread it over devices nothing in the envs or learners changes: the copies' axis is
given a ``NamedSharding(mesh, P("envs"))`` over a 1-D mesh, everything else (env params, network weights,
optimiser state) is replicated (``P()``), and ``jit`` (GSPMD) partitions the computation. Reductions over the batch
(a loss's mean, hence its gradient; observation statistics; episode means) become all-reduces the compiler inserts,
so gradients are averaged exactly once. No hand-written ``pmean`` is needed; note that inside ``jax.shard_map`` the
gradient of a replicated parameter is already summed over devices, so brax's ``pmean(grad(loss))`` there gives
``N_devices`` times the gradient (``grad(pmean(loss))`` is the right order).

Random numbers do not depend on the layout (``jax_threefry_partitionable``, JAX's default), so a sharded run equals
the single-device run up to the order of floating-point reductions.

Several hosts: ``initialize_distributed`` (``jax.distributed.initialize``) joins the processes; the mesh then spans
every process's devices, each process steps the copies on its own devices, ``to_host`` gathers results to every
process, and only ``is_main_process()`` writes files.

``devices`` (config key and CLI ``--devices``): ``"all"`` (every device JAX sees, over all processes), a positive
integer N (the first N), or ``None``/``1`` (no sharding: the code paths of a single device, unchanged).
"""

from __future__ import annotations

import os
from typing import Any

import jax
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from scg_jax.validation import FieldError

BATCH_AXIS = "envs"
"""Name of the mesh axis the env copies are laid out along."""


# --------------------------------------------------------------------------------------------- options
def check_devices(value, path: str = "devices"):
    """``value`` as ``"all"``, a positive int, or ``None``; FieldError naming ``path`` and the allowed values."""
    if value is None or value == "all":
        return value
    if isinstance(value, str) and value.strip().isdigit():
        value = int(value.strip())
    if isinstance(value, bool) or not isinstance(value, int | np.integer) or value < 1:
        raise FieldError(path, f"expected 'all' or a positive integer (number of devices), got {value!r}")
    return int(value)


def device_count(devices) -> int:
    """How many devices ``devices`` (``"all"``, N or None) selects; FieldError when more than JAX sees."""
    devices = check_devices(devices)
    available = jax.device_count()
    if devices is None:
        return 1
    if devices == "all":
        return available
    if devices > available:
        raise FieldError(
            "devices",
            f"{devices} devices asked for but JAX sees {available} ({jax.default_backend()}); use 'all' or at most "
            f"{available} (on CPU, XLA_FLAGS=--xla_force_host_platform_device_count=N simulates N devices)",
        )
    return devices


def make_mesh(devices) -> Mesh | None:
    """The 1-D mesh ``("envs",)`` over the devices ``devices`` selects, or ``None`` when that is one device of one
    process (nothing is sharded then, and every code path is the single-device one)."""
    n = device_count(devices)
    if n == 1 and jax.process_count() == 1:
        return None
    return Mesh(np.asarray(jax.devices()[:n]), (BATCH_AXIS,))


def mesh_size(mesh: Mesh | None) -> int:
    """Number of devices of ``mesh`` (1 for ``None``)."""
    return 1 if mesh is None else int(mesh.devices.size)


def check_divisible(batch: int, mesh: Mesh | None, what: str = "num_envs") -> None:
    """ValueError naming both numbers when ``batch`` copies cannot be split evenly over the mesh's devices."""
    n = mesh_size(mesh)
    if int(batch) % n:
        lower, upper = (int(batch) // n) * n, (int(batch) // n + 1) * n
        options = f"{lower} or {upper}" if lower else f"{upper}"
        raise FieldError(
            what,
            f"{int(batch)} env copies do not split evenly over {n} devices; use a multiple of {n} (e.g. {options}) "
            f"or another device count (devices)",
        )


# --------------------------------------------------------------------------------------------- shardings
def batch_sharding(mesh: Mesh, axis: int = 0) -> NamedSharding:
    """Sharding of an array whose axis ``axis`` is the env batch (the other axes whole on every device)."""
    return NamedSharding(mesh, PartitionSpec(*([None] * axis), BATCH_AXIS))


def replicated(mesh: Mesh) -> NamedSharding:
    """Sharding of an array held whole on every device (params, network weights, keys)."""
    return NamedSharding(mesh, PartitionSpec())


def _put(leaf, sharding: NamedSharding):
    """``leaf`` (the same global value on every process) placed with ``sharding``; works across processes."""
    if isinstance(leaf, jax.Array) and jax.dtypes.issubdtype(leaf.dtype, jax.dtypes.prng_key):
        return jax.random.wrap_key_data(_put(jax.random.key_data(leaf), sharding), impl=jax.random.key_impl(leaf))
    if sharding.is_fully_addressable:
        return jax.device_put(leaf, sharding)
    host = np.asarray(leaf)
    return jax.make_array_from_callback(host.shape, sharding, lambda index: host[index])


def shard_batch(tree, mesh: Mesh | None, axis: int = 0):
    """Every leaf of ``tree`` laid out along its axis ``axis`` (the env copies) over ``mesh``; ``tree`` unchanged
    when ``mesh`` is None. The leaves hold the global batch (the same values on every process)."""
    if mesh is None:
        return tree
    sharding = batch_sharding(mesh, axis)
    for leaf in jax.tree.leaves(tree):
        check_divisible(np.shape(leaf)[axis], mesh)
    return jax.tree.map(lambda leaf: _put(leaf, sharding), tree)


def replicate(tree, mesh: Mesh | None):
    """Every leaf of ``tree`` held whole on every device of ``mesh`` (``tree`` unchanged when ``mesh`` is None)."""
    if mesh is None:
        return tree
    sharding = replicated(mesh)
    return jax.tree.map(lambda leaf: _put(leaf, sharding), tree)


def constrain_batch(tree, mesh: Mesh | None, axis: int = 0):
    """Inside ``jit``: tell the partitioner that ``tree``'s leaves are batched along ``axis`` (identity without a
    mesh). Used where a batch is created inside a compiled function (reset keys, rollout carries)."""
    if mesh is None:
        return tree
    sharding = batch_sharding(mesh, axis)
    return jax.tree.map(lambda leaf: jax.lax.with_sharding_constraint(leaf, sharding), tree)


def shardings_of(tree):
    """The ``.sharding`` of every leaf (for ``jit(in_shardings=..., out_shardings=...)``)."""
    return jax.tree.map(lambda leaf: leaf.sharding, tree)


# --------------------------------------------------------------------------------------------- hosts
def to_host(tree):
    """Every leaf as a numpy array of the *global* value: leaves spread over several processes are gathered
    (``multihost_utils.process_allgather``, a collective: every process must call it), others copied. Typed PRNG
    keys come back as their raw ``uint32`` data (``jax.random.key_data``)."""

    def gather(leaf):
        if isinstance(leaf, jax.Array) and jax.dtypes.issubdtype(leaf.dtype, jax.dtypes.prng_key):
            leaf = jax.random.key_data(leaf)
        if isinstance(leaf, jax.Array) and not leaf.is_fully_addressable:
            from jax.experimental import multihost_utils

            return np.asarray(multihost_utils.process_allgather(leaf, tiled=True))
        return np.asarray(leaf)

    return jax.tree.map(gather, tree)


def is_main_process() -> bool:
    """Whether this process writes files (process 0; always true without ``jax.distributed``)."""
    return jax.process_index() == 0


def initialize_distributed(
    coordinator_address: str | None = None,
    num_processes: int | None = None,
    process_id: int | None = None,
    local_device_count: int | None = None,
) -> dict[str, Any]:
    """Join a multi-process JAX job (``jax.distributed.initialize``); call before any JAX computation.

    Arguments left ``None`` come from the environment: ``JAX_COORDINATOR_ADDRESS`` (read by JAX),
    ``SCG_JAX_NUM_PROCESSES`` and ``SCG_JAX_PROCESS_ID``, and otherwise JAX's cluster auto-detection (SLURM,
    Open MPI, Kubernetes, TPU pods). On CPU the cross-process collectives use gloo; ``local_device_count`` (or
    ``SCG_JAX_LOCAL_DEVICES``) simulates that many CPU devices per process (tests, a laptop).

    Returns:
        ``{"process_index", "process_count", "local_devices", "global_devices"}``.
    """
    env = os.environ
    if num_processes is None and env.get("SCG_JAX_NUM_PROCESSES"):
        num_processes = int(env["SCG_JAX_NUM_PROCESSES"])
    if process_id is None and env.get("SCG_JAX_PROCESS_ID"):
        process_id = int(env["SCG_JAX_PROCESS_ID"])
    if local_device_count is None and env.get("SCG_JAX_LOCAL_DEVICES"):
        local_device_count = int(env["SCG_JAX_LOCAL_DEVICES"])
    if local_device_count is not None:
        jax.config.update("jax_num_cpu_devices", int(local_device_count))
    # Without a GPU/TPU the processes exchange arrays over gloo (TCP); on accelerators JAX picks NCCL etc.
    jax.config.update("jax_cpu_collectives_implementation", "gloo")
    jax.distributed.initialize(
        coordinator_address=coordinator_address, num_processes=num_processes, process_id=process_id
    )
    return {
        "process_index": jax.process_index(),
        "process_count": jax.process_count(),
        "local_devices": jax.local_device_count(),
        "global_devices": jax.device_count(),
    }
