"""The three gmapping runs of fr079_albertB, against each other, as real independently built maps.

The runs (map312, map342, map371) were built by gmapping with different
parameters from the same Albert-B log of building 079, and share one YAML
origin, ``(-30, -20, 0)``: gmapping starts every run at the log's first pose,
so their metric frames coincide.  The truth is therefore the identity of the
metric frames (:func:`pgvd.grid.relative_matrix`), and it was checked, not
assumed (``python3 -m bench gmapping`` redoes it, with a picture):

* an exhaustive search of rigid fits of B's walls onto A's (chamfer distance,
  +-2 deg in 0.1 deg and +-8 cells in 0.5 cells, then 0.01 deg / 0.05 cells
  around the best; ``bench/results/gmapping_truth.md``) finds map371 onto
  map342 at exactly the identity (their right halves alone: 0.32 deg, 0.4 cells);
* map312 sits on both others at exactly the identity on the right half of the
  building, but its left wing is bent by about 1 deg -- a mapping error of
  that run -- so a fit of the whole map settles at -0.64 / -0.72 deg and about
  a cell away.  Pairs with map312 are real maps with real distortion; a merge
  that aligns them within 2 deg and 3 cells of the identity is a success.

Each pair is cropped to its known cells (plus a margin) and each map is
turned by a random angle (nearest-neighbour resampling keeps the cell values
as they are) into a canvas that holds it whole.
"""

from __future__ import annotations

import argparse
import itertools
from pathlib import Path

import numpy as np
from scipy import ndimage

from bench.data.pairs import MapPair, overlap_fraction, turn_about
from pgvd.grid import Grid, relative_matrix, rigid_matrix
from pgvd.io import read_map
from pgvd.transform import warp

ROOT = Path(__file__).resolve().parents[2]
SHARED = ROOT.parent / "shared"
RUNS = ("map312", "map342", "map371")
#: Unknown border kept around the known cells of a run, cells.
MARGIN = 20


def load(shared: Path = SHARED) -> dict[str, Grid]:
    """The three runs, in their shared metric frame."""
    return {r: read_map(shared / "maps" / "fr079_albertB" / f"{r}.yaml") for r in RUNS}


def _place(grid: Grid, psi: float) -> tuple[Grid, np.ndarray]:
    """The grid cropped to its known cells and turned by ``psi``; and old pixel -> new pixel."""
    rows, cols = np.nonzero(grid.logodds != 0)
    r0, c0 = max(0, rows.min() - MARGIN), max(0, cols.min() - MARGIN)
    r1 = min(grid.shape[0], rows.max() + MARGIN + 1)
    c1 = min(grid.shape[1], cols.max() + MARGIN + 1)
    h, w = r1 - r0, c1 - c0
    side = int(np.ceil(np.hypot(h, w))) + 2
    turn = rigid_matrix(psi, 0.0, 0.0)
    centre = np.array([(w - 1) / 2.0, (h - 1) / 2.0])
    turn[:2, 2] = (side - 1) / 2.0 - turn[:2, :2] @ centre
    crop = np.array([[1.0, 0.0, -c0], [0.0, 1.0, -r0], [0.0, 0.0, 1.0]])
    lo = warp(grid.logodds[r0:r1, c0:c1], turn, (side, side), order=0, cval=0.0)
    return Grid(lo.astype(np.float32), grid.resolution), turn @ crop


def gmapping_pairs(n: int, seed: int, shared: Path = SHARED) -> list[MapPair]:
    """``n`` pairs of different runs (ordered pairs in turn), each map turned at random."""
    runs = load(shared)
    rng = np.random.default_rng(seed)
    order = list(itertools.permutations(RUNS, 2))
    out = []
    for i in range(n):
        a_name, b_name = order[i % len(order)]
        a, to_a = _place(runs[a_name], rng.uniform(0.0, 2.0 * np.pi))
        b, to_b = _place(runs[b_name], rng.uniform(0.0, 2.0 * np.pi))
        truth = to_a @ relative_matrix(runs[a_name], runs[b_name]) @ np.linalg.inv(to_b)
        info = {"kind": "gmapping", "a": a_name, "b": b_name, "seed": seed}
        out.append(
            MapPair(
                a, b, truth, overlap_fraction(a, b, truth), f"gmap-{a_name}-{b_name}-{i:02d}", info
            )
        )
    return out


