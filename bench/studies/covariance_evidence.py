"""The constants of the thin-evidence inflation, measured on development pairs at their truth.

    python3 -m bench covariance_evidence [--pairs 12] [--seed 10]

:mod:`pgvd.inflation` widens the merge covariance (eq. (3)) where the information
of the point-to-line fit is thin.  Its two constants are properties of the maps,
not of the errors, so they are measured, not fitted: on overlapping pairs of the
intel and freiburg-079 logs (:func:`bench.pairs.make_pairs`, the generator of
:mod:`bench.covariance`), every wall cell of B placed on A by the *true* matrix and
matched to A's nearest wall within 2 cells (the fit's radius):

* normal noise ``s^2 = E[sin^2 delta]`` of a normal's angle error ``delta``.  A's
  and B's normals at a matched cell err independently, so their angle ``theta``
  has ``E[sin^2 theta] = 2 s^2 (1 - s^2)``, solved for ``s^2``;
* correlation length ``ell``: residuals ``r_i = n_i . (R x_i + t - y_i)`` of cells
  on one wall (normals within 20 degrees, within 1.5 cells of each other's line)
  are correlated; ``ell = 1 + 2 sum_{i<j} r_i r_j / sum r_i^2`` over such pairs
  closer than the first distance at which their correlation drops below 0.05
  (the variance of a mean of ``L`` cells of wall is ``ell sigma^2 / L``).

Writes ``covariance-evidence.md`` (per pair, and pooled over the pairs: the
constants :data:`pgvd.inflation.MEASURED` holds) and the sums they come from,
``covariance-evidence.json``, to ``--out`` (default ``bench/results/``).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from pgvd.walls import WallMap

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared"
RESULTS = ROOT / "bench" / "results"
#: Wall cells of B farther than this (cells) from A's walls are not matched (the fit's radius).
MATCH_RADIUS = 2.0
#: Neighbouring cells whose normals differ by more than this are on different walls.
SAME_WALL_DEG = 20.0
#: ... and so are cells farther than this (cells) from each other's wall line.
SAME_LINE_CELLS = 1.5
#: The correlation of residuals is summed out to the first distance where it is below this.
CORRELATION_CUT = 0.05
#: Farthest distance (cells) the correlation is measured at.
MAX_LAG = 60


def matched(a: WallMap, b: WallMap, truth: np.ndarray) -> dict[str, np.ndarray]:
    """B's wall cells placed on A by ``truth`` within :data:`MATCH_RADIUS` of A's walls: their
    positions in A, residuals along A's normals, A's normals and B's normals turned into A."""
    rot = truth[:2, :2]
    moved = b.walls @ rot.T + truth[:2, 2]
    dist, idx = a.tree.query(moved, distance_upper_bound=MATCH_RADIUS)
    ok = np.isfinite(dist)
    n_a = a.normals(idx[ok])
    n_b = b.normals(np.flatnonzero(ok)) @ rot.T
    res = np.sum(n_a * (moved[ok] - a.walls[idx[ok]]), axis=1)
    return {"points": moved[ok], "res": res, "n_a": n_a, "n_b": n_b}


def normal_noise(sin2_theta: float) -> float:
    """``s^2`` from the mean ``E[sin^2 theta]`` of the angle between two maps' normals at
    matched cells (module docstring)."""
    return 0.5 * (1.0 - np.sqrt(max(0.0, 1.0 - 2.0 * sin2_theta)))


