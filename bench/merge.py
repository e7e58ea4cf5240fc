"""Merge benchmark: pgvd against the methods people use, side by side on the same real pairs.

Pairs come from two segments of the corrected intel and freiburg-079 logs
(:mod:`pgvd.pairs`), each map in its own random frame, with the true B -> A
matrix.  Every method runs on every pair in this one process:

``pgvd``        this project's merge (:func:`pgvd.merge.merge`);
``pgvd-det``    the paper's deterministic variant (Gamma_det, plain GVD):
                ``MergeParams(probabilistic=False)``;
``m-explore``   multirobot_map_merge's AKAZE + affine RANSAC pipeline (OpenCV);
``hough``       Carpin's Hough-spectrum merging;
``exhaustive``  every heading at 1 degree + FFT cross-correlation (reference).

Success on an overlapping pair: accepted, heading within 2 degrees and mean
error of B's occupied cells within 3 cells.  A false accept: any accept on a
pair with no overlap.  Times are wall-clock per merge in this process.  Time
scaling uses one intel pair rendered at ~500^2 cells and upsampled (nearest,
x2 and x4, so the content is identical) to ~1000^2 and ~2000^2.

Run from the project root::

    python3 -m bench.merge                       # full: 20+5 pairs per log
    python3 -m bench.merge --overlap 2 --disjoint 1 --logs intel --no-scaling

Writes ``bench/results/merge.md``, ``merge.png`` and ``merge.json``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import pickle
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from pgvd.carmen import read_carmen
from pgvd.grid import Grid, heading
from pgvd.pairs import (
    DISJOINT_LENGTHS,
    MIN_OVERLAP,
    OVERLAP_LENGTHS,
    MapPair,
    make_pair,
    make_pairs,
)

ROOT = Path(__file__).resolve().parents[1]
LOGS = {"intel": "intel-corrected.log.gz", "fr079": "freiburg-079-corrected.log.gz"}
RESULTS = ROOT / "bench" / "results"
#: Success thresholds of issue 3.
MAX_HEADING_DEG = 2.0
MAX_CELL_ERROR = 3.0
#: The paper's reported time per merge, seconds (10 to 13 s).
PAPER_SECONDS = (10.0, 13.0)
#: Cell size of the scaling pair: intel at 0.07 m is ~500 cells per side.
SCALE_RESOLUTION = 0.07

Method = Callable[[Grid, Grid], tuple[bool, np.ndarray]]


def _pgvd(**overrides) -> Method:
    from pgvd.merge import MergeParams, merge

    params = MergeParams(diagnostics=False, **overrides)

    def run(a: Grid, b: Grid) -> tuple[bool, np.ndarray]:
        result = merge(a, b, params)
        return bool(result.accepted), np.asarray(result.matrix)

    return run


def _baseline(module: str, **kwargs) -> Method:
    import importlib

    merge = importlib.import_module(f"bench.baselines.{module}").merge

    def run(a: Grid, b: Grid) -> tuple[bool, np.ndarray]:
        result = merge(a, b, **kwargs)
        return bool(result.accepted), result.matrix

    return run


def methods(exhaustive_step: float = 1.0, exhaustive_coarse: int = 4) -> dict[str, Method]:
    """The methods of the table, in column order."""
    out: dict[str, Method] = {"pgvd": _pgvd(), "pgvd-det": _pgvd(probabilistic=False)}
    out["m-explore"] = _baseline("mexplore")
    out["hough"] = _baseline("hough")
    out["exhaustive"] = _baseline("exhaustive", step_deg=exhaustive_step, coarse=exhaustive_coarse)
    return out


def errors(pair: MapPair, matrix: np.ndarray) -> tuple[float, float]:
    """Heading error (deg) and mean cell error of B's occupied cells against the truth."""
    truth = pair.truth
    dpsi = heading(matrix) - heading(truth)
    heading_error = abs(np.degrees((dpsi + np.pi) % (2 * np.pi) - np.pi))
    rows, cols = np.nonzero(pair.b.logodds > 0)
    pts = np.vstack([cols, rows, np.ones_like(rows)]).astype(np.float64)
    cell = float(np.mean(np.linalg.norm((matrix @ pts - truth @ pts)[:2], axis=0)))
    return float(heading_error), cell


