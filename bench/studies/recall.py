"""Heading and pose recall of a bench run, from its ``merge.json`` alone (no rerun).

For every overlapping pair (negatives have nothing to find):

*heading recall*: is the true heading within ``--tolerance`` degrees (2 by
default, the success bound) of any heading that went through pgvd's matching
stages?  The searched headings are the ``searched_deg`` of each pgvd record
(:mod:`bench.capture`).

*pose recall*: is one of the finalists that reached the decision, after its
refinement, within the success bounds of the truth (``finalist_success`` of
each record)?  A pair that fails with its pose found was lost by the decision;
one that fails without it, by the search.

*heading sigma*: for the searched heading nearest the truth (within
:data:`SAME_MODE_DEG`: the right peak, not a look-alike), ``z = error / sigma``
with the candidate's sigma (the square root of its variance, which blurs B
before its PGVD, eq. (8)).  A sigma that matches the error gives a mean ``z^2``
of 1, a median of 0.45 and 95 % within 2 sigma.

*returned pose right*: is the pose the method returns, accepted or not, within
the success bounds?  Any method has it, so it compares pgvd's search with the
``exhaustive`` reference's (every heading at 1 degree): a pair whose best
whole-pose score is not the truth is lost to the evidence, not to the search.

Printed per set and per source, with the heading misses listed (methods that
record no searched headings or finalists get the first two columns only).

    python3 -m bench recall [bench/results/merge.json] [--method pgvd] [--tolerance 2]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from bench.merge import RESULTS
from bench.tables import MAX_HEADING_DEG, frac, pose_right


def angle_gap(a_deg: float, b_deg: float) -> float:
    """Smallest absolute difference of two headings, degrees."""
    return abs((a_deg - b_deg + 180.0) % 360.0 - 180.0)


def nearest_gap(record: dict) -> float | None:
    """Degrees from the true heading to the nearest searched heading (None if unknown)."""
    searched = record.get("searched_deg")
    truth = record.get("truth_heading_deg")
    if truth is None or not searched:
        return None
    return min(angle_gap(truth, s) for s in searched)


#: A searched heading this close to the truth is the true heading's peak, however biased.
SAME_MODE_DEG = 10.0


def heading_z(record: dict) -> float | None:
    """Error / sigma of the searched heading nearest the truth (None if unknown or too far)."""
    searched, sigmas = record.get("searched_deg"), record.get("searched_sigma_deg")
    truth = record.get("truth_heading_deg")
    if truth is None or not searched or not sigmas:
        return None
    gaps = [angle_gap(truth, s) for s in searched]
    i = int(np.argmin(gaps))
    return gaps[i] / sigmas[i] if gaps[i] <= SAME_MODE_DEG and sigmas[i] > 0 else None


def sigma_line(records: list[dict]) -> str:
    """How well the candidates' heading sigma matches their error, one line."""
    z = np.array([v for v in map(heading_z, records) if v is not None])
    if z.size == 0:
        return "heading sigma: not recorded"
    return (
        f"heading sigma over {z.size} pairs: mean z^2 {np.mean(z**2):.2f} (1 if calibrated), "
        f"median z^2 {np.median(z**2):.2f} (0.45), within 2 sigma {np.mean(z <= 2):.0%} (95 %)"
    )


def recall(records: list[dict], tolerance: float) -> dict:
    """Hits, pairs and the misses of one group of records."""
    gaps = [(r, nearest_gap(r)) for r in records]
    gaps = [(r, g) for r, g in gaps if g is not None]
    misses = [(r["pair"], round(g, 2)) for r, g in gaps if g > tolerance]
    return {"hits": len(gaps) - len(misses), "pairs": len(gaps), "misses": misses}


def pose_recall(records: list[dict]) -> tuple[int, int, int]:
    """Pairs whose pose was found, pairs that record finalists, and pairs lost by the decision.

    Found: a finalist is within the success bounds, or the pair is a success (the
    winner's final refinement, on every wall cell, can reach the truth from a
    finalist just outside).  Lost: found but not a success.
    """
    known = [r for r in records if r.get("finalist_success") is not None]
    found = [r for r in known if r["success"] or any(r["finalist_success"])]
    return len(found), len(known), sum(not r["success"] for r in found)


def table(records: list[dict], tolerance: float) -> list[str]:
    """Markdown rows: heading and pose recall per set and per source."""
    lines = [
        "| group | success | returned pose right | pose recall | lost by the decision "
        "| heading recall | heading misses (pair: degrees to the nearest searched heading) |"
    ]
    lines.append("|---|---|---|---|---|---|---|")
    groups = [("set", s) for s in sorted({r["set"] for r in records})]
    groups += [("source", s) for s in sorted({r["source"] for r in records})]
    for key, value in [*groups, ("all", None)]:
        mine = records if value is None else [r for r in records if r[key] == value]
        if not mine:
            continue
        got = recall(mine, tolerance)
        found, known, lost = pose_recall(mine)
        success = frac(sum(r["success"] for r in mine), len(mine), 1)
        right = frac(sum(map(pose_right, mine)), len(mine), 1)
        miss = ", ".join(f"{p}: {g}" for p, g in got["misses"]) or "-"
        lines.append(
            f"| {value or '**all**'} | {success} | {right} | {frac(found, known, 1)} "
            f"| {lost if known else '-'} | {frac(got['hits'], got['pairs'], 1)} | {miss} |"
        )
    return lines


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("json", nargs="?", type=Path, default=RESULTS / "merge.json")
    parser.add_argument("--method", default="pgvd")
    parser.add_argument("--tolerance", type=float, default=MAX_HEADING_DEG, help="degrees")
    args = parser.parse_args(argv)
    doc = json.loads(args.json.read_text())
    records = [r for r in doc["records"] if r["method"] == args.method and r["overlap"] > 0]
    if not records:
        print(f"{args.json}: no overlapping pair recorded for {args.method}")
        return 1
    command = "python3 -m bench recall " + " ".join(argv if argv is not None else sys.argv[1:])
    print(f"# Heading (within {args.tolerance} deg) and pose recall ({args.method})\n")
    print(f"`{command.strip()}`\n")
    print("\n".join(table(records, args.tolerance)))
    gaps = [g for g in map(nearest_gap, records) if g is not None]
    if gaps:
        print(f"\nmedian gap {np.median(gaps):.2f} deg, max {np.max(gaps):.2f} deg")
        print(sigma_line(records))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
