"""The paper's results, reproduced by one command (``scg-jax reproduce``); installed as ``scg_experiments``.

Each result is a module with ``NAME``, ``TITLE``, ``PROFILES`` and ``run(ctx) -> Section`` (see ``common``);
``RESULTS`` lists them in the paper's order and ``reproduce`` runs some or all of them and writes ``report.md``.
"""

from __future__ import annotations

import platform
import time
from collections.abc import Sequence
from pathlib import Path

# name -> module, in the paper's order.
RESULTS = {
    name: f"scg_experiments.{name}"
    for name in ("control_performance", "learning_efficiency", "constraint_satisfaction", "robustness", "throughput")
}


def result_module(name: str):
    """The module of the result ``name``; ``ValueError`` naming the allowed names otherwise."""
    from scg_algorithms.registry import lookup

    return lookup(RESULTS, name, "result")


# Results that time the machine run alone, after the others (parallel processes would share its cores).
EXCLUSIVE = ("throughput",)
# The order results are handed to parallel processes: the longest first, so the others fill the remaining processes.
LONGEST_FIRST = ("robustness", "constraint_satisfaction", "learning_efficiency", "control_performance")


def reproduce(names: Sequence[str], out, profile: str = "quick", seeds: int = 1, progress=None, jobs: int = 1) -> list:
    """Run the results ``names`` (all when empty) with ``profile`` and seeds ``0..seeds-1`` into ``out``.

    Writes ``out/<name>/`` (data, PNG) per result, ``out/cache/`` (trained policies, GPs, curves; reused by a rerun),
    ``out/run.json`` (this run's wall time and cache hits) and ``out/report.md`` (the sections of every result run so
    far in ``out``, whole or not at all, rewritten as each result ends). With ``jobs`` > 1 the results run in up to
    ``jobs`` processes (``spawn``), the longest first, and those in ``EXCLUSIVE`` alone afterwards; processes that
    need the same cached artefact wait for the one making it (``common.cached``). Reports through ``progress`` (a
    ``scg_algorithms.progress.Progress``; None: silent): a note per result as it starts and ends, and what its
    training and steps report (from other processes, their notes, prefixed with the result's name). Returns the
    ``Section``s of this run, in the order of ``names``.
    """
    from scg_algorithms.progress import as_progress
    from scg_experiments import common

    if profile not in common.PROFILES:
        raise ValueError(f"profile: unknown {profile!r}; allowed values are {', '.join(common.PROFILES)}")
    if isinstance(seeds, bool) or int(seeds) != seeds or seeds < 1:
        raise ValueError(f"seeds: must be a positive integer, got {seeds!r}")
    if isinstance(jobs, bool) or int(jobs) != jobs or jobs < 1:
        raise ValueError(f"jobs: must be a positive integer, got {jobs!r}")
    names = list(names) or list(RESULTS)
    for name in names:
        result_module(name)  # every name checked before any work
    progress = as_progress(progress)
    out = Path(out)
    run = {"profile": profile, "seeds": int(seeds), "jobs": int(jobs), "results": names, "done": [],
           "cache_entries_at_start": cache_entries(out / "cache"), "cache_hits": 0, "cache_misses": 0, "wall_s": 0.0,
           "finished": False}  # fmt: skip
    start = time.perf_counter()
    sections = {}

    def finish(section, stats) -> None:
        sections[section.name] = section
        run["done"].append(section.name)
        run["cache_hits"] += stats["cache_hits"]
        run["cache_misses"] += stats["cache_misses"]
        run["wall_s"] = time.perf_counter() - start
        _write_report(out, profile, seeds, run)

    shared = [name for name in names if name not in EXCLUSIVE]
    if jobs > 1 and len(shared) > 1:
        shared.sort(key=lambda n: LONGEST_FIRST.index(n) if n in LONGEST_FIRST else len(LONGEST_FIRST))
        for section, stats in _run_parallel(shared, out, profile, int(seeds), progress, int(jobs)):
            finish(section, stats)
        alone = [name for name in names if name in EXCLUSIVE]
    else:
        alone = names
    for name in alone:
        finish(*run_result(name, out, profile, int(seeds), progress))
    run["finished"] = True
    run["wall_s"] = time.perf_counter() - start
    common.write_data(out / "run.json", run)
    _write_report(out, profile, seeds, run)
    return [sections[name] for name in names]


