"""What a perfect rotation stage would buy: the heading misses merged again with the true heading.

Of a bench run's overlapping pairs, those whose searched headings all miss the
truth by more than the success bound (:func:`bench.recall.nearest_gap`) are
merged again, with the exact true heading added to the Radon candidates of
eq. (10) (:func:`pgvd.rotation.estimate_headings`), everything else as the
merge has it.  The outcome bounds what any better heading stage can gain on
these pairs, and shows what the rest of the merge does with a right heading:
a pair that still fails is lost by the translation search or the decision.

    python3 -m bench.oracle [bench/results/merge.json] [--out bench/results/oracle.md]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from unittest import mock

import numpy as np

from bench.merge import CACHE, MAX_HEADING_DEG, RESULTS, evaluate
from bench.recall import nearest_gap
from bench.sets import FULL, build
from pgvd.grid import heading
from pgvd.merge import MergeParams, merge
from pgvd.rotation import HeadingCandidate, estimate_headings

#: The module whose name ``estimate_headings`` the merge calls (``pgvd.merge`` the name is
#: the function re-exported by the package).
_MERGE_MODULE = sys.modules[merge.__module__]


def with_truth(psi: float):
    """``estimate_headings`` with the true heading ``psi`` (radians) added last."""

    def estimate(a: np.ndarray, b: np.ndarray, max_candidates: int) -> list[HeadingCandidate]:
        found = estimate_headings(a, b, max_candidates)
        return [*found, HeadingCandidate(psi, found[0].variance, found[0].score)]

    return estimate


def rerun(records: list[dict], cache: Path, seed: int) -> list[dict]:
    """The heading misses of ``records`` merged with the true heading added."""
    misses = {
        r["pair"]: r
        for r in records
        if r["set"] != "negative" and (nearest_gap(r) or 0.0) > MAX_HEADING_DEG
    }
    out = []
    for entry in build(FULL, seed, cache):
        rec = misses.get(entry.pair.name)
        if rec is None:
            continue
        pair = entry.pair
        with mock.patch.object(_MERGE_MODULE, "estimate_headings", with_truth(heading(pair.truth))):
            result = merge(pair.a, pair.b, MergeParams(diagnostics=False))
        row = evaluate(pair, result.accepted, result.matrix)
        row.update(pair=pair.name, set=entry.set, gap=nearest_gap(rec), margin=result.margin)
        mark = "ok" if row["success"] else "ACC" if row["accepted"] else "rej"
        print(f"[oracle] {pair.name}: {mark} margin {result.margin:.2f}", flush=True)
        out.append(row)
    return out


def markdown(rows: list[dict], command: str) -> str:
    """The report: per set, then every pair."""
    lines = [
        "# The heading misses with the true heading searched",
        "",
        f"`{command}`",
        "",
        "| set | heading misses | right with the true heading | accepted at a wrong pose |",
        "|---|---|---|---|",
    ]
    for s in sorted({r["set"] for r in rows}):
        group = [r for r in rows if r["set"] == s]
        right = sum(r["success"] for r in group)
        wrong = sum(r["accepted"] and not r["success"] for r in group)
        lines.append(f"| {s} | {len(group)} | {right} | {wrong} |")
    lines += ["", "| pair | degrees to the nearest searched heading | outcome | margin |"]
    lines.append("|---|---|---|---|")
    for r in rows:
        outcome = "right" if r["success"] else "accepted, wrong" if r["accepted"] else "rejected"
        if r["accepted"] and not r["success"]:
            outcome += (
                f" ({r['heading_deg']:.2f} deg, {r['cell_err']:.1f} cells,"
                f" tolerance {r['cell_tolerance']:.1f})"
            )
        lines.append(f"| {r['pair']} | {r['gap']:.1f} | {outcome} | {r['margin']:.2f} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("json", nargs="?", type=Path, default=RESULTS / "merge.json")
    parser.add_argument("--method", default="pgvd", help="records of this bench method")
    parser.add_argument("--seed", type=int, default=1, help="seed of the run's pairs")
    parser.add_argument("--cache", type=Path, default=CACHE)
    parser.add_argument("--out", type=Path, default=RESULTS / "oracle.md")
    args = parser.parse_args(argv)
    try:
        records = json.loads(args.json.read_text())["records"]
    except (OSError, ValueError, KeyError) as exc:
        parser.error(f"cannot read bench records from {args.json}: {exc}")
    records = [r for r in records if r["method"] == args.method]
    rows = rerun(records, args.cache, args.seed)
    command = "python3 -m bench.oracle " + " ".join(argv if argv is not None else sys.argv[1:])
    args.out.write_text(markdown(rows, command.strip()))
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
