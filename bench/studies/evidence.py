"""What the maps say at the true pose, against the wrong poses that reached the decision.

For every overlapping pair of a merge-bench run that failed, the true pose and
every wrong finalist are counted as the decision counts hypotheses
(:func:`pgvd.scoring.score_hypothesis`: walls on walls ``agree``, walls on clear
free space ``disagree``, both ways, each few-metre square re-aligned first), and
the pair is put in one class:

``margin``     the returned pose is right, but it did not stand out (rejected);
``search``     with the truth among the finalists, the decision
               (:func:`pgvd.scoring.decide_finalists`: rivals, probes and the last
               refinement included) picks it, returns a right pose and accepts it:
               the search lost it;
``faint``      the decision picks the truth and returns a right pose, but it does not
               stand out (margin below the threshold);
``refinement`` the decision picks the truth, but its last refinement leaves the
               success bounds;
``weighting``  a wrong finalist's evidence beats the truth's, but none of them
               agrees as much *and* conflicts as little: another weight ``w`` of a
               conflict would prefer the truth on this pair;
``dominated``  a wrong finalist agrees at least as much and conflicts no more: no
               weighting of the two counts prefers the truth.

Over every overlapping pair, failed or not, the report also counts those whose
exact truth the merge's last refinement (:func:`pgvd.refinement.final_refinement`)
moves out of the success bounds: where the two maps' best fit is not the truth
within the bounds, no search or decision can succeed.

Pairs rejected before the decision (no supported translation) have no finalists:
the truth is weighed against its probes alone.  The truth handed in is the
exact one and, when it stays within the success bounds, the same after a short
ICP (3 and 2 cells): the better of the two by evidence.  It tells
whether the remaining failures need a better search, a better decision, or
evidence the two maps do not hold.

    python3 -m bench evidence [bench/results/merge.json] [--set low] [--out FILE]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from bench.data.pairs import MapPair
from bench.data.sets import FULL, build
from bench.merge import CACHE, RESULTS, evaluate
from bench.studies.redecide import decision_maps
from pgvd.alignment import refine
from pgvd.overlay import Agreement
from pgvd.params import MergeParams
from pgvd.pooling import decision_pool, from_pooled, to_pooled
from pgvd.refinement import final_refinement
from pgvd.sampling import subsample
from pgvd.scoring import decide_finalists, score_hypothesis
from pgvd.walls import WallMap

CLASSES = ("margin", "search", "faint", "refinement", "weighting", "dominated")
SETS = ("standard", "low", "drifted")


def classify(
    truth: Agreement,
    wrong: list[Agreement],
    returned_right: bool,
    outcome: tuple[bool, float] | None,
    threshold: float,
) -> str:
    """The class of a failed pair (module docstring).

    Parameters
    ----------
    truth : Agreement
        Counts at the true pose.
    wrong : list of Agreement
        Counts at each finalist outside the success bounds.
    returned_right : bool
        Whether the pose the merge returned is within the success bounds.
    outcome : tuple of (bool, float) or None
        When the decision, handed the truth among the finalists, picks it: whether the
        pose it returns is right, and its margin; None when it picks another pose.
    threshold : float
        The decision's acceptance threshold (``MergeParams.min_margin``).

    Returns
    -------
    str
        One of :data:`CLASSES`.
    """
    if returned_right:
        return "margin"
    if outcome is not None:
        right, margin = outcome
        if not right:
            return "refinement"
        return "search" if margin >= threshold else "faint"
    if any(w.agree >= truth.agree and w.disagree <= truth.disagree for w in wrong):
        return "dominated"
    return "weighting"


def _right(pair: MapPair, matrix: np.ndarray) -> bool:
    """Whether ``matrix``, in the pixels of the decision's maps (pooled for fine maps,
    :func:`pgvd.pooling.decision_pool`), is within the pair's success bounds."""
    full = from_pooled(np.asarray(matrix), decision_pool(pair.a.resolution))
    return bool(evaluate(pair, True, full)["success"])


def truth_stays(pair: MapPair, maps: tuple[WallMap, WallMap], params: MergeParams) -> bool:
    """Whether the merge's last refinement, started at the exact truth, stays within the
    success bounds."""
    truth = to_pooled(pair.truth, decision_pool(pair.a.resolution))
    return _right(pair, final_refinement(truth, *maps, params))