def evaluate(pair: MapPair, accepted: bool, matrix: np.ndarray, cell_scale: float = 1.0) -> dict:
    """One row of the per-pair record: accept, errors (cells / ``cell_scale``) and success."""
    heading, cell = errors(pair, matrix)
    cell /= cell_scale
    overlapping = pair.overlap > 0
    ok = accepted and overlapping and heading <= MAX_HEADING_DEG and cell <= MAX_CELL_ERROR
    return {"accepted": accepted, "heading_deg": heading, "cell_err": cell, "success": ok}


def _log(msg: str) -> None:
    print(msg, flush=True)


def build_pairs(
    logs: list[str],
    n_overlap: int,
    n_disjoint: int,
    seed: int,
    resolution: float,
    cache: Path | None,
    odom_noise: tuple[float, float] | None = None,
    band: tuple[float, float] = (MIN_OVERLAP, 1.0),
) -> list[MapPair]:
    """The bench pairs of every log, optionally cached (pickle) between runs."""
    shared = ROOT.parent / "shared" / "logs"
    pairs: list[MapPair] = []
    for name in logs:
        lengths = f"{OVERLAP_LENGTHS}-{DISJOINT_LENGTHS}-{band}"
        key = f"{name}-{n_overlap}-{n_disjoint}-{seed}-{resolution}-{odom_noise}-{lengths}.pkl"
        if cache is not None and (cache / key).exists():
            pairs += pickle.loads((cache / key).read_bytes())
            _log(f"[pairs] {name}: loaded from {cache / key}")
            continue
        t0 = time.perf_counter()
        scans = read_carmen(shared / LOGS[name])
        _log(f"[pairs] {name}: {len(scans)} scans; rendering {n_overlap}+{n_disjoint} pairs")
        made = make_pairs(
            scans, n_overlap, n_disjoint, seed, name, resolution, odom_noise, overlap_band=band
        )
        for p in made:
            _log(f"[pairs]   {p.name}: {p.a.shape} {p.b.shape} overlap {p.overlap:.2f}")
        _log(f"[pairs] {name}: done in {time.perf_counter() - t0:.0f} s")
        if cache is not None:
            cache.mkdir(parents=True, exist_ok=True)
            (cache / key).write_bytes(pickle.dumps(made))
        pairs += made
    return pairs


def run_pairs(pairs: list[MapPair], table: dict[str, Method]) -> list[dict]:
    """Every method on every pair; one record per (pair, method)."""
    records = []
    for i, pair in enumerate(pairs, 1):
        line = []
        for name, method in table.items():
            t0 = time.perf_counter()
            accepted, matrix = method(pair.a, pair.b)
            seconds = time.perf_counter() - t0
            rec = evaluate(pair, accepted, matrix)
            rec.update(pair=pair.name, overlap=pair.overlap, method=name, seconds=seconds)
            rec["cells"] = int(np.sqrt(pair.a.logodds.size * pair.b.logodds.size))
            records.append(rec)
            mark = "ok" if rec["success"] else ("ACC" if accepted else "rej")
            line.append(f"{name} {mark} {seconds:.2f}s")
        _log(f"[merge] {i}/{len(pairs)} {pair.name} ov={pair.overlap:.2f}: " + " | ".join(line))
    return records


def upsample(pair: MapPair, factor: int) -> MapPair:
    """The same pair at ``factor`` x the cells per axis (nearest), truth rescaled."""
    if factor == 1:
        return pair
    s = np.array([[factor, 0.0, (factor - 1) / 2], [0.0, factor, (factor - 1) / 2], [0, 0, 1.0]])

    def up(g: Grid) -> Grid:
        lo = np.repeat(np.repeat(g.logodds, factor, axis=0), factor, axis=1)
        return Grid(lo, g.resolution / factor, g.origin)

    return dataclasses.replace(
        pair,
        a=up(pair.a),
        b=up(pair.b),
        truth=s @ pair.truth @ np.linalg.inv(s),
        name=f"{pair.name}-x{factor}",
    )


