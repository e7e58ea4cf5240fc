"""Does propagating the transform's uncertainty, eqs. (4)-(8), make a chained fusion truer?

    python3 -m bench propagation [--hops 3 5] [--starts 8]

A real chain: consecutive, half-overlapping segments of the intel and
freiburg-079 logs are robots R0, R1, ..., Rk, each map in its own random
frame.  Each link R(i+1) -> Ri is merged (:func:`pgvd.merge.merge`); the
links are composed into Rk -> R0 with their covariances
(:func:`pgvd.uncertainty.compose_covariance`), and Rk is fused into R0
(:func:`pgvd.fusion.fuse_maps`) twice: with propagation (8) and without (a
plain warp).

Measure: the cross-entropy (nats per cell) of the fused map's probability
against the true-frame map of Rk: Rk's scans ray-cast at their true poses
straight into R0's frame (labels: occupied where its probability > 0.5, else
free), over the cells that map knows (|p - 0.5| > 0.15), also split into
wall and free cells; lower is truer.  Writes
``bench/results/propagation.md`` and ``propagation.json``.
"""

from __future__ import annotations

import argparse
import itertools
import json
import sys
from pathlib import Path

import numpy as np

from bench.data.pairs import random_frame, true_matrix
from pgvd.carmen import LaserScan, read_carmen
from pgvd.fusion import fuse_maps
from pgvd.grid import Grid, relative_matrix
from pgvd.integrate import MapFrame, frame_for, integrate, select_segment
from pgvd.merge import merge
from pgvd.params import MergeParams
from pgvd.uncertainty import compose_covariance

ROOT = Path(__file__).resolve().parents[2]
SHARED = ROOT.parent / "shared"
RESULTS = ROOT / "bench" / "results"
LOGS = {"intel": "intel-corrected.log.gz", "fr079": "freiburg-079-corrected.log.gz"}
#: Each segment's share of the log; consecutive segments overlap by half of it.
SEGMENT = 0.12
#: Reference cells: known under the truth (probability this far from 0.5).
KNOWN = 0.15


def robots(
    scans: list[LaserScan], start: float, hops: int, seed: int
) -> list[tuple[Grid, np.ndarray, list[LaserScan]]]:
    """``hops + 1`` maps of consecutive half-overlapping segments, each in a random frame.

    Each robot is its map, its world-to-map transform and its scans.
    """
    rng = np.random.default_rng(seed)
    out = []
    for i in range(hops + 1):
        lo = start + i * SEGMENT / 2
        part = select_segment(scans, (lo, lo + SEGMENT))
        transform = random_frame(rng)
        out.append((integrate(part, frame_for(part, 0.05, transform)), transform, part))
    return out


def compose_chain(maps: list[Grid]) -> tuple[np.ndarray, np.ndarray] | None:
    """Merge every link and compose them into last -> first, with covariance; None if one fails."""
    params = MergeParams(diagnostics=False)
    matrix, cov = np.eye(3), np.zeros((3, 3))
    for a, b in itertools.pairwise(maps):
        r = merge(a, b, params)
        if not r.accepted:
            return None
        cov = compose_covariance(matrix, cov, r.matrix, r.covariance)
        matrix = matrix @ r.matrix
    return matrix, cov


def cross_entropy(p: np.ndarray, label: np.ndarray) -> float:
    """Mean binary cross-entropy (nats) of probabilities ``p`` against bool labels."""
    p = np.clip(p.astype(np.float64), 1e-9, 1 - 1e-9)
    return float(-np.mean(np.where(label, np.log(p), np.log1p(-p))))


def truth_frame_map(scans: list[LaserScan], a_from_world: np.ndarray, canvas: Grid) -> Grid:
    """The scans ray-cast at their true poses straight into ``canvas``'s cells (A's frame)."""
    frame = MapFrame(canvas.resolution, canvas.shape, a_from_world, canvas.origin[:2])
    return integrate(scans, frame)