def lag_sums(m: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Per whole cell of distance 0..MAX_LAG, the sum of ``r_i r_j`` (normals made to point the
    same way) over pairs of matched cells on one wall, and how many pairs."""
    points, normals, res = m["points"], m["n_a"], m["res"]
    pairs = cKDTree(points).query_pairs(MAX_LAG, output_type="ndarray")
    i, j = pairs[:, 0], pairs[:, 1]
    cos = np.sum(normals[i] * normals[j], axis=1)
    off_line = np.abs(np.sum(normals[i] * (points[j] - points[i]), axis=1))
    same = (np.abs(cos) > np.cos(np.radians(SAME_WALL_DEG))) & (off_line < SAME_LINE_CELLS)
    i, j = i[same], j[same]
    lag = np.rint(np.linalg.norm(points[i] - points[j], axis=1)).astype(int)
    prod = res[i] * res[j] * np.sign(cos[same])
    return (
        np.bincount(lag, weights=prod, minlength=MAX_LAG + 1)[: MAX_LAG + 1],
        np.bincount(lag, minlength=MAX_LAG + 1)[: MAX_LAG + 1],
    )


def correlation_cells(
    sums: np.ndarray, counts: np.ndarray, sum_r2: float, cells: int
) -> tuple[float, int]:
    """``ell`` (module docstring) from :func:`lag_sums` and ``sum r_i^2`` over ``cells``
    matched cells, and the distance (cells) it is summed out to."""
    profile = sums[1:] / np.maximum(counts[1:], 1) / (sum_r2 / cells)
    below = np.flatnonzero(profile < CORRELATION_CUT)
    cut = int(below[0]) if below.size else MAX_LAG  # lags 1..cut are summed
    return 1.0 + 2.0 * float(np.sum(sums[1 : cut + 1])) / sum_r2, cut


def measure(n_pairs: int, seed: int) -> list[dict]:
    """The terms of both constants on ``n_pairs`` overlapping pairs of each development log."""
    from bench.covariance import LOGS
    from bench.data.pairs import make_pairs
    from pgvd.carmen import read_carmen
    from pgvd.merge import MergeParams

    params = MergeParams()
    rows = []
    for log, file in LOGS.items():
        t0 = time.perf_counter()
        pairs = make_pairs(read_carmen(SHARED / "logs" / file), n_pairs, 0, seed, log)
        print(f"{log}: {len(pairs)} pairs in {time.perf_counter() - t0:.0f} s", flush=True)
        for p in pairs:
            a = WallMap(p.a.probability(), params.occupied, params.free)
            b = WallMap(p.b.probability(), params.occupied, params.free)
            m = matched(a, b, p.truth)
            sin_theta = m["n_a"][:, 0] * m["n_b"][:, 1] - m["n_a"][:, 1] * m["n_b"][:, 0]
            sums, counts = lag_sums(m)
            row = {
                "name": p.name,
                "resolution": p.a.resolution,
                "cells": len(m["res"]),
                "sum_sin2": float(np.sum(sin_theta**2)),
                "sum_r2": float(np.sum(m["res"] ** 2)),
                "lag_sums": sums.tolist(),
                "lag_counts": counts.tolist(),
            }
            rows.append(row)
            ell = correlation_cells(sums, counts, row["sum_r2"], row["cells"])[0]
            s2 = normal_noise(row["sum_sin2"] / row["cells"])
            print(f"  {p.name}: {row['cells']} cells, s^2 {s2:.4f}, ell {ell:.2f}", flush=True)
    return rows


def pooled(rows: list[dict]) -> dict:
    """Both constants over all the pairs' matched cells at once, in metres where a length."""
    cells = sum(r["cells"] for r in rows)
    sum_r2 = sum(r["sum_r2"] for r in rows)
    sums = np.sum([r["lag_sums"] for r in rows], axis=0)
    counts = np.sum([r["lag_counts"] for r in rows], axis=0)
    ell, cut = correlation_cells(sums, counts, sum_r2, cells)
    (res,) = {r["resolution"] for r in rows}
    return {
        "pairs": len(rows),
        "cells": cells,
        "normal_noise": normal_noise(sum(r["sum_sin2"] for r in rows) / cells),
        "correlation_cells": ell,
        "correlation_m": ell * res,
        "cut_cells": cut,
        "profile": (sums[1:] / np.maximum(counts[1:], 1) / (sum_r2 / cells)).tolist(),
    }


def markdown(rows: list[dict], seed: int) -> str:
    """The report: the pooled constants and each pair's."""
    total = pooled(rows)
    lines = [
        "# Constants of the thin-evidence inflation (pgvd.inflation)",
        "",
        f"`python3 -m bench covariance_evidence --pairs {len(rows) // 2} --seed {seed}`: "
        f"{total['pairs']} overlapping pairs of the intel and freiburg-079 logs (development "
        f"data), B's wall cells placed on A by the true matrix; {total['cells']} matched cells.",
        "",
        f"- normal noise s^2 = {total['normal_noise']:.4f} rad^2 "
        f"(rms angle {np.degrees(np.sqrt(total['normal_noise'])):.1f} deg)",
        f"- correlation length ell = {total['correlation_cells']:.2f} cells = "
        f"{total['correlation_m']:.3f} m (residual correlation summed to {total['cut_cells']} "
        f"cells, where it falls below {CORRELATION_CUT})",
        "",
        "Residual correlation of cells on one wall by distance (cells 1-10): "
        + ", ".join(f"{v:.2f}" for v in total["profile"][:10]),
        "",
        "| pair | matched cells | s^2 | ell (cells) | summed to |",
        "|---|---|---|---|---|",
    ]
    for r in rows:
        ell, cut = correlation_cells(
            np.array(r["lag_sums"]), np.array(r["lag_counts"]), r["sum_r2"], r["cells"]
        )
        s2 = normal_noise(r["sum_sin2"] / r["cells"])
        lines.append(f"| {r['name']} | {r['cells']} | {s2:.4f} | {ell:.2f} | {cut} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--pairs", type=int, default=12, help="overlapping pairs per log")
    ap.add_argument("--seed", type=int, default=10)
    ap.add_argument("--out", type=Path, default=RESULTS)
    args = ap.parse_args(argv)
    rows = measure(args.pairs, args.seed)
    text = markdown(rows, args.seed)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "covariance-evidence.md").write_text(text)
    doc = {"seed": args.seed, "rows": rows}
    (args.out / "covariance-evidence.json").write_text(json.dumps(doc))
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
