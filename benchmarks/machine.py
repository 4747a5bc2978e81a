"""Facts about the machine a benchmark ran on, recorded with every result."""

from __future__ import annotations

import os


def cpu_count() -> int:
    """CPU cores this process may run on (its affinity mask where the OS has one)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


def load_average() -> list[float] | None:
    """1, 5 and 15 minute load averages, or None where the OS does not report them."""
    try:
        return [round(v, 2) for v in os.getloadavg()]
    except (AttributeError, OSError):
        return None


def run_record(benchmark: str) -> dict:
    """What every benchmark's JSON starts with: its name, the time, the versions, the device and the machine load.

    Imports JAX and scg_jax, so call it after the benchmark's own ``jax.config`` settings (e.g. x64).
    """
    import datetime
    import platform

    import jax

    import scg_jax

    dev = jax.devices()[0]
    return {
        "benchmark": benchmark,
        "created": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
        "jax_version": jax.__version__,
        "scg_jax_version": scg_jax.__version__,
        "python": platform.python_version(),
        "machine": platform.platform(),
        "device": {"platform": dev.platform, "device_kind": dev.device_kind, "count": jax.device_count()},
        "cpu_count": cpu_count(),
        "cpu_count_total": os.cpu_count(),
        "load_average_start": load_average(),
    }


def print_machine(console, record: dict, prefix: str = "", suffix: str = "") -> None:
    """Print the versions, device, cores and load of a ``run_record``, and a warning when the load average at the
    start exceeds half the usable cores (timings would be low)."""
    device, load = record["device"], record["load_average_start"]
    console.print(
        f"{prefix}jax {record['jax_version']} on {device['platform']} ({device['device_kind']}), "
        f"{record['cpu_count']} CPU cores, load average {load}{suffix}",
        highlight=False,
    )
    if load and load[0] > 0.5 * record["cpu_count"]:
        console.print("[yellow]warning: the machine is busy (load average above half the cores); timings may be low")
