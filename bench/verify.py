"""How the agent's check of a predicted pose (:func:`pgvd.verify.verify`) does, near and far.

At predictions near the truth, and at wrong ones.

    python3 -m bench verify [--metres 0.5] [--degrees 3] [--seed 7] [--out FILE]
                            [--json bench/results/merge.json] [--cache bench/cache]

The agent checks a pair at a prediction before it searches (``pgvd agent --known-pose``,
and the chain of links already accepted): a check confirms the prediction's refined pose
or rejects it.  A rejected prior, or a chain's first rejection, sends the pair on to the
full search; a chain's rejection of a pair rejected before, or over links that each lie on
a triangle, stands (:func:`agent.worker.verify_check`).  Every pair of the merge
bench (:data:`bench.data.sets.FULL`, from its cache) is checked at:

- ``near`` (overlapping pairs): the truth turned about B's wall centroid by
  ``N(0, degrees)`` and shifted by ``N(0, metres)`` along each axis, as a known initial
  pose measured by hand is off.  Confirmed right, confirmed at a wrong pose, or rejected;
- ``shifted`` and ``turned`` (overlapping pairs): a chain with a wrong link, the truth
  shifted 4-8 m, or turned by a quarter or a half turn about B's wall centroid;
- ``negative`` (the bench's 110 negatives): where the merge's search overlaid the maps
  best (its winning pose in ``merge.json``, rejected there), the hardest wrong prediction.

Every confirmation of a wrong prediction is a false link.  Writes ``bench/results/verify.md``,
and every check (prediction, outcome, errors, margin) in ``verify.json``.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections import Counter
from pathlib import Path

import numpy as np

from bench.data.pairs import MapPair, turn_about
from bench.data.sets import FULL, build
from bench.merge import CACHE, RESULTS, evaluate
from pgvd.params import MergeParams
from pgvd.verify import BASIN_DEG, BASIN_M, verify

#: How far a wrong chain's shift puts B (m): farther than the check's basin, within a building.
WRONG_SHIFT_M = (4.0, 8.0)
#: The turns (degrees) of a wrong chain that turns B.
WRONG_TURNS_DEG = (90.0, 180.0, -90.0)
#: The kinds of prediction, in the order of the tables.
KINDS = ("near", "shifted", "turned", "negative")


def wall_centre(pair: MapPair, params: MergeParams) -> np.ndarray:
    """B's wall centroid ``(x, y)`` in B's pixels."""
    rows, cols = np.nonzero(pair.b.probability() > params.occupied)
    return np.array([cols.mean(), rows.mean()])


def moved(
    matrix: np.ndarray, degrees: float, shift_px: np.ndarray, point: np.ndarray
) -> np.ndarray:
    """``matrix`` (B -> A pixels) turned by ``degrees`` about B's ``point``, then shifted
    ``shift_px`` in A."""
    return turn_about(degrees, (matrix @ np.append(point, 1.0))[:2], shift_px) @ matrix


def predictions(
    pair: MapPair, record: dict, rng: np.random.Generator, metres: float, degrees: float
) -> list[tuple[str, np.ndarray]]:
    """The predictions a pair is checked at (module docstring), by kind."""
    if pair.truth is None or pair.overlap <= 0:
        return [("negative", np.asarray(record["matrix"], dtype=float))]
    centre = wall_centre(pair, MergeParams())
    px = 1.0 / pair.a.resolution
    near = moved(pair.truth, rng.normal(0, degrees), rng.normal(0, metres * px, 2), centre)
    angle, dist = rng.uniform(0, 2 * np.pi), rng.uniform(*WRONG_SHIFT_M) * px
    away = dist * np.array([np.cos(angle), np.sin(angle)])
    shifted = moved(pair.truth, 0.0, away, centre)
    turned = moved(pair.truth, float(rng.choice(WRONG_TURNS_DEG)), np.zeros(2), centre)
    return [("near", near), ("shifted", shifted), ("turned", turned)]


def outcome(kind: str, accepted: bool, right: bool) -> str:
    """``right``, ``wrong`` (a near prediction confirmed off the truth), ``false`` (a wrong
    prediction confirmed) or ``rejected``."""
    if not accepted:
        return "rejected"
    if kind == "near":
        return "right" if right else "wrong"
    return "false"


def run(metres: float, degrees: float, seed: int, cache: Path, records: dict) -> list[dict]:
    """One row per check of every bench pair that ``records`` (pgvd's, by pair) holds."""
    rng = np.random.default_rng(seed)
    params = MergeParams(diagnostics=False)
    rows = []
    entries = [e for e in build(FULL, 1, cache) if e.pair.name in records]
    for i, entry in enumerate(entries, 1):
        pair = entry.pair
        for kind, predicted in predictions(pair, records[pair.name], rng, metres, degrees):
            t0 = time.perf_counter()
            result = verify(pair.a, pair.b, predicted, params)
            seconds = time.perf_counter() - t0
            judged = evaluate(pair, True, result.matrix) if kind == "near" else {}
            rows.append(
                {
                    "pair": pair.name,
                    "source": entry.source,
                    "set": entry.set,
                    "kind": kind,
                    "outcome": outcome(kind, result.accepted, judged.get("success", False)),
                    "heading_deg": judged.get("heading_deg"),
                    "cell_err": judged.get("cell_err"),
                    "predicted": predicted.tolist(),
                    # JSON has no NaN: a check rejected before its decision has no margin
                    "margin": float(result.margin) if np.isfinite(result.margin) else None,
                    "reason": result.reason,
                    "seconds": seconds,
                }
            )
        last = rows[-1]
        print(f"[verify] {i}/{len(entries)} {pair.name}: {last['outcome']}", flush=True)
    return rows


def _share(n: int, total: int) -> str:
    return f"{n}/{total} ({100 * n / total:.0f} %)" if total else "-"


def table(rows: list[dict], group: str) -> list[str]:
    """Markdown rows by ``group`` (``set`` or ``source``): near predictions confirmed right
    and wrong, and wrong predictions confirmed, of each kind."""
    lines = [
        f"| {group} | near: right | near: wrong pose | shifted: confirmed | turned: confirmed "
        "| negative: confirmed |",
        "|---|---|---|---|---|---|",
    ]
    for name in sorted({r[group] for r in rows}):
        mine = [r for r in rows if r[group] == name]
        n = Counter(r["kind"] for r in mine)
        hit = Counter((r["kind"], r["outcome"]) for r in mine)
        cells = [
            _share(hit["near", "right"], n["near"]),
            _share(hit["near", "wrong"], n["near"]),
            *(_share(hit[k, "false"], n[k]) for k in KINDS[1:]),
        ]
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return lines


def rejections(rows: list[dict]) -> list[str]:
    """Markdown rows: why near predictions were rejected, by set (the reason up to its colon)."""
    why = Counter(
        (r["set"], r["reason"].split(":")[0])
        for r in rows
        if r["kind"] == "near" and r["outcome"] == "rejected"
    )
    lines = ["| set | near predictions rejected because | checks |", "|---|---|---|"]
    return lines + [f"| {s} | {reason} | {n} |" for (s, reason), n in sorted(why.items())]


def markdown(rows: list[dict], command: str, metres: float, degrees: float) -> str:
    """The report: by set, by source, the wrong confirmations and the time a check takes."""
    bad = [r for r in rows if r["outcome"] in ("wrong", "false")]
    seconds = np.array([r["seconds"] for r in rows])
    out = [
        "# Checks at a prediction (pgvd.verify)",
        "",
        f"`{command}`",
        "",
        f"Near: the truth turned by N(0, {degrees} deg) about B's wall centroid and shifted "
        f"N(0, {metres} m) along each axis. Shifted: {WRONG_SHIFT_M[0]:g}-{WRONG_SHIFT_M[1]:g} "
        "m off. Turned: a quarter or half turn. Negative: the pose where the merge's search "
        "overlaid a negative pair best. A check rejects a prediction that its refinement "
        f"moved more than {BASIN_M:g} m or {BASIN_DEG:g} deg; a near prediction that far off "
        "cannot be confirmed.",
        "",
        *table(rows, "set"),
        "",
        *table(rows, "source"),
        "",
        *rejections(rows),
        "",
        f"Wrong poses and false links: {len(bad)} of {len(rows)} checks" + (":" if bad else "."),
        "",
        *(
            f"- {r['pair']} ({r['kind']}): margin {r['margin']:.2f}"
            for r in sorted(bad, key=lambda r: -r["margin"])
        ),
        "",
        f"A check takes {np.median(seconds):.3f} s (median; 95th percentile "
        f"{np.percentile(seconds, 95):.3f} s), reading the maps included.",
        "",
    ]
    return "\n".join(out)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--json", type=Path, default=RESULTS / "merge.json")
    parser.add_argument("--metres", type=float, default=0.5, help="near: shift sigma per axis")
    parser.add_argument("--degrees", type=float, default=3.0, help="near: heading sigma")
    parser.add_argument("--seed", type=int, default=7)
    parser.add_argument("--cache", type=Path, default=CACHE)
    parser.add_argument("--out", type=Path, default=RESULTS / "verify.md")
    args = parser.parse_args(argv)
    if args.metres < 0 or args.degrees < 0:
        parser.error("--metres and --degrees must be >= 0")
    try:
        records = json.loads(args.json.read_text())["records"]
    except (OSError, ValueError, KeyError) as exc:
        parser.error(f"cannot read bench records from {args.json}: {exc}")
    pgvd = {r["pair"]: r for r in records if r["method"] == "pgvd"}
    rows = run(args.metres, args.degrees, args.seed, args.cache, pgvd)
    command = "python3 -m bench verify " + " ".join(argv if argv is not None else sys.argv[1:])
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(markdown(rows, command.strip(), args.metres, args.degrees))
    args.out.with_suffix(".json").write_text(json.dumps(rows))
    print(f"wrote {args.out} and {args.out.with_suffix('.json').name}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
