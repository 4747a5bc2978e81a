"""The scale-out options of ``rollout``, ``eval`` and ``train``: ``--devices`` (the env copies over several
devices, ``scg_jax.sharding``) and ``--distributed`` (one job over several processes or hosts)."""

from __future__ import annotations

import argparse
import os

from scg_cli.common import UsageError


def add_scale_arguments(parser: argparse.ArgumentParser) -> None:
    """``--devices``, ``--distributed`` and its explicit coordinator options."""
    group = parser.add_argument_group("scale-out (docs/scaling.md)")
    group.add_argument(
        "--devices",
        metavar="all|N",
        help="lay the env copies out over all devices or the first N (overrides the config's devices; default: one)",
    )
    group.add_argument(
        "--distributed",
        action="store_true",
        help="join a multi-process job (jax.distributed.initialize: cluster auto-detection, or the options below, "
        "or JAX_COORDINATOR_ADDRESS / SCG_JAX_NUM_PROCESSES / SCG_JAX_PROCESS_ID); only process 0 writes files",
    )
    group.add_argument("--coordinator", metavar="HOST:PORT", help="address of process 0's coordinator service")
    group.add_argument("--num-processes", type=int, metavar="N", help="processes in the job")
    group.add_argument("--process-id", type=int, metavar="I", help="this process's index, 0..N-1")


def start_distributed(args: argparse.Namespace) -> None:
    """Join the job when ``--distributed`` is given; must run before any JAX computation (so before the env)."""
    if not getattr(args, "distributed", False):
        for flag in ("coordinator", "num_processes", "process_id"):
            if getattr(args, flag, None) is not None:
                raise UsageError(f"argument --{flag.replace('_', '-')}: only with --distributed")
        return
    from scg_jax.sharding import initialize_distributed

    try:
        initialize_distributed(args.coordinator, args.num_processes, args.process_id)
    except (ValueError, RuntimeError) as error:
        if args.coordinator is None and not os.environ.get("JAX_COORDINATOR_ADDRESS"):
            # JAX's own words here are "coordinator_address should be defined."
            raise UsageError(
                "argument --distributed: found no cluster to join (SLURM, Open MPI or Kubernetes) and no coordinator; "
                "pass --coordinator HOST:PORT --num-processes N --process-id I (or set JAX_COORDINATOR_ADDRESS, "
                "SCG_JAX_NUM_PROCESSES and SCG_JAX_PROCESS_ID); docs/scaling.md has launch recipes"
            ) from None
        raise UsageError(f"argument --distributed: could not join the job: {error}") from None
    if args.devices is None:
        args.devices = "all"  # a multi-process job spans every process's devices


def make_mesh(args: argparse.Namespace, cfg):
    """The mesh of ``--devices`` (else the config's ``devices``), or None for one device; a --distributed job's mesh
    spans every device of every process (a UsageError otherwise)."""
    import jax

    from scg_jax.sharding import make_mesh as mesh_of
    from scg_jax.validation import FieldError

    flag = getattr(args, "devices", None)
    try:
        mesh = mesh_of(flag if flag is not None else cfg.devices)
    except FieldError as error:
        raise UsageError(f"argument --devices: {error.reason}" if flag is not None else str(error)) from None
    if jax.process_count() > 1 and mesh.devices.size != jax.device_count():  # a process left out has nothing to step
        raise UsageError(
            f"argument --devices: a --distributed job spans the {jax.device_count()} devices of its "
            f"{jax.process_count()} processes; use all (the default with --distributed), not {flag}"
        )
    return mesh


def is_main_process() -> bool:
    """Whether this process writes files (process 0 of a ``--distributed`` job; always without one)."""
    from scg_jax.sharding import is_main_process as main

    return main()


def check_batch(mesh, copies: int, flag: str) -> None:
    """UsageError naming ``flag`` when ``copies`` do not split evenly over the mesh's devices."""
    from scg_jax.sharding import check_divisible
    from scg_jax.validation import FieldError

    try:
        check_divisible(copies, mesh, flag)
    except FieldError as error:
        raise UsageError(f"argument {flag}: {error.reason}") from None
