"""The merge on maps of other cell sizes: the same laser logs mapped at each resolution.

Every map of the merge bench has 5 cm cells, and the decision's distances in
cells were set there.  A user's SLAM may map at 2.5 cm or 10 cm.  For each
``--resolutions`` value, overlapping pairs and negatives are cut from the intel
and freiburg-079 logs with one seed, the same segments whatever the cell size (as
far as the overlap band allows), and merged.  The negatives are those of the merge
bench (:mod:`bench.data.negatives`): disjoint parts of one log, a part against its
mirror image, look-alike corridors (fewer where a building has no two out of
each other's sight) and a part of one building against a part of the other.
A pose is right when accepted within 2 degrees and 0.15 m (B's occupied
cells, mean): a bound in metres, so that the cell sizes compare.

    python3 -m bench resolution [--resolutions 0.0175 0.025 0.05 0.1] [--overlap 8]
        [--negatives 3] [--out bench/results]

Writes ``resolution.md``: per cell size, right / overlapping pairs, wrong and
false accepts, the smallest margin of a right pose, the largest margin of a
negative, the median error of the right poses (m) and the median time.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

from bench.data.negatives import cross_pairs, lookalike_pairs, mirror_pairs
from bench.data.pairs import MAX_DRAWS, MapPair, make_pairs
from bench.data.sets import cached
from bench.data.sources import SHARED
from bench.merge import CACHE, RESULTS, errors
from pgvd.carmen import read_carmen
from pgvd.merge import merge
from pgvd.params import MergeParams

LOGS = {"intel": "intel-corrected.log.gz", "fr079": "freiburg-079-corrected.log.gz"}
#: A right pose: within these of the truth (degrees; metres, mean over B's occupied cells).
MAX_HEADING_DEG, MAX_ERROR_M = 2.0, 0.15


def pairs_at(
    resolution: float, n_overlap: int, n_negative: int, seed: int, cache: Path | None
) -> list[MapPair]:
    """Each log's overlapping pairs and negatives, then the cross pairs, at ``resolution``
    (cached)."""
    runs = {name: read_carmen(SHARED / "logs" / log) for name, log in LOGS.items()}
    out: list[MapPair] = []
    for name, scans in runs.items():

        def make(scans: list = scans, name: str = name) -> list[MapPair]:
            return (
                make_pairs(scans, n_overlap, 0, seed, name, resolution=resolution)
                + make_pairs(scans, 0, n_negative, seed, name, resolution, max_draws=4 * MAX_DRAWS)
                + mirror_pairs(scans, n_negative, seed, name, resolution)
                + lookalike_pairs(scans, n_negative, seed, name, resolution)
            )

        key = f"resolution-{name}-ov-dj-mi-la-{resolution}-{n_overlap}-{n_negative}-{seed}"
        out += cached(cache, key, make)
    key = f"resolution-cross-{resolution}-{n_negative}-{seed}"
    return out + cached(cache, key, lambda: cross_pairs(runs, n_negative, seed, resolution))


def judge(pair: MapPair, params: MergeParams) -> dict:
    """One merge: accepted, right (metric bounds), margin, error (m) and seconds."""
    t0 = time.perf_counter()
    result = merge(pair.a, pair.b, params)
    seconds = time.perf_counter() - t0
    heading_deg, cells = errors(pair, result.matrix)
    error_m = cells * pair.a.resolution
    right = heading_deg <= MAX_HEADING_DEG and error_m <= MAX_ERROR_M
    return {
        "pair": pair.name,
        "overlap": pair.overlap,
        "accepted": bool(result.accepted),
        "right": bool(result.accepted and pair.overlap > 0 and right),
        "margin": result.margin,
        "error_m": error_m,
        "seconds": seconds,
    }


def row(resolution: float, rows: list[dict]) -> str:
    """The table row of one cell size."""
    over = [r for r in rows if r["overlap"] > 0]
    neg = [r for r in rows if r["overlap"] == 0]
    right = [r for r in over if r["right"]]
    wrong = sum(r["accepted"] and not r["right"] for r in over)
    false = sum(r["accepted"] for r in neg)

    def worst(values: list[float], pick) -> str:
        finite = [v for v in values if v == v]  # NaN: rejected before the decision
        return f"{pick(finite):.2f}" if finite else "-"

    error = f"{statistics.median(r['error_m'] for r in right):.3f}" if right else "-"
    return (
        f"| {resolution} | {len(right)}/{len(over)} | {wrong} | {false}/{len(neg)} | "
        f"{worst([r['margin'] for r in right], min)} | {worst([r['margin'] for r in neg], max)} | "
        f"{error} | {statistics.median(r['seconds'] for r in rows):.2f} |"
    )


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--resolutions", type=float, nargs="+", default=[0.0175, 0.025, 0.05, 0.1])
    parser.add_argument("--overlap", type=int, default=8, help="overlapping pairs per log")
    parser.add_argument("--negatives", type=int, default=3, help="negatives of each kind")
    parser.add_argument("--seed", type=int, default=7)
    parser.add_argument("--cache", type=Path, default=CACHE)
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args(argv)
    if any(not r > 0 for r in args.resolutions) or args.overlap < 1 or args.negatives < 0:
        parser.error("resolutions must be > 0, --overlap >= 1 and --negatives >= 0")
    params = MergeParams(diagnostics=False)
    command = " ".join(["python3 -m bench resolution", *(sys.argv[1:] if argv is None else argv)])
    lines = [
        "# The merge at other cell sizes",
        "",
        f"`{command}` (intel and freiburg-079 logs: {args.overlap} overlapping pairs and "
        f"{args.negatives} negatives of each kind each, and {args.negatives} pairs of the two "
        f"buildings; seed {args.seed}). Right: accepted within "
        f"{MAX_HEADING_DEG:g} deg and {MAX_ERROR_M:g} m.",
        "",
        "| cell (m) | right | wrong | false | smallest right margin | largest negative margin "
        "| median error of right (m) | median s |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for resolution in args.resolutions:
        pairs = pairs_at(resolution, args.overlap, args.negatives, args.seed, args.cache)
        rows = []
        for pair in pairs:
            rows.append(judge(pair, params))
            r = rows[-1]
            print(
                f"[resolution] {resolution} {r['pair']:12} ov {r['overlap']:.2f} "
                f"{'ACC' if r['accepted'] else 'rej'} right={int(r['right'])} "
                f"margin {r['margin']:.2f} error {r['error_m']:.3f} m {r['seconds']:.2f} s",
                flush=True,
            )
        lines.append(row(resolution, rows))
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "resolution.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