def score(
    a: Grid, d: Grid, truth_d: Grid, est: np.ndarray, cov: np.ndarray
) -> dict[str, dict[str, float]]:
    """Cross-entropies of the fusion of ``d`` into ``a`` at ``est``, with and without (8).

    ``truth_d`` is Rk's scans rendered at their true poses in A's frame, on a
    canvas that is A shifted by whole cells (as every fused map is).
    """
    p_true = truth_d.probability()
    known = np.abs(p_true - 0.5) > KNOWN
    label = p_true > 0.5
    out = {}
    for name, prop in (("with", True), ("without", False)):
        fused = fuse_maps(a, d, est, cov, propagation=prop)
        # both canvases hold A at whole-cell offsets: truth cell (r, c) is (r + dy, c + dx)
        dx, dy = np.rint(relative_matrix(fused, truth_d)[:2, 2]).astype(int)
        p = np.full(truth_d.shape, 0.5)
        pf = fused.probability()
        rows = slice(max(0, -dy), min(p.shape[0], pf.shape[0] - dy))
        cols = slice(max(0, -dx), min(p.shape[1], pf.shape[1] - dx))
        p[rows, cols] = pf[rows.start + dy : rows.stop + dy, cols.start + dx : cols.stop + dx]
        out[name] = {
            "all": cross_entropy(p[known], label[known]),
            "walls": cross_entropy(p[known & label], label[known & label]),
            "free": cross_entropy(p[known & ~label], label[known & ~label]),
        }
    return out


def run(logs: list[str], hops_list: list[int], n_starts: int, seed: int) -> list[dict]:
    """Every chain of every log: its composed error and both cross-entropies."""
    from bench.covariance import nees, pose_error

    records = []
    for log in logs:
        scans = read_carmen(SHARED / "logs" / LOGS[log])
        for hops in hops_list:
            span = SEGMENT * (1 + hops / 2)
            for k, start in enumerate(np.linspace(0.0, 1.0 - span, n_starts)):
                chain = robots(scans, float(start), hops, seed + 100 * hops + k)
                maps = [g for g, _, _ in chain]
                rec = {"log": log, "hops": hops, "start": round(float(start), 4)}
                found = compose_chain(maps)
                if found is None:
                    rec["accepted"] = False
                    records.append(rec)
                    print(f"{log} hops {hops} start {start:.3f}: a link was rejected", flush=True)
                    continue
                est, cov = found
                (a, ta, _), (d, td, d_scans) = chain[0], chain[-1]
                truth = true_matrix(a, ta, d, td)
                canvas = fuse_maps(a, d, truth, np.zeros((3, 3)), propagation=False)
                truth_d = truth_frame_map(d_scans, ta, canvas)
                err = pose_error(truth, est)
                rec.update(
                    accepted=True,
                    error=err.tolist(),
                    sigma=np.sqrt(np.diag(cov)).tolist(),
                    nees=float(nees(err[None], cov[None])[0]),
                    cross_entropy=score(a, d, truth_d, est, cov),
                )
                records.append(rec)
                ce = rec["cross_entropy"]
                print(
                    f"{log} hops {hops} start {start:.3f}: NEES {rec['nees']:.2f} "
                    f"CE with {ce['with']['all']:.4f} without {ce['without']['all']:.4f}",
                    flush=True,
                )
    return records


def summarise(records: list[dict]) -> dict:
    """Per hop count: chains, mean cross-entropies, and how many chains propagation improved."""
    out = {}
    for hops in sorted({r["hops"] for r in records}):
        done = [r for r in records if r["hops"] == hops and r["accepted"]]
        row = {"chains": sum(r["hops"] == hops for r in records), "composed": len(done)}
        if done:
            for part in ("all", "walls", "free"):
                w = np.array([r["cross_entropy"]["with"][part] for r in done])
                wo = np.array([r["cross_entropy"]["without"][part] for r in done])
                row[part] = {"with": float(w.mean()), "without": float(wo.mean())}
                if part == "all":
                    row["improved"] = int(np.sum(w < wo))
            row["mean_nees"] = float(np.mean([r["nees"] for r in done]))
        out[str(hops)] = row
    return out


def gain(record: dict) -> float:
    """Per cent by which (8) lowers a chain's cross-entropy (negative: raises it)."""
    ce = record["cross_entropy"]
    return 100 * (1 - ce["with"]["all"] / ce["without"]["all"])


#: Bins (pixels) of the composed pose's translation error for :func:`by_error`.
ERROR_BINS_PX = (0.0, 1.0, 2.0, np.inf)


