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


def reproduce(names: Sequence[str], out, profile: str = "quick", seeds: int = 1, progress=None) -> list:
    """Run the results ``names`` (all when empty) with ``profile`` and seeds ``0..seeds-1`` into ``out``.

    Writes ``out/<name>/`` (data, PNG) per result, ``out/cache/`` (trained policies, GPs, curves; reused by a rerun)
    and ``out/report.md`` (the sections of every result run so far in ``out``, whole or not at all). Reports through
    ``progress`` (a ``scg_algorithms.progress.Progress``; None: silent): a note per result as it starts and ends,
    and what its training and steps report. Returns the ``Section``s of this run.
    """
    from scg_algorithms.progress import as_progress
    from scg_experiments import common
    from scg_jax.files import write_atomic

    if profile not in common.PROFILES:
        raise ValueError(f"profile: unknown {profile!r}; allowed values are {', '.join(common.PROFILES)}")
    if isinstance(seeds, bool) or int(seeds) != seeds or seeds < 1:
        raise ValueError(f"seeds: must be a positive integer, got {seeds!r}")
    names = list(names) or list(RESULTS)
    modules = [result_module(name) for name in names]  # every name checked before any work
    progress = as_progress(progress)
    out = Path(out)
    sections = []
    for name, module in zip(names, modules, strict=True):
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
                                                     "claims": [c.__dict__ for c in section.claims]})  # fmt: skip
        write_atomic(ctx.out / "section.md", lambda f, s=section: f.write(s.markdown().encode()))
        progress.note(f"{name}: {section.wall_s:.1f} s; " + ", ".join(f"{c.verdict}" for c in section.claims))
        sections.append(section)
        _write_report(out, profile, seeds)
    return sections


def _write_report(out: Path, profile: str, seeds: int) -> None:
    """``report.md``: a header with the machine, a claims summary and every result's section found in ``out``."""
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
        "Claims: " + ", ".join(f"{n} {v}" for v, n in sorted(counts.items())),
        "",
    ]
    text = "\n".join(header) + "\n" + "\n".join(parts)
    write_atomic(out / "report.md", lambda f: f.write(text.encode()))