# ----------------------------------------------------------------------------- the check


def _walls(g: Grid) -> np.ndarray:
    return g.probability() > 0.65


def _chamfer(dist_a: np.ndarray, pts: np.ndarray, m: np.ndarray) -> float:
    """Mean distance (cells, capped at 3) of B's wall points through ``m`` to A's walls."""
    q = pts @ m[:2, :2].T + m[:2, 2]
    d = ndimage.map_coordinates(dist_a, [q[:, 1], q[:, 0]], order=1, mode="nearest")
    return float(np.minimum(d, 3.0).mean())


def best_fit(a: Grid, b: Grid, pts_mask: np.ndarray | None = None) -> tuple[float, float, float]:
    """Exhaustive rigid fit of B's walls onto A's near the identity: (deg, tx, ty) in cells.

    The rotation is about the centroid of B's walls; ``pts_mask`` selects a part of them.
    """
    dist_a = ndimage.distance_transform_edt(~_walls(a))
    rows, cols = np.nonzero(_walls(b))
    pts = np.column_stack([cols, rows]).astype(np.float64)
    centre = pts.mean(axis=0)
    if pts_mask is not None:
        pts = pts[pts_mask(pts, centre)]
    best = (np.inf, (0.0, 0.0, 0.0))
    for grid in (
        (np.arange(-2.0, 2.01, 0.1), np.arange(-8.0, 8.01, 0.5)),
        (np.arange(-0.1, 0.101, 0.01), np.arange(-0.5, 0.51, 0.05)),
    ):
        psi0, tx0, ty0 = best[1]
        for psi, tx, ty in itertools.product(grid[0] + psi0, grid[1] + tx0, grid[1] + ty0):
            score = _chamfer(dist_a, pts, turn_about(psi, centre, (tx, ty)))
            if score < best[0]:
                best = (score, (float(psi), float(tx), float(ty)))
    return best[1]


def main(argv: list[str] | None = None) -> int:
    """Check the truth of the three runs; write ``gmapping_truth.md`` and ``.png``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    parser = argparse.ArgumentParser(description=main.__doc__)
    parser.add_argument("--out", type=Path, default=ROOT / "bench" / "results")
    args = parser.parse_args(argv)
    runs = load()
    lines = [
        "# fr079_albertB gmapping runs: the true relative transform",
        "",
        "`python3 -m bench gmapping`",
        "",
        "Best rigid fit of B's walls onto A's near the identity (chamfer, rotation about "
        "the centroid of B's walls), whole map and right half (x >= centroid) only.",
        "",
        "| A | B | whole map: deg, tx, ty (cells) | right half: deg, tx, ty |",
        "|---|---|---|---|",
    ]
    for a, b in itertools.combinations(RUNS, 2):
        whole = best_fit(runs[a], runs[b])
        right = best_fit(runs[a], runs[b], lambda p, c: p[:, 0] >= c[0])
        lines.append(
            f"| {a} | {b} | {whole[0]:.2f}, {whole[1]:.2f}, {whole[2]:.2f} "
            f"| {right[0]:.2f}, {right[1]:.2f}, {right[2]:.2f} |"
        )
        print(lines[-1], flush=True)
    a, b = runs["map312"], runs["map342"]
    rows, cols = np.nonzero(a.logodds != 0)
    view = (slice(rows.min(), rows.max() + 1), slice(cols.min(), cols.max() + 1))
    wb = warp(_walls(b).astype(np.float32), np.eye(3), a.shape, order=0) > 0.5
    img = np.ones((*a.shape, 3))
    img[_walls(a)] = (1.0, 0.0, 0.0)
    img[wb] = (0.0, 0.0, 1.0)
    img[_walls(a) & wb] = (0.0, 0.0, 0.0)
    fig, ax = plt.subplots(figsize=(14, 6))
    ax.imshow(img[view])
    ax.set_title("map312 (red) and map342 (blue) at the identity (same YAML origin); black: both")
    fig.tight_layout()
    args.out.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.out / "gmapping_truth.png", dpi=90)
    plt.close(fig)
    (args.out / "gmapping_truth.md").write_text("\n".join(lines) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