def by_error(records: list[dict]) -> list[str]:
    """The gain of (8) by how far the composed pose is from the truth.

    Propagation blurs B by its pose uncertainty: that pays where the pose is
    off by about that much and costs a little sharpness where it is right, so
    its average over chains hides where it helps.
    """
    rows = [
        "| translation error of the composed pose (px) | chains | mean CE gain of (8) "
        "| chains improved |",
        "|---|---|---|---|",
    ]
    done = [r for r in records if r["accepted"]]
    for lo, hi in itertools.pairwise(ERROR_BINS_PX):
        group = [r for r in done if lo <= np.hypot(*r["error"][:2]) < hi]
        if not group:
            continue
        gains = [gain(r) for r in group]
        label = f"{lo:g} or more" if np.isinf(hi) else f"{lo:g}-{hi:g}"
        improved = sum(g > 0 for g in gains)
        rows.append(f"| {label} | {len(group)} | {np.mean(gains):.1f} % | {improved} |")
    return rows


def chain_rows(records: list[dict]) -> list[str]:
    """One table row per composed chain: the gain of (8) beside the chain's real error."""
    rows = [
        "| log | hops | start | CE gain of (8) | translation error (px) | heading error (deg) "
        "| heading sigma (deg) |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in records:
        if not r["accepted"]:
            continue
        e = r["error"]
        rows.append(
            f"| {r['log']} | {r['hops']} | {r['start']} | {gain(r):.1f} % "
            f"| {np.hypot(e[0], e[1]):.2f} | {np.degrees(abs(e[2])):.3f} "
            f"| {np.degrees(r['sigma'][2]):.3f} |"
        )
    return rows


def markdown(summary: dict, records: list[dict], command: str) -> str:
    """The report: summary table, conclusions, one row per chain."""
    lines = [
        "# Propagation (4)-(8) on chained links",
        "",
        f"`{command}`",
        "",
        "Cross-entropy (nats per cell, lower is truer) of the fused map R0 + Rk against Rk's "
        "scans ray-cast at their true poses in R0's frame, over the cells they know; Rk -> R0 "
        "composed from k merged links (consecutive half-overlapping segments of the intel and "
        "freiburg-079 logs) with their calibrated covariances. 'without' is "
        "`fuse_maps(..., propagation=False)`, a plain bilinear warp.",
        "",
        "| hops | chains | composed | CE with (8) | CE without | walls with / without "
        "| free with / without | chains improved | mean NEES of the composed pose |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for hops, r in summary.items():
        if "all" not in r:
            lines.append(f"| {hops} | {r['chains']} | 0 | - | - | - | - | - | - |")
            continue
        lines.append(
            f"| {hops} | {r['chains']} | {r['composed']} | {r['all']['with']:.4f} "
            f"| {r['all']['without']:.4f} | {r['walls']['with']:.3f} / {r['walls']['without']:.3f} "
            f"| {r['free']['with']:.4f} / {r['free']['without']:.4f} "
            f"| {r['improved']} of {r['composed']} | {r['mean_nees']:.2f} |"
        )
    lines.append("")
    for hops, r in summary.items():
        if "all" in r:
            mean_gain = 100 * (1 - r["all"]["with"] / r["all"]["without"])
            lines.append(
                f"- {hops} hops: propagation lowers the mean cross-entropy by {mean_gain:.1f} % "
                f"(negative: raises it); it is lower with (8) in {r['improved']} of "
                f"{r['composed']} chains."
            )
    lines += ["", *by_error(records), "", *chain_rows(records)]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--logs", nargs="+", choices=sorted(LOGS), default=list(LOGS))
    ap.add_argument("--hops", type=int, nargs="+", default=[3, 5])
    ap.add_argument("--starts", type=int, default=8, help="chains per log and hop count")
    ap.add_argument("--seed", type=int, default=20)
    ap.add_argument("--out", type=Path, default=RESULTS)
    args = ap.parse_args(argv)
    # made before the long run, so that a path that cannot be written fails at once
    args.out.mkdir(parents=True, exist_ok=True)
    records = run(args.logs, args.hops, args.starts, args.seed)
    summary = summarise(records)
    command = "python3 -m bench propagation " + " ".join(argv if argv is not None else sys.argv[1:])
    (args.out / "propagation.json").write_text(
        json.dumps({"summary": summary, "records": records}, indent=2) + "\n"
    )
    (args.out / "propagation.md").write_text(markdown(summary, records, command.strip()))
    print(markdown(summary, records, command.strip()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
