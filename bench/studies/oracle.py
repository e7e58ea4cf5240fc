"""What a perfect stage would buy: failed pairs merged again with the truth handed to one stage.

Two stages, one at a time, everything else as the merge has it:

``--stage heading``: the overlapping pairs whose searched headings all miss the
truth by more than the success bound (:func:`bench.studies.recall.nearest_gap`), with
the exact true heading added to the Radon candidates of eq. (10)
(:func:`pgvd.rotation.estimate_headings`).  It bounds what any better heading
stage can gain on them.

``--stage finalist``: the pairs whose true heading was searched but whose true
pose never reached the decision (no finalist within the success bounds), with
the supported coarse hypothesis nearest the truth added to the finalists.  It
tells apart a true translation that the search never proposed (the nearest
hypothesis is far) from one that the finalists' ranking left out, and shows
whether the decision would accept it.

Both wrap private functions of :mod:`pgvd.merge` for one merge, as
:mod:`bench.capture` does.

    python3 -m bench oracle [bench/results/merge.json] [--stage heading|finalist] [--out FILE]
"""

from __future__ import annotations

import argparse
import contextlib
import json
import sys
from collections.abc import Callable, Iterator
from pathlib import Path
from unittest import mock

import numpy as np

from bench.data.pairs import MapPair
from bench.data.sets import FULL, build
from bench.merge import CACHE, RESULTS, evaluate
from bench.studies.recall import nearest_gap
from bench.tables import MAX_HEADING_DEG, mark
from pgvd.grid import heading
from pgvd.merge import merge
from pgvd.params import MergeParams
from pgvd.pooling import block_scale, decision_pool, from_pooled
from pgvd.rotation import HeadingCandidate, estimate_headings

#: The module of the merge (``pgvd.merge`` the name is the function the package exports).
_MERGE_MODULE = sys.modules[merge.__module__]


def with_truth(psi: float) -> Callable[..., list[HeadingCandidate]]:
    """``estimate_headings`` with the true heading ``psi`` (radians) added last."""

    def estimate(a: np.ndarray, b: np.ndarray, max_candidates: int) -> list[HeadingCandidate]:
        found = estimate_headings(a, b, max_candidates)
        return [*found, HeadingCandidate(psi, found[0].variance, found[0].score)]

    return estimate


@contextlib.contextmanager
def true_heading(pair: MapPair, seen: dict) -> Iterator[None]:
    """The merge's Radon candidates with ``pair``'s true heading added."""
    with mock.patch.object(_MERGE_MODULE, "estimate_headings", with_truth(heading(pair.truth))):
        yield


@contextlib.contextmanager
def true_finalist(pair: MapPair, seen: dict) -> Iterator[None]:
    """The merge's finalists with the supported coarse hypothesis nearest the truth added.

    ``seen`` gets ``coarse_err`` (that hypothesis' mean cell error, in coarse
    cells) and ``was_finalist``.
    """
    pick, decide = _MERGE_MODULE.choose_finalists, _MERGE_MODULE.decide_hypotheses
    supported: list = []

    def finalists(good: list, params: MergeParams) -> list:
        supported[:] = good
        return pick(good, params)

    def decide_with_truth(chosen: list, fine_a, fine_b, to_fine, k, params, res):
        # the decision's frame is the maps pooled for it; k is the coarse cell in its cells
        pool = decision_pool(pair.a.resolution)

        def error(h) -> float:
            pooled = to_fine @ h.coarse_matrix @ np.linalg.inv(block_scale(k))
            return evaluate(pair, True, from_pooled(pooled, pool))["cell_err"] / (k * pool)

        nearest = min(supported, key=error)
        seen.update(coarse_err=error(nearest), was_finalist=any(h is nearest for h in chosen))
        if not seen["was_finalist"]:
            chosen = [*chosen, nearest]
        return decide(chosen, fine_a, fine_b, to_fine, k, params, res)

    with (
        mock.patch.object(_MERGE_MODULE, "choose_finalists", finalists),
        mock.patch.object(_MERGE_MODULE, "decide_hypotheses", decide_with_truth),
    ):
        yield


def heading_misses(record: dict) -> bool:
    """An overlapping pair none of whose searched headings is within the success bound."""
    return record["set"] != "negative" and (nearest_gap(record) or 0.0) > MAX_HEADING_DEG


def search_misses(record: dict) -> bool:
    """A failed overlapping pair whose true heading was searched but whose pose was not found."""
    gap = nearest_gap(record)
    return (
        record["set"] != "negative"
        and not record["success"]
        and gap is not None
        and gap <= MAX_HEADING_DEG
        and not any(record.get("finalist_success") or [])
    )


