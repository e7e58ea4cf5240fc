"""Acceptance, heading coverage, drift and ablation of the PGVD merge on development data.

Pair sets (every map in a random frame, true B -> A matrix known):

``standard``  intel and freiburg-079 log pairs (:mod:`bench.pairs`), overlap >= 10 %,
              with their disjoint pairs;
``low``       log pairs with overlap 15-35 %;
``drifted``   log pairs with extra odometry noise (0.01 m/m, 0.002 rad/rad), and
              their disjoint pairs;
``images``    pairs cut from the development map images (two windows of one
              building sharing 20-80 % of the shorter, the second turned), and
              negatives: two halves of a building with a gap between them, a
              building against its own mirror image (a building that does not
              exist), and every building against every other.

Per variant of :class:`pgvd.merge.MergeParams` (the default and the ablations:
without PGVD weighting, without the rho veto (32), without Gamma ranking,
without the heading blur (8)) it reports success (accepted, heading within
2 deg, mean error of B's walls within 3 cells), wrong accepts and false
accepts per set.  For the default it also reports

* how often the true heading (within 2 deg) is among the headings that went
  through matching (``MergeResult.headings_deg``);
* the heading error of the rotation stage against its sigma (eq. (10));
* the margin of the acceptance test (:mod:`pgvd.decision`) of true and
  false hypotheses (``acceptance.png``);
* the residual distortion of accepted rigid and drifted pairs.

Run from the project root::

    python3 -m bench.acceptance --cache /tmp/benchcache            # everything
    python3 -m bench.acceptance --cache /tmp/benchcache --quick    # fewer pairs, default only

Writes ``bench/results/acceptance.md``, ``acceptance.json``, ``acceptance.png``.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from bench.merge import RESULTS, build_pairs, evaluate
from bench.pairs import MapPair
from pgvd.grid import Grid, rigid_matrix
from pgvd.io import read_map
from pgvd.merge import MergeParams, merge
from pgvd.rotation import estimate_headings
from pgvd.transform import resample, warp

ROOT = Path(__file__).resolve().parents[1]
#: Development map images (other buildings are held out and never used here).
IMAGES = {
    "intel": "intel/intel.yaml",
    "fr079": "fr079_albertB/map312.yaml",
    "willow": "willow/willow-2010-02-18-0.10.yaml",
    "ritsumeikan": "ritsumeikan_cc4f/cc4.1.yaml",
    "stata": "mit_stata_basement/stata_basement.yaml",
    "uos_avz": "uos_avz/avz.yaml",
}
VARIANTS = {
    "pgvd": {},
    "without PGVD weighting": {"probabilistic": False},
    "without rho veto": {"rho_veto": False},
    "without Gamma ranking": {"gamma_ranking": False},
    "without heading blur": {"heading_blur": False},
}
#: Overlap shares of the image pairs, alternating the cut direction.
IMAGE_OVERLAPS = (0.6, 0.45, 0.35, 0.8, 0.25, 0.2)


def _log(msg: str) -> None:
    print(msg, flush=True)


def _load_image(rel: str) -> np.ndarray:
    """A development map at 0.05 m, as probabilities, cropped to its known cells."""
    g = read_map(ROOT.parent / "shared" / "maps" / rel)
    if not np.isclose(g.resolution, 0.05):
        g = resample(g, 0.05)
    p = g.probability()
    known = np.abs(p - 0.5) > 0.05
    rows, cols = np.flatnonzero(known.any(axis=1)), np.flatnonzero(known.any(axis=0))
    return p[rows[0] : rows[-1] + 1, cols[0] : cols[-1] + 1]


def _turned(p: np.ndarray, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """``p`` turned by a random angle on a canvas that holds it; returns it and the matrix."""
    h, w = p.shape
    side = int(np.ceil(np.hypot(h, w))) + 20
    m = rigid_matrix(rng.uniform(0.0, 2.0 * np.pi), 0.0, 0.0)
    centre = np.array([(w - 1) / 2.0, (h - 1) / 2.0])
    m[:2, 2] = (side - 1) / 2.0 + rng.uniform(-8.0, 8.0, 2) - m[:2, :2] @ centre
    return warp(p, m, (side, side), order=0, cval=0.5), m


def _grid(p: np.ndarray) -> Grid:
    return Grid.from_probability(np.clip(p, 0.001, 0.999), 0.05)


def _shift(dx: float, dy: float) -> np.ndarray:
    return np.array([[1.0, 0.0, dx], [0.0, 1.0, dy], [0.0, 0.0, 1.0]])


def _windows(p: np.ndarray, share: float, axis: int, rng: np.random.Generator):
    """Two windows of ``p`` along ``axis`` sharing ``share`` of the shorter; with offsets."""
    n = p.shape[axis]
    cut = rng.uniform(0.35, 0.65) * n
    half = share * min(cut, n - cut) / 2.0
    a_end, b_start = int(cut + half), int(cut - half)
    if axis == 1:
        return (p[:, :a_end], _shift(0, 0)), (p[:, b_start:], _shift(-b_start, 0))
    return (p[:a_end], _shift(0, 0)), (p[b_start:], _shift(0, -b_start))


def image_pairs(seed: int, quick: bool) -> list[MapPair]:
    """Positive and negative pairs cut from the development map images."""
    rng = np.random.default_rng(seed)
    maps = {name: _load_image(rel) for name, rel in IMAGES.items()}
    pairs: list[MapPair] = []
    shares = IMAGE_OVERLAPS[:3] if quick else IMAGE_OVERLAPS
    for name, p in maps.items():
        axis = int(p.shape[1] >= p.shape[0])
        for i, share in enumerate(shares):
            (pa, ta), (pb, tb) = _windows(p, share, axis if i % 2 == 0 else 1 - axis, rng)
            turned, m = _turned(pb, rng)
            truth = ta @ np.linalg.inv(tb) @ np.linalg.inv(m)
            pairs.append(MapPair(_grid(pa), _grid(turned), truth, share, f"{name}-img{i}"))
        cut = p.shape[axis] // 2
        near, far = (p[:, : cut - 20], p[:, cut + 20 :]) if axis else (p[: cut - 20], p[cut + 20 :])
        for label, other in (("halves", far), ("mirror", p[:, ::-1]), ("mirror-v", p[::-1])):
            turned, _ = _turned(other, rng)
            first = near if label == "halves" else p
            pairs.append(MapPair(_grid(first), _grid(turned), np.eye(3), 0.0, f"{name}-{label}"))
    if not quick:
        for na, pa in maps.items():
            for nb, pb in maps.items():
                if na != nb:
                    turned, _ = _turned(pb, rng)
                    pairs.append(MapPair(_grid(pa), _grid(turned), np.eye(3), 0.0, f"{na}-vs-{nb}"))
    return pairs


def pair_sets(cache: Path | None, quick: bool) -> dict[str, list[MapPair]]:
    """The four sets of the module docstring; ``quick`` keeps every third pair.

    The log pairs are always drawn as in the full run (so one cache serves both).
    """
    logs = ["intel", "fr079"]
    sets = {
        "standard": build_pairs(logs, 20, 5, 1, 0.05, cache),
        "low": build_pairs(logs, 10, 0, 1, 0.05, cache, band=(0.15, 0.35)),
        "drifted": build_pairs(logs, 10, 3, 1, 0.05, cache, (0.01, 0.002)),
        "images": image_pairs(10, quick),
    }
    if quick:
        sets = {k: v if k == "images" else v[::3] for k, v in sets.items()}
    return sets


def _heading_deg(m: np.ndarray) -> float:
    return float(np.degrees(np.arctan2(m[0, 1], m[0, 0])))


def _angle_gap(a: float, b: float) -> float:
    return abs((a - b + 180.0) % 360.0 - 180.0)


def run_variant(sets: dict[str, list[MapPair]], params: MergeParams, name: str) -> list[dict]:
    """One record per pair: accept, success, margin, distortion, searched headings."""
    records = []
    for set_name, pairs in sets.items():
        for pair in pairs:
            t0 = time.perf_counter()
            r = merge(pair.a, pair.b, params)
            seconds = time.perf_counter() - t0
            rec = evaluate(pair, bool(r.accepted), np.asarray(r.matrix))
            truth = _heading_deg(pair.truth)
            rec.update(
                variant=name,
                set=set_name,
                pair=pair.name,
                overlap=pair.overlap,
                seconds=seconds,
                margin=float(r.margin),
                distortion_px=float(r.distortion_px),
                heading_searched=any(_angle_gap(h, truth) <= 2.0 for h in r.headings_deg),
                reason=r.reason,
            )
            rec["true_pose"] = bool(
                pair.overlap > 0 and rec["heading_deg"] <= 2.0 and rec["cell_err"] <= 3.0
            )
            records.append(rec)
            mark = "ok" if rec["success"] else ("ACC" if r.accepted else "rej")
            _log(f"[{name}] {set_name} {pair.name} ov={pair.overlap:.2f} {mark} m={r.margin:.2f}")
    return records


def rotation_calibration(sets: dict[str, list[MapPair]]) -> dict:
    """Error of the rotation candidate nearest the truth against its sigma (eq. (10))."""
    errors, sigmas, covered, n = [], [], 0, 0
    for pairs in sets.values():
        for pair in pairs:
            if pair.overlap == 0:
                continue
            n += 1
            truth = _heading_deg(pair.truth)
            cands = estimate_headings(pair.a.probability(), pair.b.probability(), 6)
            gaps = [_angle_gap(np.degrees(c.psi), truth) for c in cands]
            i = int(np.argmin(gaps))
            if gaps[i] <= 2.0:
                covered += 1
                errors.append(gaps[i])
                sigmas.append(float(np.degrees(np.sqrt(cands[i].variance))))
    e, s = np.array(errors), np.array(sigmas)
    return {
        "pairs": n,
        "candidate_coverage": covered / n if n else float("nan"),
        "error_rms_deg": float(np.sqrt(np.mean(e**2))),
        "sigma_median_deg": float(np.median(s)),
        "mean_z2": float(np.mean((e / s) ** 2)),
        "inside_2sigma": float(np.mean(e <= 2 * s)),
    }


def _rate(rows: list[dict], key: str) -> str:
    return f"{100 * np.mean([r[key] for r in rows]):.0f} % of {len(rows)}" if rows else "-"


def summary(records: list[dict]) -> list[dict]:
    """Per variant and set: success, wrong accepts, false accepts, median seconds."""
    rows = []
    for variant in dict.fromkeys(r["variant"] for r in records):
        for set_name in dict.fromkeys(r["set"] for r in records):
            mine = [r for r in records if r["variant"] == variant and r["set"] == set_name]
            pos = [r for r in mine if r["overlap"] > 0]
            neg = [r for r in mine if r["overlap"] == 0]
            for r in pos:
                r["wrong"] = r["accepted"] and not r["success"]
            rows.append(
                {
                    "variant": variant,
                    "set": set_name,
                    "success": _rate(pos, "success"),
                    "wrong": _rate(pos, "wrong"),
                    "false": _rate(neg, "accepted"),
                    "median_s": float(np.median([r["seconds"] for r in mine])),
                }
            )
    return rows


def margin_chart(records: list[dict], threshold: float, path: Path) -> None:
    """Histogram of the acceptance margin of true and false winning hypotheses."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    mine = [r for r in records if r["variant"] == "pgvd" and np.isfinite(r["margin"])]
    true = [r["margin"] for r in mine if r["true_pose"]]
    false = [r["margin"] for r in mine if not r["true_pose"]]
    fig, ax = plt.subplots(figsize=(7, 4))
    bins = np.linspace(-3.0, 1.0, 81)
    ax.hist(np.clip(false, -3, 1), bins, alpha=0.6, label=f"false hypotheses ({len(false)})")
    ax.hist(np.clip(true, -3, 1), bins, alpha=0.6, label=f"true hypotheses ({len(true)})")
    ax.axvline(threshold, color="k", ls="--", label=f"threshold {threshold}")
    ax.set_xlabel("margin: (E_win - max(E_rival, 0)) / overlapping wall cells (clipped at -3)")
    ax.set_ylabel("winning hypotheses")
    ax.set_title("acceptance margin, development pairs")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def markdown(command: str, rows: list[dict], records: list[dict], rot: dict, params) -> str:
    """The report."""
    mine = [r for r in records if r["variant"] == "pgvd"]
    pos = [r for r in mine if r["overlap"] > 0]
    true_m = [r["margin"] for r in mine if r["true_pose"]]
    false_m = [r["margin"] for r in mine if not r["true_pose"] and np.isfinite(r["margin"])]
    acc = [r for r in mine if r["accepted"]]
    rigid = [r["distortion_px"] for r in acc if r["set"] in ("standard", "low")]
    drifted = [r["distortion_px"] for r in acc if r["set"] == "drifted"]
    lines = [
        "# Acceptance, heading coverage, drift and ablation",
        "",
        f"`{command}`",
        "",
        "| variant | set | success | wrong accepts | false accepts | median s |",
        "|---|---|---|---|---|---|",
    ]
    lines += [
        f"| {r['variant']} | {r['set']} | {r['success']} | {r['wrong']} | {r['false']} | "
        f"{r['median_s']:.2f} |"
        for r in rows
    ]
    searched = np.mean([r["heading_searched"] for r in pos])
    lines += [
        "",
        f"True heading (within 2 deg) among the headings that went through matching: "
        f"{100 * searched:.1f} % of {len(pos)} overlapping pairs.",
        f"Rotation stage (eq. (10)), {rot['pairs']} overlapping pairs: the truth is within "
        f"2 deg of a candidate in {100 * rot['candidate_coverage']:.1f} %; error of the "
        f"nearest candidate rms {rot['error_rms_deg']:.3f} deg, sigma median "
        f"{rot['sigma_median_deg']:.3f} deg, mean (error/sigma)^2 {rot['mean_z2']:.2f} "
        f"(1 = calibrated), {100 * rot['inside_2sigma']:.0f} % within 2 sigma.",
        f"Margin (threshold {params.min_margin}): true hypotheses min "
        f"{min(true_m, default=np.nan):.2f}, median {np.median(true_m) if true_m else np.nan:.2f}; "
        f"false hypotheses max {max(false_m, default=np.nan):.2f} (n = {len(false_m)}).",
        f"Residual distortion of accepted pairs (px, median / max): rigid "
        f"{np.median(rigid) if rigid else np.nan:.1f} / {max(rigid, default=np.nan):.1f}, "
        f"drifted {np.median(drifted) if drifted else np.nan:.1f} / "
        f"{max(drifted, default=np.nan):.1f}.",
        "",
        "Success: accepted, heading within 2 deg, mean error of B's occupied cells within "
        "3 cells. Wrong: accepted on an overlapping pair outside those bounds. False: "
        "accepted on a pair with no overlap. Times: wall clock, one process, shared machine.",
        "",
    ]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cache", type=Path, default=None, help="pickle the log pairs here")
    parser.add_argument("--quick", action="store_true", help="fewer pairs, default variant only")
    parser.add_argument("--variants", nargs="+", choices=sorted(VARIANTS), default=None)
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args(argv)
    command = "python3 -m bench.acceptance " + " ".join(argv if argv is not None else sys.argv[1:])
    names = args.variants or (["pgvd"] if args.quick else list(VARIANTS))
    if "pgvd" not in names:
        names = ["pgvd", *names]
    sets = pair_sets(args.cache, args.quick)
    rot = rotation_calibration(sets)
    records = []
    for name in names:
        records += run_variant(sets, MergeParams(diagnostics=False, **VARIANTS[name]), name)
    params = MergeParams()
    rows = summary(records)
    args.out.mkdir(parents=True, exist_ok=True)
    text = markdown(command.strip(), rows, records, rot, params)
    (args.out / "acceptance.md").write_text(text)
    doc = {"command": command.strip(), "rows": rows, "rotation": rot, "records": records}
    (args.out / "acceptance.json").write_text(json.dumps(doc, indent=1, default=float) + "\n")
    margin_chart(records, params.min_margin, args.out / "acceptance.png")
    _log(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
