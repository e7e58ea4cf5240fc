"""What the decision makes of the true pose: how much any better search could still gain.

For every overlapping pair of a bench run, the exact true pose is handed to the decision
(:func:`pgvd.merge.decide_finalists`, replayed as :mod:`bench.redecide` does) beside the
run's own finalists at other poses.  The truth is refined and scored like any finalist and
measured against those rivals and against its own shifted copies.  Per pair it tells:

- ``accepted``: the truth wins and passes the merge's threshold: a perfect search (every
  heading, translation and finalist right) would merge this pair with the decision as it is;
- ``below``: the truth wins, but its margin is under the threshold: its walls agree no
  better than a copy of it shifted a few metres (a corridor seen along its length) or than
  the maps contradict it, so only another statistic could accept it;
- ``beaten``: a finalist at another pose scores better than the truth: on these maps the
  evidence itself prefers a wrong pose.

Only the last two are lost whatever the search; the first bounds what search work can add
to the run's successes.

    python3 -m bench.ceiling [RUN/merge.json] [--out bench/results/ceiling.md]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from bench.merge import CACHE, RESULTS, evaluate
from bench.pairs import MapPair
from bench.redecide import replay
from bench.sets import FULL, build
from bench.sources import SOURCES
from pgvd.merge import MergeParams

#: What happens to the truth at the decision (module docstring).
OUTCOMES = ("accepted", "below", "beaten")


def truth_at_decision(pair: MapPair, others: list[np.ndarray], params: MergeParams) -> dict:
    """The decision with ``pair``'s true pose as a finalist among ``others``.

    Parameters
    ----------
    pair : MapPair
        The maps and their true B pixel -> A pixel matrix.
    others : list of numpy.ndarray
        Finalists at other poses than the truth.
    params : MergeParams
        The decision's parameters.

    Returns
    -------
    dict
        ``outcome`` (one of :data:`OUTCOMES`; a truth that wins but is refined off the
        success bounds, as a drifted map's may be, counts as beaten) and the winner's
        ``margin``.
    """
    got = replay(pair.a, pair.b, [pair.truth, *others], params)
    won = got["winner"] == 0 and evaluate(pair, True, got["matrix"])["success"]
    outcome = "beaten" if not won else "accepted" if got["accepted"] else "below"
    return {"outcome": outcome, "margin": float(got["margin"])}


def other_finalists(pair: MapPair, finalists: list) -> list[np.ndarray]:
    """The run's finalists whose pose is wrong by the bench's success bounds."""
    mats = [np.asarray(m, dtype=float) for m in finalists]
    return [m for m in mats if not evaluate(pair, True, m)["success"]]


def run(records: list[dict], pairs: dict[str, MapPair], params: MergeParams) -> list[dict]:
    """One row per overlapping pair with finalists: its set, source, the run's success and
    what the decision makes of its truth."""
    rows = []
    todo = [r for r in records if r["set"] != "negative" and r.get("finalists")]
    for i, rec in enumerate(todo, 1):
        pair = pairs[rec["pair"]]
        got = truth_at_decision(pair, other_finalists(pair, rec["finalists"]), params)
        rows.append(
            {
                "pair": rec["pair"],
                "set": rec["set"],
                "source": rec["source"],
                "run": bool(rec["success"]),
                **got,
            }
        )
        print(
            f"[ceiling] {i}/{len(todo)} {rec['pair']} {rows[-1]['outcome']} "
            f"margin {got['margin']:.2f}",
            file=sys.stderr,
            flush=True,
        )
    return rows


def table(rows: list[dict], key: str) -> list[str]:
    """Markdown rows per value of ``key`` (``set`` or ``source``), then all."""
    lines = [
        f"| {key} | pairs | right in the run | truth accepted | truth wins, margin below "
        "| truth beaten | median margin of the truth when it wins |",
        "|---|---|---|---|---|---|---|",
    ]
    groups = sorted({r[key] for r in rows})
    for name in [*groups, "**all**"]:
        mine = [r for r in rows if name == "**all**" or r[key] == name]
        wins = [r["margin"] for r in mine if r["outcome"] != "beaten"]
        counts = [sum(r["outcome"] == o for r in mine) for o in OUTCOMES]
        median = f"{np.median(wins):.2f}" if wins else "-"
        lines.append(
            f"| {name} | {len(mine)} | {sum(r['run'] for r in mine)} | "
            + " | ".join(str(c) for c in counts)
            + f" | {median} |"
        )
    return lines


def markdown(rows: list[dict], params: MergeParams, command: str) -> str:
    """The report: per set, per source, and the pairs the run lost that the truth would win."""
    gained = sorted(r["pair"] for r in rows if r["outcome"] == "accepted" and not r["run"])
    lines = [
        "# What the decision makes of the true pose",
        "",
        f"`{command}`",
        "",
        f"The exact true pose handed to the decision beside the run's finalists at other poses "
        f"(threshold {params.min_margin}). 'truth accepted' bounds what any better search "
        "could give with this decision; the rest is lost to the decision's statistic "
        "('margin below': the truth wins, but no more clearly than a shifted copy of it or "
        "than the maps contradict it) or to the evidence ('beaten': a wrong pose scores "
        "better, or the truth refines off the success bounds).",
        "",
        *table(rows, "set"),
        "",
        *table(rows, "source"),
        "",
        f"Pairs the run lost that the truth would win ({len(gained)}): "
        + (", ".join(gained) if gained else "none"),
        "",
    ]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("json", nargs="?", type=Path, default=RESULTS / "merge.json")
    parser.add_argument("--out", type=Path, default=RESULTS / "ceiling.md")
    parser.add_argument("--seed", type=int, default=1, help="seed of the run's pairs")
    parser.add_argument("--cache", type=Path, default=CACHE)
    args = parser.parse_args(argv)
    try:
        doc = json.loads(args.json.read_text())
    except (OSError, ValueError) as exc:
        print(f"bench.ceiling: cannot read {args.json}: {exc}", file=sys.stderr)
        return 2
    records = [r for r in doc.get("records", []) if r.get("method") == "pgvd"]
    if not records:
        print(f"bench.ceiling: {args.json} holds no pgvd records", file=sys.stderr)
        return 2
    pairs = {e.pair.name: e.pair for e in build(FULL, args.seed, args.cache, SOURCES)}
    params = MergeParams(diagnostics=False)
    rows = run(records, pairs, params)
    command = "python3 -m bench.ceiling " + " ".join(argv if argv is not None else sys.argv[1:])
    args.out.write_text(markdown(rows, params, command.strip()))
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