def run_scaling(table: dict[str, Method], seed: int, repeats: int) -> list[dict]:
    """Time per merge of one intel pair at ~500^2, ~1000^2 and ~2000^2 cells."""
    scans = read_carmen(ROOT.parent / "shared" / "logs" / LOGS["intel"])
    base = make_pair(
        scans, (0.0, 0.55), (0.45, 1.0), seed, resolution=SCALE_RESOLUTION, name="intel-scale"
    )
    records = []
    for factor in (1, 2, 4):
        pair = upsample(base, factor)
        cells = int(np.sqrt(pair.a.logodds.size))
        for name, method in table.items():
            times = []
            for _ in range(repeats):
                t0 = time.perf_counter()
                accepted, matrix = method(pair.a, pair.b)
                times.append(time.perf_counter() - t0)
            # Success judged in cells of the ~500^2 base map: upsampling scales pixel errors.
            rec = evaluate(pair, accepted, matrix, cell_scale=factor)
            rec.update(method=name, cells=cells, seconds=float(np.median(times)))
            records.append(rec)
            _log(f"[scale] {cells}^2 {name}: {rec['seconds']:.2f} s success={rec['success']}")
    return records


def summarise(records: list[dict], scaling: list[dict], names: list[str]) -> list[dict]:
    """Per-method numbers of the table."""
    rows = []
    for name in names:
        mine = [r for r in records if r["method"] == name]
        ov = [r for r in mine if r["overlap"] > 0]
        ov30 = [r for r in ov if r["overlap"] >= 0.3]
        dj = [r for r in mine if r["overlap"] == 0]
        good = [r for r in ov if r["success"]]
        secs = np.array([r["seconds"] for r in mine]) if mine else np.array([np.nan])
        row = {
            "method": name,
            "n_overlap": len(ov),
            "n_overlap30": len(ov30),
            "n_disjoint": len(dj),
            "success": np.mean([r["success"] for r in ov]) if ov else np.nan,
            "success30": np.mean([r["success"] for r in ov30]) if ov30 else np.nan,
            "false_accept": np.mean([r["accepted"] for r in dj]) if dj else np.nan,
            "wrong_accept": np.mean([r["accepted"] and not r["success"] for r in ov])
            if ov
            else np.nan,
            "heading_deg": np.median([r["heading_deg"] for r in good]) if good else np.nan,
            "cell_err": np.median([r["cell_err"] for r in good]) if good else np.nan,
            "median_s": float(np.median(secs)),
            "p95_s": float(np.percentile(secs, 95)),
        }
        for r in scaling:
            if r["method"] == name:
                row[f"t{r['cells']}"] = r["seconds"]
        rows.append(row)
    return rows


def _fmt(v: float, pct: bool = False, digits: int = 2) -> str:
    if v is None or (isinstance(v, float) and np.isnan(v)):
        return "-"
    return f"{100 * v:.0f} %" if pct else f"{v:.{digits}f}"


def markdown(rows: list[dict], command: str, scale_cells: list[int], notes: list[str]) -> str:
    """The results table as markdown."""
    head = [
        "method",
        "success (all ov.)",
        "success (ov. >= 30 %)",
        "false accepts (disjoint)",
        "wrong accepts (ov.)",
        "median heading err (deg)",
        "median cell err",
        "median s",
        "p95 s",
    ] + [f"s @ {c}^2" for c in scale_cells]
    lines = [
        "# Merge benchmark",
        "",
        f"`{command}`",
        "",
        "| " + " | ".join(head) + " |",
        "|" + "---|" * len(head),
    ]
    for r in rows:
        cells = [
            r["method"],
            f"{_fmt(r['success'], True)} of {r['n_overlap']}",
            f"{_fmt(r['success30'], True)} of {r['n_overlap30']}",
            f"{_fmt(r['false_accept'], True)} of {r['n_disjoint']}",
            _fmt(r["wrong_accept"], True),
            _fmt(r["heading_deg"]),
            _fmt(r["cell_err"]),
            _fmt(r["median_s"]),
            _fmt(r["p95_s"]),
        ] + [_fmt(r.get(f"t{c}", np.nan)) for c in scale_cells]
        lines.append("| " + " | ".join(cells) + " |")
    lines += ["", *notes, ""]
    return "\n".join(lines)