def assess(pair: MapPair, record: dict, maps: tuple[WallMap, WallMap], params: MergeParams) -> dict:
    """One failed pair: the counts at its truth and best wrong finalist, and its class.

    Parameters
    ----------
    pair : MapPair
        The pair, with its true B->A matrix.
    record : dict
        Its pgvd record of ``merge.json``: ``finalists`` (3x3 B->A matrices, may be
        empty), ``matrix`` (the returned pose) and ``set``.
    maps : tuple of WallMap
        :func:`bench.studies.redecide.decision_maps` of the pair.
    params : MergeParams
        The decision's parameters.

    Returns
    -------
    dict
        ``pair``, ``set``, ``class``, ``truth`` and ``rival`` (``[agree, disagree]``
        of the truth and of the wrong finalist of best evidence, or None).
    """
    pool = decision_pool(pair.a.resolution)
    res = pair.a.resolution * pool
    fine_a, fine_b = maps
    truths = [to_pooled(pair.truth, pool)]
    near = refine(fine_a, subsample(fine_b.walls, params.refine_points), truths[0], (3.0, 2.0))
    if _right(pair, near):
        truths.append(near)
    weight = params.disagreement_weight
    truth = max(
        (score_hypothesis(m, fine_a, fine_b, params, res) for m in truths),
        key=lambda s: s.evidence(weight),
    )
    finalists = [to_pooled(np.asarray(f, dtype=float), pool) for f in record.get("finalists") or []]
    index, decision, matrix = decide_finalists(
        [truth.matrix, *finalists], fine_a, fine_b, params, res
    )
    outcome = (_right(pair, matrix), decision.margin) if index == 0 else None
    wrong = [
        score_hypothesis(m, fine_a, fine_b, params, res) for m in finalists if not _right(pair, m)
    ]
    returned = record.get("matrix")
    right = returned is not None and evaluate(pair, True, np.asarray(returned))["success"]
    rival = max(wrong, key=lambda s: s.evidence(weight), default=None)
    counts = [s.agreement for s in wrong]
    return {
        "pair": pair.name,
        "set": record["set"],
        "class": classify(truth.agreement, counts, right, outcome, params.min_margin),
        "truth_margin": None if outcome is None else outcome[1],
        "truth": [truth.agreement.agree, truth.agreement.disagree],
        "rival": None if rival is None else [rival.agreement.agree, rival.agreement.disagree],
    }


def markdown(rows: list[dict], stays: dict[str, list[bool]], command: str) -> str:
    """The report: failed pairs per set and class, then every pair.

    ``stays`` holds, per set, :func:`truth_stays` of every overlapping pair.
    """
    lines = ["# The failed pairs' truth against their wrong finalists", "", f"`{command}`", ""]
    head = "| set | pairs | truth refined off the bounds | failed | " + " | ".join(CLASSES)
    lines += [head + " |", "|---" * (4 + len(CLASSES)) + "|"]
    for s in SETS:
        group = [r for r in rows if r["set"] == s]
        every = stays.get(s, [])
        if every:
            counts = " | ".join(str(sum(r["class"] == c for r in group)) for c in CLASSES)
            off = len(every) - sum(every)
            lines.append(f"| {s} | {len(every)} | {off} | {len(group)} | {counts} |")
    lines += [
        "",
        "agree / disagree: walls on walls / walls on clear free space, both ways, on the "
        "decision's subsample.",
        "",
        "| pair | class | truth agree / disagree | its margin if picked "
        "| best wrong finalist agree / disagree |",
        "|---|---|---|---|---|",
    ]
    for r in rows:
        rival = "-" if r["rival"] is None else "{} / {}".format(*r["rival"])
        margin = "-" if r["truth_margin"] is None else f"{r['truth_margin']:.2f}"
        truth = "{} / {}".format(*r["truth"])
        lines.append(f"| {r['pair']} | {r['class']} | {truth} | {margin} | {rival} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("json", nargs="?", type=Path, default=RESULTS / "merge.json")
    parser.add_argument("--set", choices=SETS, help="only this set")
    parser.add_argument("--method", default="pgvd", help="records of this bench method")
    parser.add_argument("--seed", type=int, default=1, help="seed of the run's pairs")
    parser.add_argument("--cache", type=Path, default=CACHE)
    parser.add_argument("--out", type=Path, default=RESULTS / "evidence.md")
    args = parser.parse_args(argv)
    try:
        records = json.loads(args.json.read_text())["records"]
    except (OSError, ValueError, KeyError) as exc:
        parser.error(f"cannot read bench records from {args.json}: {exc}")
    chosen = {
        r["pair"]: r
        for r in records
        if r["method"] == args.method and r["set"] in SETS and args.set in (None, r["set"])
    }
    params = MergeParams(diagnostics=False)
    rows: list[dict] = []
    stays: dict[str, list[bool]] = {}
    for entry in build(FULL, args.seed, args.cache):
        record = chosen.get(entry.pair.name)
        if record is None:
            continue
        maps = decision_maps(entry.pair.a, entry.pair.b, params)
        stays.setdefault(record["set"], []).append(truth_stays(entry.pair, maps, params))
        got = "right"
        if not record["success"]:
            rows.append(assess(entry.pair, record, maps, params))
            got = rows[-1]["class"]
        done = sum(map(len, stays.values()))
        print(f"[evidence] {done}/{len(chosen)} {entry.pair.name}: {got}", flush=True)
    command = "python3 -m bench evidence " + " ".join(argv if argv is not None else sys.argv[1:])
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(markdown(rows, stays, command.strip()))
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
