"""Replay the decision of a bench run from its saved finalists, without the search.

The search of a merge (headings, PGVD, Gamma, rho) takes most of its time and
does not depend on the decision.  The merge bench records, for every pgvd
pair, the refined finalists that reached the decision (``finalists`` in
``merge.json``, :mod:`bench.capture`).  This replays only the decision,
:func:`pgvd.scoring.decide_finalists`, on them with the current code and
``MergeParams`` (fields overridden with ``--param``), so that a change of the
scoring or of the threshold is measured on the whole bench in a fraction of
its time.  With the code and parameters of the run it gives the run's margins.

A replayed pair is accepted when ``margin >= min_margin``; the floors the
merge applies after that (``min_overlap`` of agreeing walls, the optional
``min_agreement``) are not replayed.  Printed per set: successes (accepted at
a right pose) against the run's own, wrong and false accepts, and the largest
margin of a winner at a wrong pose or on a negative pair: a threshold above
it accepts none of them.  ``-v`` prints every pair.

    python3 -m bench redecide [bench/results/merge.json] [--set drifted] [--param min_margin=0.7]

``--method pgvd-heading`` replays the records of that bench method instead of
``pgvd``'s (its finalists; the decision's parameters are still ``MergeParams``
with the ``--param`` overrides).

``--frontier`` asks whether the decision's own statistics could be recalibrated
into more successes: the winner's margin is split into its margin against the
other poses and against its shifted copies, and the best pair of thresholds on
the two that still accepts no wrong or negative winner is reported
(:func:`frontier`).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from pathlib import Path

import numpy as np

from bench.data.sets import FULL, Entry, build
from bench.data.sources import SOURCES
from bench.merge import CACHE, RESULTS, evaluate
from bench.tables import mark
from pgvd.decision import margin_against
from pgvd.grid import Grid
from pgvd.inputs import registration_probability
from pgvd.params import MergeParams
from pgvd.pooling import decision_pool, from_pooled, to_pooled
from pgvd.scoring import decide_finalists, fine_maps
from pgvd.walls import WallMap

SETS = ("standard", "low", "drifted", "negative")


def params_from(overrides: list[str]) -> MergeParams:
    """MergeParams with ``name=value`` overrides, each value read as its field's type.

    Raises
    ------
    ValueError
        An override without ``=``, an unknown field or a value its type refuses.
    """
    base = MergeParams(diagnostics=False)
    fields = set(MergeParams.field_names())
    changes: dict[str, object] = {}
    for item in overrides:
        name, sep, value = item.partition("=")
        if not sep or name not in fields:
            raise ValueError(f"--param expects FIELD=VALUE with a MergeParams field, got {item!r}")
        kind = type(getattr(base, name))
        changes[name] = value.lower() in ("1", "true", "yes") if kind is bool else kind(value)
    return dataclasses.replace(base, **changes)


def decision_maps(a: Grid, b: Grid, params: MergeParams) -> tuple[WallMap, WallMap]:
    """:func:`pgvd.scoring.fine_maps` of two grids, each read and pooled as the merge reads
    it (:func:`pgvd.inputs.registration_probability`, :func:`pgvd.pooling.decision_pool`)."""
    pa, pb = registration_probability(a, params), registration_probability(b, params)
    return fine_maps(pa, pb, params, decision_pool(a.resolution))


def replay(a: Grid, b: Grid, finalists: list, params: MergeParams) -> dict:
    """The decision on one pair's finalists: margin, rival, accept and the B->A matrix.

    Parameters
    ----------
    a, b : Grid
        The pair's maps.
    finalists : list
        The refined finalists' 3x3 B->A pixel matrices (nested lists or arrays).
    params : MergeParams
        Parameters of the decision.

    Returns
    -------
    dict
        ``winner`` (index in ``finalists``), ``margin``, ``rival``, ``accepted``,
        ``matrix`` (3x3 array) and the whole ``decision`` (:class:`pgvd.decision.Decision`).
    """
    fine_a, fine_b = decision_maps(a, b, params)
    pool = decision_pool(a.resolution)
    mats = [to_pooled(np.asarray(m, dtype=float), pool) for m in finalists]
    index, decision, matrix = decide_finalists(mats, fine_a, fine_b, params, a.resolution * pool)
    return {
        "winner": index,
        "margin": decision.margin,
        "rival": decision.rival,
        "accepted": decision.margin >= params.min_margin,
        "matrix": from_pooled(matrix, pool),
        "decision": decision,
    }


def replay_run(
    records: list[dict], entries: dict[str, Entry], params: MergeParams, verbose: bool
) -> list[dict]:
    """Replay every record that has finalists; one row per pair."""
    rows = []
    for rec in records:
        if not rec.get("finalists") or rec["pair"] not in entries:
            continue
        pair = entries[rec["pair"]].pair
        got = replay(pair.a, pair.b, rec["finalists"], params)
        right = evaluate(pair, True, got["matrix"])["success"]
        row = {
            "pair": rec["pair"],
            "set": rec["set"],
            "before": bool(rec["success"]),
            "right": right,
            "accepted": got["accepted"],
            "margin": got["margin"],
            "decision": got["decision"],
        }
        rows.append(row)
        if verbose:
            run = rec.get("result", {}).get("margin")
            outcome = mark(right and got["accepted"], got["accepted"])
            print(
                f"{outcome:3} {rec['pair']:36} {rec['set']:8} right={int(right)} "
                f"margin {got['margin']:6.2f} (run {np.nan if run is None else run:6.2f}) "
                f"rival {got['rival']:7.0f} (another pose {got['decision'].other:7.0f}, "
                f"shifted {got['decision'].shifted:7.0f})",
                flush=True,
            )
    return rows


def summary(rows: list[dict]) -> list[str]:
    """Per set: successes now and in the run, wrong or false accepts; the largest bad margin."""
    lines = []
    for name in SETS:
        mine = [r for r in rows if r["set"] == name]
        if not mine:
            continue
        now = sum(r["accepted"] and r["right"] for r in mine)
        bad = sum(r["accepted"] and not r["right"] for r in mine)
        before = sum(r["before"] for r in mine)
        lines.append(
            f"{name}: {now}/{len(mine)} right and accepted (run: {before}), "
            f"{bad} {'false' if name == 'negative' else 'wrong'} accepts"
        )
    bad = [r for r in rows if not r["right"]]
    if bad:
        worst = max(bad, key=lambda r: r["margin"])
        lines.append(
            f"largest margin of a wrong or negative winner: {worst['margin']:.3f} ({worst['pair']})"
        )
    return lines


def split_margins(rows: list[dict], params: MergeParams) -> np.ndarray:
    """Per row, the winner's margin against its other poses and against its shifted copies.

    The decision takes the larger of the two rivals (:attr:`pgvd.decision.Decision.rival`);
    measured apart, each has a margin of its own (:func:`pgvd.decision.margin_against`),
    and the smaller of the two is the decision's margin.  A kind with no rival while the
    other has one puts no bound on it (``inf``): the margin counts a missing rival as
    evidence 0, as it counts one the maps contradict.
    """
    w, noise = params.disagreement_weight, params.margin_noise
    out = []
    for d in (r["decision"] for r in rows):
        out.append(
            [
                np.inf
                if np.isneginf(rival) and np.isfinite(d.rival)
                else margin_against(d.winner, rival, w, noise)
                for rival in (d.other, d.shifted)
            ]
        )
    return np.array(out, dtype=float).reshape(-1, 2)


def frontier(rows: list[dict], params: MergeParams, gap: float = 0.03) -> list[str]:
    """The most right poses any pair of thresholds on the two split margins accepts.

    A rule "margin against other poses >= t1 and against shifted copies >= t2" is
    allowed when every wrong or negative winner is more than ``gap`` below one of its
    thresholds (no bad accept, with room to spare); t1 and t2 run from 0 to 1.5 in
    steps of 0.02, and of equal rules the first (smallest t1, then t2) is reported.
    The merge's own rule is ``t1 = t2 = min_margin``.  If no allowed rule accepts more
    right poses than that, the decision's statistics cannot be recalibrated into more
    successes: what is rejected looks, to them, like what is wrong.
    """
    margins = split_margins(rows, params)
    right = np.array([r["right"] for r in rows], bool)
    sets = np.array([r["set"] for r in rows])
    bad = margins[~right]
    steps = np.round(np.arange(0.0, 1.5 + 1e-9, 0.02), 2)
    best = (-1, 0.0, 0.0)
    for t1 in steps:
        for t2 in steps:
            if np.any((bad[:, 0] >= t1 - gap) & (bad[:, 1] >= t2 - gap)):
                continue
            n = int(np.sum(right & (margins[:, 0] >= t1) & (margins[:, 1] >= t2)))
            best = max(best, (n, t1, t2), key=lambda b: b[0])
    n, t1, t2 = best
    if n < 0:
        return [f"frontier: no pair of thresholds keeps every bad winner {gap} below"]
    chosen = right & (margins[:, 0] >= t1) & (margins[:, 1] >= t2)
    per_set = ", ".join(f"{k} {int(np.sum(chosen & (sets == k)))}" for k in SETS[:3])
    single = int(np.sum(right & (margins.min(axis=1) >= params.min_margin)))
    return [
        f"frontier (gap {gap}): at most {n} right accepts ({per_set}), with t1 = {t1:.2f} "
        f"against other poses and t2 = {t2:.2f} against shifted copies; min_margin "
        f"{params.min_margin} on both accepts {single}"
    ]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("json", nargs="?", type=Path, default=RESULTS / "merge.json")
    parser.add_argument("--set", choices=SETS, help="only this set")
    parser.add_argument("--method", default="pgvd", help="records of this bench method")
    parser.add_argument("--param", nargs="*", default=[], help="MergeParams FIELD=VALUE")
    parser.add_argument("--seed", type=int, default=1, help="seed of the run's pairs")
    parser.add_argument("--cache", type=Path, default=CACHE)
    parser.add_argument("-v", "--verbose", action="store_true")
    parser.add_argument(
        "--frontier", action="store_true", help="best two-threshold rule on the split margins"
    )
    args = parser.parse_args(argv)
    params = params_from(args.param)
    doc = json.loads(args.json.read_text())
    records = [
        r
        for r in doc["records"]
        if r["method"] == args.method and (args.set is None or r["set"] == args.set)
    ]
    if not records:
        print(f"{args.json}: no records of method {args.method!r}")
        return 1
    entries = {e.pair.name: e for e in build(FULL, args.seed, args.cache, SOURCES)}
    rows = replay_run(records, entries, params, args.verbose)
    print("\n".join(summary(rows)))
    if args.frontier:
        print("\n".join(frontier(rows, params)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
