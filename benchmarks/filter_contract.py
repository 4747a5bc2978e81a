"""The safety filters' contract, measured: systems x constraints x filters (``scg_algorithms.safety_filters.contract``).

For each case (a config with a state constraint added) LQR runs alone and behind each filter with its defaults on the
same episodes; a filter either refuses when it is built (its message is the cell) or is scored by its violating
steps per episode and its RMSE next to LQR's. The contract: at most 10 % of LQR's violating steps at most 1.5x its
RMSE.

Writes ``benchmarks/results/filter_contract.json`` (merged per case and filter, so ``--filters``/``--cases`` add to
an earlier run) and ``docs/benchmarks/filter_contract.md``. The nonlinear MPSC runs IPOPT per copy and step on the
host: give it fewer episodes (``--host-episodes``). Run ``python benchmarks/filter_contract.py --help``.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from machine import run_record, write_markdown_table  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
DEFAULT_JSON = ROOT / "benchmarks" / "results" / "filter_contract.json"
DEFAULT_MD = ROOT / "docs" / "benchmarks" / "filter_contract.md"
HOST_FILTERS = ("nonlinear_mpsc",)


def main(argv=None) -> int:
    from scg_algorithms.safety_filters import contract as C

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--episodes", type=int, default=16, help="episodes per JAX filter and for LQR (default 16)")
    parser.add_argument("--host-episodes", type=int, default=4, help="episodes per host filter (default 4)")
    parser.add_argument("--filters", nargs="+", default=list(C.FILTER_NAMES), choices=C.FILTER_NAMES)
    parser.add_argument("--cases", nargs="+", type=int, help="indices into CASES (default: all)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--merge", nargs="+", type=Path, default=[], help="JSONs of other runs to merge in first")
    parser.add_argument("--render-only", action="store_true", help="run nothing: merge and write the page")
    parser.add_argument("--json", type=Path, default=DEFAULT_JSON)
    parser.add_argument("--md", type=Path, default=DEFAULT_MD)
    args = parser.parse_args(argv)

    record = run_record("filter_contract")
    previous = json.loads(args.json.read_text()) if args.json.exists() else {}
    labels = {case.label for case in C.CASES}  # rows of cases no longer in CASES are dropped
    outcomes = [r for path in args.merge for r in json.loads(path.read_text())["outcomes"]]
    rows = {(r["case"], r["filter"]): r for r in [*previous.get("outcomes", []), *outcomes] if r["case"] in labels}
    cases = [] if args.render_only else (args.cases if args.cases is not None else range(len(C.CASES)))
    for index in cases:
        case = C.CASES[index]
        env, params = case.make()
        for name in args.filters:
            episodes = args.host_episodes if name in HOST_FILTERS else args.episodes
            # LQR on the same episodes as the filter (same key and count: the same initial states and plants).
            controller, baseline = C.lqr_baseline(env, params, episodes, args.seed)
            outcome = C.run_filter(case, name, env, params, controller, baseline, episodes, args.seed)
            rows[(case.label, name)] = {**C.outcome_row(outcome), "episodes": episodes}
            print(json.dumps(rows[(case.label, name)]), flush=True)
    order = {case.label: i for i, case in enumerate(C.CASES)}
    outcomes = sorted(rows.values(), key=lambda r: (order.get(r["case"], 99), C.FILTER_NAMES.index(r["filter"])))
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps({**record, "outcomes": outcomes}, indent=1) + "\n")
    write_markdown_table(args.md, "Safety filters: the contract over systems and constraints", record, *table(outcomes))
    return 0


def table(outcomes) -> tuple[list[str], list[list], str]:
    """The columns, rows and notes of the page from the JSON outcomes."""
    columns = [
        "system and constraint", "filter", "episodes", "LQR violating steps", "filtered", "share", "LQR RMSE",
        "filtered RMSE", "ratio", "infeasible steps", "contract",
    ]  # fmt: skip
    rows = []
    for r in outcomes:
        r = {**r, "case": r["case"].replace("|", "\\|")}  # a bound |x| inside a Markdown table cell
        if r["refusal"] is not None:
            cells = ["refused: " + r["refusal"].replace("|", "\\|"), "", "", "", "", "", ""]
            rows.append([r["case"], r["filter"], r["episodes"], f"{r['lqr_violations']:.1f}", *cells])
            continue
        rows.append([
            r["case"], r["filter"], r["episodes"], f"{r['lqr_violations']:.1f}", f"{r['violations']:.2f}",
            f"{100 * r['violation_share']:.1f} %", f"{r['lqr_rmse']:.3f}", f"{r['rmse']:.3f}",
            f"{r['rmse_ratio']:.2f}x",
            f"{100 * r['infeasible_fraction']:.1f} %", "holds" if r["holds"] else "fails",
        ])  # fmt: skip
    notes = (
        "Violating steps: steps per episode with the configured constraint violated; share: filtered / LQR's "
        "(contract: at most 10 %); ratio: filtered RMSE / LQR's (contract: at most 1.5x); infeasible steps: the "
        "filter's problem had no certified solution and its fallback was applied. LQR and the filter run the same "
        "episodes (same key). Each filter with its defaults, as `scg-jax eval --controller lqr --filter NAME` builds "
        "it; the cases are `scg_algorithms.safety_filters.contract.CASES`. Rows merge over several runs (seed 0); the "
        "machine line is the last run's."
    )
    return columns, rows, notes


if __name__ == "__main__":
    sys.exit(main())