def chart(rows: list[dict], records: list[dict], scaling: list[dict], path: Path) -> None:
    """Success / false-accept bars, time per merge, and time against map size."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = [r["method"] for r in rows]
    fig, axes = plt.subplots(1, 3, figsize=(15, 4.5))
    x = np.arange(len(names))
    axes[0].bar(x - 0.27, [r["success"] for r in rows], 0.27, label="success (overlapping)")
    axes[0].bar(x, [r["wrong_accept"] for r in rows], 0.27, label="wrong pose accepted")
    axes[0].bar(x + 0.27, [r["false_accept"] for r in rows], 0.27, label="accepted (disjoint)")
    axes[0].set_xticks(x, names, rotation=20)
    axes[0].set_ylim(0, 1.25)
    axes[0].legend(loc="upper right", fontsize=8, ncol=3)
    axes[0].set_title("accuracy on real pairs")
    axes[1].boxplot(
        [[r["seconds"] for r in records if r["method"] == n] for n in names], tick_labels=names
    )
    axes[1].set_yscale("log")
    axes[1].axhspan(*PAPER_SECONDS, color="grey", alpha=0.3, label="paper: 10-13 s")
    axes[1].set_ylabel("seconds per merge")
    axes[1].legend(fontsize=8)
    axes[1].tick_params(axis="x", rotation=20)
    axes[1].set_title("time per merge")
    for n in names:
        pts = sorted((r["cells"], r["seconds"]) for r in scaling if r["method"] == n)
        if pts:
            axes[2].loglog(*zip(*pts, strict=True), "o-", label=n)
    axes[2].set_xlabel("cells per side")
    axes[2].set_ylabel("seconds per merge")
    if scaling:
        axes[2].legend(fontsize=8)
    axes[2].set_title("time vs map size")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--logs", nargs="+", choices=sorted(LOGS), default=["intel", "fr079"])
    parser.add_argument("--overlap", type=int, default=20, help="overlapping pairs per log")
    parser.add_argument("--disjoint", type=int, default=5, help="disjoint pairs per log")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--resolution", type=float, default=0.05)
    parser.add_argument("--exhaustive-step", type=float, default=1.0, help="degrees")
    parser.add_argument("--exhaustive-coarse", type=int, default=4, help="pooling factor")
    parser.add_argument("--no-scaling", action="store_true", help="skip the map-size run")
    parser.add_argument("--repeats", type=int, default=1, help="timing repeats per size")
    parser.add_argument(
        "--odom-noise",
        type=float,
        nargs=2,
        metavar=("M_PER_M", "RAD_PER_RAD"),
        help="extra odometry noise on both robots (pgvd.integrate.perturb_odometry)",
    )
    parser.add_argument(
        "--overlap-band",
        type=float,
        nargs=2,
        default=(MIN_OVERLAP, 1.0),
        metavar=("LO", "HI"),
        help="overlap fraction range of the overlapping pairs",
    )
    parser.add_argument("--cache", type=Path, default=None, help="pickle the pairs here")
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args(argv)
    command = "python3 -m bench.merge " + " ".join(argv if argv is not None else sys.argv[1:])

    table = methods(args.exhaustive_step, args.exhaustive_coarse)
    notes = [
        f"Pairs: segments of {', '.join(args.logs)} (pgvd.pairs, seed {args.seed}, "
        f"{args.resolution} m cells, extra odometry noise {args.odom_noise}, overlap of "
        f"the overlapping pairs in {list(args.overlap_band)}), each map in its own random frame.",
        "Success: accepted, heading within 2 deg and mean error of B's occupied cells "
        "within 3 cells. Errors are medians over successes. Times: wall clock, one process.",
        "Wrong accepts: accepted on an overlapping pair with a pose outside those bounds.",
    ]
    if not args.no_scaling:
        notes.append(
            f"Scaling: one intel pair at {SCALE_RESOLUTION} m (~500^2), upsampled x2 and x4 "
            "(nearest: same content, more cells); success there in cells of the base map."
        )
    noise = tuple(args.odom_noise) if args.odom_noise else None
    pairs = build_pairs(
        args.logs,
        args.overlap,
        args.disjoint,
        args.seed,
        args.resolution,
        args.cache,
        noise,
        tuple(args.overlap_band),
    )
    records = run_pairs(pairs, table)
    scaling = [] if args.no_scaling else run_scaling(table, args.seed, args.repeats)
    scale_cells = sorted({r["cells"] for r in scaling})
    rows = summarise(records, scaling, list(table))
    args.out.mkdir(parents=True, exist_ok=True)
    text = markdown(rows, command.strip(), scale_cells, notes)
    (args.out / "merge.md").write_text(text)
    doc = {"command": command.strip(), "rows": rows, "records": records, "scaling": scaling}
    (args.out / "merge.json").write_text(json.dumps(doc, indent=1, default=float) + "\n")
    chart(rows, records, scaling, args.out / "merge.png")
    _log(text)
    _log(f"wrote {args.out / 'merge.md'}, merge.json, merge.png")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
