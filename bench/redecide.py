"""Replay the decision of a bench run from its saved finalists, without the search.

The search of a merge (headings, PGVD, Gamma, rho) takes most of its time and
does not depend on the decision.  The merge bench records, for every pgvd
pair, the refined finalists that reached the decision (``finalists`` in
``merge.json``, :mod:`bench.capture`).  This replays only the decision,
:func:`pgvd.merge.decide_finalists`, on them with the current code and
``MergeParams`` (fields overridden with ``--param``), so that a change of the
scoring or of the threshold is measured on the whole bench in a fraction of
its time.  With the code and parameters of the run it gives the run's margins.

A replayed pair is accepted when ``margin >= min_margin``; the floors the
merge applies after that (``min_overlap`` of agreeing walls, the optional
``min_agreement``) are not replayed.  Printed per set: successes (accepted at
a right pose) against the run's own, wrong and false accepts, and the largest
margin of a winner at a wrong pose or on a negative pair: a threshold above
it accepts none of them.  ``-v`` prints every pair.

    python3 -m bench.redecide [bench/results/merge.json] [--set drifted] [--param min_margin=0.7]

``--method pgvd-heading`` replays the records of that bench method instead of
``pgvd``'s (its finalists; the decision's parameters are still ``MergeParams``
with the ``--param`` overrides).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from pathlib import Path

import numpy as np

from bench.merge import CACHE, RESULTS, evaluate
from bench.report import mark
from bench.sets import FULL, Entry, build
from bench.sources import SOURCES
from pgvd.grid import Grid
from pgvd.matching import WallMap
from pgvd.merge import MergeParams, decide_finalists

SETS = ("standard", "low", "drifted", "negative")


def params_from(overrides: list[str]) -> MergeParams:
    """MergeParams with ``name=value`` overrides, each value read as its field's type.

    Raises
    ------
    ValueError
        An override without ``=``, an unknown field or a value its type refuses.
    """
    base = MergeParams(diagnostics=False)
    fields = {f.name for f in dataclasses.fields(base)}
    changes: dict[str, object] = {}
    for item in overrides:
        name, sep, value = item.partition("=")
        if not sep or name not in fields:
            raise ValueError(f"--param expects FIELD=VALUE with a MergeParams field, got {item!r}")
        kind = type(getattr(base, name))
        changes[name] = value.lower() in ("1", "true", "yes") if kind is bool else kind(value)
    return dataclasses.replace(base, **changes)


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
        ``winner`` (index in ``finalists``), ``margin``, ``rival``, ``accepted`` and
        ``matrix`` (3x3 array).
    """
    fine_a = WallMap(a.probability(), params.occupied, params.free, lookup=True)
    fine_b = WallMap(b.probability(), params.occupied, params.free)
    mats = [np.asarray(m, dtype=float) for m in finalists]
    index, decision, matrix = decide_finalists(mats, fine_a, fine_b, params, a.resolution)
    return {
        "winner": index,
        "margin": decision.margin,
        "rival": decision.rival,
        "accepted": decision.margin >= params.min_margin,
        "matrix": matrix,
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
        }
        rows.append(row)
        if verbose:
            run = rec.get("result", {}).get("margin")
            outcome = mark(right and got["accepted"], got["accepted"])
            print(
                f"{outcome:3} {rec['pair']:36} {rec['set']:8} right={int(right)} "
                f"margin {got['margin']:6.2f} (run {np.nan if run is None else run:6.2f}) "
                f"rival {got['rival']:7.0f}",
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


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("json", nargs="?", type=Path, default=RESULTS / "merge.json")
    parser.add_argument("--set", choices=SETS, help="only this set")
    parser.add_argument("--method", default="pgvd", help="records of this bench method")
    parser.add_argument("--param", nargs="*", default=[], help="MergeParams FIELD=VALUE")
    parser.add_argument("--seed", type=int, default=1, help="seed of the run's pairs")
    parser.add_argument("--cache", type=Path, default=CACHE)
    parser.add_argument("-v", "--verbose", action="store_true")
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
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