def run_result(name: str, out, profile: str, seeds: int, progress=None):
    """Run the result ``name`` into ``out/<name>/`` (its data, ``section.json``, ``section.md``); a result that raises
    gets a section saying so. Returns ``(Section, cache stats)``; importable, so a ``spawn`` process can run it."""
    from scg_algorithms.progress import as_progress
    from scg_experiments import common
    from scg_jax.files import write_atomic

    progress = as_progress(progress)
    module = result_module(name)
    out = Path(out)
    ctx = common.Context(out / name, out / "cache", profile, tuple(range(int(seeds))), progress)
    ctx.out.mkdir(parents=True, exist_ok=True)
    progress.note(f"== {module.TITLE} [{profile}] ==")
    start = time.perf_counter()
    try:
        section = module.run(ctx)
    except Exception as error:  # one broken result is reported in the report; the others still run
        section = common.Section(name, module.TITLE)
        text = common.failure_text(error)
        section.claims = [common.Claim(f"the result {name} ran", common.NOT_MEASURED, f"not measured: {text}")]
        section.notes.append(f"{name} stopped with {text}; nothing of it was measured")
        progress.note(f"{name} failed: {text}")
    section.wall_s = time.perf_counter() - start
    common.write_data(ctx.out / "section.json", {"markdown": section.markdown(), "wall_s": section.wall_s,
                                                 "claims": [c.__dict__ for c in section.claims],
                                                 "stats": ctx.stats})  # fmt: skip
    write_atomic(ctx.out / "section.md", lambda f, s=section: f.write(s.markdown().encode()))
    progress.note(f"{name}: {section.wall_s:.1f} s; " + ", ".join(f"{c.verdict}" for c in section.claims))
    return section, dict(ctx.stats)


def _child_result(name: str, out: str, profile: str, seeds: int, queue):
    """``run_result`` in a worker process, its notes sent to ``queue`` prefixed with the result's name."""
    from scg_algorithms.progress import Progress

    return run_result(name, out, profile, seeds, Progress(note=lambda text: queue.put(f"[{name}] {text}")))


def _run_parallel(names: list, out: Path, profile: str, seeds: int, progress, jobs: int):
    """``run_result`` of each of ``names`` in up to ``jobs`` spawned processes; yields ``(Section, stats)`` as each
    ends, while a thread forwards the processes' notes to ``progress.note``."""
    import concurrent.futures
    import multiprocessing
    import threading

    context = multiprocessing.get_context("spawn")  # fork would copy this process's JAX threads
    with context.Manager() as manager:
        queue = manager.Queue()

        def forward():
            while (text := queue.get()) is not None:
                progress.note(text)

        forwarder = threading.Thread(target=forward, daemon=True)
        forwarder.start()
        try:
            with concurrent.futures.ProcessPoolExecutor(min(jobs, len(names)), mp_context=context) as pool:
                futures = [pool.submit(_child_result, name, str(out), profile, seeds, queue) for name in names]
                for future in concurrent.futures.as_completed(futures):
                    yield future.result()
        finally:
            queue.put(None)
            forwarder.join()


def _write_report(out: Path, profile: str, seeds: int, run: dict | None = None) -> None:
    """``report.md``: a header with the machine, this run's wall time and cache hits, a claims summary and every
    result's section found in ``out``."""
    import json

    import jax

    from scg_jax.files import write_atomic

    parts, summary = [], []
    for name in RESULTS:
        path = out / name / "section.json"
        if path.is_file():
            data = json.loads(path.read_text())
            parts.append(data["markdown"])
            summary += [(name, c) for c in data["claims"]]
    counts = {}
    for _, c in summary:
        counts[c["verdict"]] = counts.get(c["verdict"], 0) + 1
    header = [
        "# scg-jax reproduction of the safe-control-gym paper's results",
        "",
        f"Profile `{profile}`, {seeds} seed(s); machine: {platform.platform()}, {jax.devices()[0].platform} "
        f"({len(jax.devices())} device(s)), Python {platform.python_version()}, jax {jax.__version__}; written "
        f"{time.strftime('%Y-%m-%d %H:%M:%S UTC', time.gmtime())}.",
        "",
    ]
    if run is not None:
        header += [run_line(run), ""]
    header += ["Claims: " + ", ".join(f"{n} {v}" for v, n in sorted(counts.items())), ""]
    text = "\n".join(header) + "\n" + "\n".join(parts)
    write_atomic(out / "report.md", lambda f: f.write(text.encode()))


def cache_entries(cache: Path) -> int:
    """Complete or partial entries (folders) in the cache folder ``cache``; 0 when it does not exist."""
    return sum(1 for path in cache.iterdir() if path.is_dir()) if cache.is_dir() else 0


def run_line(run: dict) -> str:
    """The report's line about the run that wrote it: wall time, processes, cache use. A cold run starts with no
    cache entry; its hits are entries one result made and another one used (a shared policy or GP)."""
    hits, made, before = run["cache_hits"], run["cache_misses"], run["cache_entries_at_start"]
    state = "" if run["finished"] else f" (running: {len(run['done'])} of {len(run['results'])} results done)"
    cold = "a cold run" if before == 0 else "not a cold run"
    return (
        f"This run: {', '.join(run['results'])} in {run['jobs']} process(es); wall time {run['wall_s']:.0f} s from "
        f"the start to this report{state}; cache: {before} entr{'y' if before == 1 else 'ies'} at the start "
        f"({cold}), {hits} hit(s), {made} entr{'y' if made == 1 else 'ies'} made."
    )