STAGES = {"heading": (heading_misses, true_heading), "finalist": (search_misses, true_finalist)}


def rerun(records: list[dict], stage: str, cache: Path, seed: int) -> list[dict]:
    """The pairs of ``records`` that ``stage`` selects, merged with its truth handed in."""
    selects, oracle = STAGES[stage]
    chosen = {r["pair"]: r for r in records if selects(r)}
    out = []
    for entry in build(FULL, seed, cache):
        rec = chosen.get(entry.pair.name)
        if rec is None:
            continue
        pair, seen = entry.pair, {}
        with oracle(pair, seen):
            result = merge(pair.a, pair.b, MergeParams(diagnostics=False))
        row = evaluate(pair, result.accepted, result.matrix)
        row.update(
            seen,
            pair=pair.name,
            set=entry.set,
            gap=nearest_gap(rec),
            margin=result.margin,
            before=bool(rec["success"]),
        )
        outcome = mark(row["success"], row["accepted"])
        print(f"[oracle] {pair.name}: {outcome} margin {result.margin:.2f}", flush=True)
        out.append(row)
    return out


def _outcome(row: dict) -> str:
    if row["success"]:
        return "right"
    if not row["accepted"]:
        return "rejected"
    return (
        f"accepted, wrong ({row['heading_deg']:.2f} deg, {row['cell_err']:.1f} cells,"
        f" tolerance {row['cell_tolerance']:.1f})"
    )


#: How far (coarse cells) the nearest supported hypothesis may be from the truth and still
#: refine to it (the finalists' ICP starts at a 12-cell radius at full resolution).
PROPOSED_CELLS = 3.0


def markdown(rows: list[dict], stage: str, command: str) -> str:
    """The report: per set, then every pair."""
    finalist = stage == "finalist"
    title = {
        "heading": "The heading misses with the true heading searched",
        "finalist": "The search misses with the nearest hypothesis to the truth as a finalist",
    }[stage]
    head = (
        "| set | pairs | right in the run | right with the truth handed in "
        "| of them new | accepted at a wrong pose |"
    )
    extra = " true translation proposed |" if finalist else ""
    lines = [f"# {title}", "", f"`{command}`", "", head + extra]
    lines.append("|---" * (6 + finalist) + "|")
    for s in sorted({r["set"] for r in rows}):
        group = [r for r in rows if r["set"] == s]
        before = sum(r["before"] for r in group)
        right = sum(r["success"] for r in group)
        new = sum(r["success"] and not r["before"] for r in group)
        wrong = sum(r["accepted"] and not r["success"] for r in group)
        cells = f" {sum(r['coarse_err'] <= PROPOSED_CELLS for r in group)} |" if finalist else ""
        lines.append(f"| {s} | {len(group)} | {before} | {right} | {new} | {wrong} |{cells}")
    lines.append("")
    if finalist:
        lines += [
            "| pair | nearest supported hypothesis (coarse cells) | was a finalist | outcome "
            "| margin |",
            "|---|---|---|---|---|",
        ]
        lines += [
            f"| {r['pair']} | {r['coarse_err']:.1f} | {'yes' if r['was_finalist'] else 'no'} "
            f"| {_outcome(r)} | {r['margin']:.2f} |"
            for r in rows
        ]
    else:
        lines += ["| pair | degrees to the nearest searched heading | outcome | margin |"]
        lines.append("|---|---|---|---|")
        lines += [
            f"| {r['pair']} | {r['gap']:.1f} | {_outcome(r)} | {r['margin']:.2f} |" for r in rows
        ]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("json", nargs="?", type=Path, default=RESULTS / "merge.json")
    parser.add_argument("--stage", choices=sorted(STAGES), default="heading")
    parser.add_argument("--method", default="pgvd", help="records of this bench method")
    parser.add_argument("--seed", type=int, default=1, help="seed of the run's pairs")
    parser.add_argument("--cache", type=Path, default=CACHE)
    parser.add_argument("--out", type=Path, help="default: bench/results/oracle-STAGE.md")
    args = parser.parse_args(argv)
    try:
        records = json.loads(args.json.read_text())["records"]
    except (OSError, ValueError, KeyError) as exc:
        parser.error(f"cannot read bench records from {args.json}: {exc}")
    records = [r for r in records if r["method"] == args.method]
    out = args.out or RESULTS / f"oracle-{args.stage}.md"
    out.parent.mkdir(parents=True, exist_ok=True)
    rows = rerun(records, args.stage, args.cache, args.seed)
    command = "python3 -m bench oracle " + " ".join(argv if argv is not None else sys.argv[1:])
    out.write_text(markdown(rows, args.stage, command.strip()))
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
