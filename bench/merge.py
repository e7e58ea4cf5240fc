"""Merge benchmark: pgvd against the methods people use, on pairs from every development building.

Pairs (:mod:`bench.data.sets`): the intel and freiburg-079 logs, simulated LMS200
runs over the development map images (intel, fr079_albertB, willow,
ritsumeikan_cc4f, mit_stata_basement, uos_avz; :mod:`pgvd.lidar`,
:mod:`pgvd.trajectory`) and the three gmapping runs of fr079_albertB against
each other (:mod:`bench.data.gmapping`).  Sets: standard (overlap >= 30 %), low
overlap (15-35 %), drifted (odometry noise on the scan poses) and negatives
(disjoint parts of a building, look-alike corridors, mirror images, different
buildings).  Each map is in its own random frame, with the true B -> A matrix.

Methods, all in this one process:

``pgvd``        this project's merge (:func:`pgvd.merge.merge`);
``pgvd-det``    the paper's deterministic variant (Gamma_det, plain GVD):
                ``MergeParams(probabilistic=False)``;
``pgvd-no-rho``, ``pgvd-no-gamma``, ``pgvd-no-blur``, ``pgvd-rigid``, ``pgvd-as-drawn``
                ablations: without the rho veto (32), without Gamma's ranking (27),
                without the heading blur (8), hypotheses scored on the rigid overlay
                instead of the drift-tolerant one (``MergeParams.drift_shift = 0``),
                and ``pgvd-as-drawn``: a map without unknown cells read as drawn, its
                free space outside its walls' convex hull not made unknown
                (``MergeParams.min_unknown = 0``, :mod:`pgvd.unexplored`);
``pgvd-no-retry`` without the retry of a rejected raw map with its lone wall cells read
                as unknown (``MergeParams.speckle_retry = 0``; the retry runs on maps with
                many lone walls: those ``--speckle`` makes raw, and 12 of the 190 rejected
                pairs of the maps as they are, where it accepts none);
``pgvd-heading`` an option that is off by default: the Radon candidates refined on
                the whole-map overlay, ``MergeParams(heading_span=6)``
                (``python -m bench recall --method pgvd-heading`` shows what it finds);
``pgvd-search`` an option that is off by default: 4 finalists more, the best by the
                search evidence (free space seen by both counts, conflicts weigh more),
                ``MergeParams(search_finalists=4)``;
``pgvd-despeckle`` an option that is off by default (``pgvd merge --despeckle``): lone
                wall cells read as unknown, ``MergeParams(speckle_radius=0.15)``
                (:mod:`pgvd.speckle`);
``pgvd-turned+0.1``, ``pgvd-turned-0.1`` not options: the default with every candidate
                heading of (10) turned by that many degrees, ``MergeParams(heading_offset)``,
                to measure how much the outcome hangs on the heading estimate;
``m-explore``   multirobot_map_merge's AKAZE + affine RANSAC pipeline (OpenCV);
``hough``       Carpin's Hough-spectrum merging;
``exhaustive``  every heading at 1 degree + FFT cross-correlation (reference).

Success on an overlapping pair: accepted, heading within 2 degrees and mean
error of B's occupied cells within 3 cells.  Times are wall-clock per merge
in this process.  Time scaling uses one intel pair rendered at ~500^2 cells
and upsampled (nearest, x2 and x4, so the content is identical) to ~1000^2 and
~2000^2.  Every pair's record (truth, what the method exposes: for pgvd every
MergeResult field, the headings searched and the finalists that reached the
decision, each marked a success or not) is in ``merge.json``.

``--unknown free`` paints every unknown cell of both maps of each pair free
(:func:`bench.data.pairs.painted_free`): the maps as images with no unknown cell.
``--speckle D`` turns a share ``D`` of each map's free cells into lone walls, drawn
independently for the two maps of a pair (:func:`bench.data.pairs.speckled_pair`): raw maps
saved without cleaning.
``--held-out`` cuts the same sets from the laser logs the shared data keeps to evaluate
the merge on buildings it was never tuned on (:func:`bench.data.sources.held_out_logs`), and
writes to ``bench/results/held-out/``.

Run from the project root::

    python3 -m bench merge --quick                # a few pairs per source and set, pgvd only
    python3 -m bench merge                        # full: ~300 pairs, pgvd, m-explore, hough

Writes ``merge.md``, ``merge.png`` and ``merge.json`` to ``--out`` (``bench/results/``), and
with pgvd among the methods the margin report of :mod:`bench.studies.acceptance`
(``acceptance.md``, ``acceptance.png``) and the covariance report of
:mod:`bench.studies.covariance_wide` (``covariance-wide.md``, ``covariance-wide.png``).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from bench import tables
from bench.capture import Finalists, SearchedHeadings, result_json, to_json
from bench.data.pairs import MapPair, make_pair, painted_pair, speckled_pair
from bench.data.sets import (
    DRIFT,
    FULL,
    LOW_BAND,
    MIDDLE_BAND,
    QUICK,
    STANDARD_BAND,
    Entry,
    build,
)
from bench.data.sources import SOURCES, held_out_logs
from bench.environment import describe, environment
from bench.studies import acceptance, covariance_wide
from bench.tables import MAX_CELL_ERROR, mark, pose_right
from pgvd.carmen import read_carmen
from pgvd.grid import Grid, heading
from pgvd.speckle import DESPECKLE_RADIUS

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "bench" / "results"
#: Reports measured on the data kept for evaluation (``--held-out``).
HELD_OUT = RESULTS / "held-out"
CACHE = ROOT / "bench" / "cache"
#: Cell size of the scaling pair: intel at 0.07 m is ~500 cells per side.
SCALE_RESOLUTION = 0.07
INTEL_LOG = ROOT.parent / "shared" / "logs" / "intel-corrected.log.gz"


#: A method: (accepted, B->A matrix, what else it exposes, JSON-ready).
Method = Callable[[Grid, Grid], tuple[bool, np.ndarray, dict]]


def _pgvd(**overrides) -> Method:
    from pgvd.merge import merge
    from pgvd.params import MergeParams
    from pgvd.pooling import decision_pool

    params = MergeParams(diagnostics=False, **overrides)

    def run(a: Grid, b: Grid) -> tuple[bool, np.ndarray, dict]:
        searched, finalists = SearchedHeadings(), Finalists()
        with searched.watching(), finalists.watching():
            result = merge(a, b, params)
        extra = {
            "result": result_json(result),
            "searched_deg": searched.degrees,
            "searched_sigma_deg": searched.sigmas,
            "finalists": finalists.full_frame(decision_pool(a.resolution)),
        }
        return bool(result.accepted), np.asarray(result.matrix), extra

    return run


def _baseline(module: str, **kwargs) -> Method:
    import importlib

    merge = importlib.import_module(f"bench.baselines.{module}").merge

    def run(a: Grid, b: Grid) -> tuple[bool, np.ndarray, dict]:
        result = merge(a, b, **kwargs)
        return bool(result.accepted), result.matrix, {"score": float(result.score)}

    return run


#: Ablations of pgvd: MergeParams overrides.
ABLATIONS = {
    "pgvd-det": {"probabilistic": False},
    "pgvd-no-rho": {"rho_veto": False},
    "pgvd-no-gamma": {"gamma_ranking": False},
    "pgvd-no-blur": {"heading_blur": False},
    "pgvd-rigid": {"drift_shift": 0.0},
    "pgvd-as-drawn": {"min_unknown": 0.0},
    "pgvd-no-retry": {"speckle_retry": 0.0},
}
#: Options of pgvd that are off by default, measured beside it: MergeParams overrides.
OPTIONS = {
    "pgvd-heading": {"heading_span": 6.0},
    "pgvd-search": {"search_finalists": 4},
    "pgvd-despeckle": {"speckle_radius": DESPECKLE_RADIUS},
    # not options a user sets: the default with every heading candidate turned a little,
    # to measure how much the outcome hangs on the heading estimate
    "pgvd-turned+0.1": {"heading_offset": 0.1},
    "pgvd-turned-0.1": {"heading_offset": -0.1},
}
#: Every pgvd variant by name: a stage off or an option on.
VARIANTS = ABLATIONS | OPTIONS
METHOD_NAMES = ("pgvd", *VARIANTS, "m-explore", "hough", "exhaustive")


def methods(
    exhaustive_step: float = 1.0, exhaustive_coarse: int = 4, names: tuple[str, ...] = METHOD_NAMES
) -> dict[str, Method]:
    """The methods of the table, in column order (those of ``names`` that exist)."""
    makers: dict[str, Callable[[], Method]] = {
        "pgvd": _pgvd,
        **{name: (lambda kw=kw: _pgvd(**kw)) for name, kw in VARIANTS.items()},
        "m-explore": lambda: _baseline("mexplore"),
        "hough": lambda: _baseline("hough"),
        "exhaustive": lambda: _baseline(
            "exhaustive", step_deg=exhaustive_step, coarse=exhaustive_coarse
        ),
    }
    return {n: makers[n]() for n in METHOD_NAMES if n in names and n in makers}


def heading_error(truth: np.ndarray, matrix: np.ndarray) -> float:
    """Absolute heading difference (deg) of two B->A matrices."""
    dpsi = heading(matrix) - heading(truth)
    return float(abs(np.degrees((dpsi + np.pi) % (2 * np.pi) - np.pi)))


def errors(pair: MapPair, matrix: np.ndarray) -> tuple[float, float]:
    """Heading error (deg) and mean cell error of B's occupied cells against the truth.

    Both are NaN for a pair with no true transform (a different building, a mirror image).
    """
    truth = pair.truth
    if truth is None:
        return float("nan"), float("nan")
    rows, cols = np.nonzero(pair.b.logodds > 0)
    pts = np.vstack([cols, rows, np.ones_like(rows)]).astype(np.float64)
    cell = float(np.mean(np.linalg.norm((matrix @ pts - truth @ pts)[:2], axis=0)))
    return heading_error(truth, matrix), cell


def cell_tolerance(pair: MapPair) -> float:
    """Mean cell error a success may have: MAX_CELL_ERROR, plus a drifted pair's own distortion.

    A drifted pair's truth is the least-squares alignment on its overlap; its maps
    disagree by ``drift_rms_m`` (RMS) even there, so an alignment within that much of
    the truth is as right as the maps allow.
    """
    rms = pair.info.get("drift_rms_m")
    extra = 0.0 if rms is None or not np.isfinite(rms) else rms / pair.a.resolution
    return MAX_CELL_ERROR + extra


def evaluate(pair: MapPair, accepted: bool, matrix: np.ndarray, cell_scale: float = 1.0) -> dict:
    """One row of the per-pair record: accept, errors (cells / ``cell_scale``) and success."""
    heading, cell = errors(pair, matrix)
    cell /= cell_scale
    rec = {
        "accepted": accepted,
        "heading_deg": heading,
        "cell_err": cell,
        "cell_tolerance": cell_tolerance(pair),
    }
    rec["success"] = bool(accepted and pair.overlap > 0 and pose_right(rec))
    return rec


def _log(msg: str) -> None:
    print(msg, flush=True)


def pair_record(entry: Entry) -> dict:
    """What the bench knows about a pair: where it belongs, its truth, how it was made."""
    p = entry.pair
    truth = p.truth
    return {
        "pair": p.name,
        "source": entry.source,
        "building": entry.building,
        "set": entry.set,
        "kind": entry.kind,
        "overlap": p.overlap,
        "resolution": p.a.resolution,
        "shape_a": list(p.a.shape),
        "shape_b": list(p.b.shape),
        "truth": None if truth is None else truth.tolist(),
        "truth_heading_deg": None if truth is None else float(np.degrees(heading(truth))),
        "info": to_json(p.info),
        "cells": int(np.sqrt(p.a.logodds.size * p.b.logodds.size)),
    }


def run_pairs(entries: list[Entry], table: dict[str, Method]) -> list[dict]:
    """Every method on every pair; one record per (pair, method)."""
    records = []
    t_start = time.perf_counter()
    for i, entry in enumerate(entries, 1):
        pair = entry.pair
        line = []
        for name, method in table.items():
            t0 = time.perf_counter()
            accepted, matrix, extra = method(pair.a, pair.b)
            seconds = time.perf_counter() - t0
            rec = pair_record(entry)
            rec.update(evaluate(pair, accepted, matrix))
            if extra.get("finalists") is not None:
                # pose recall (bench.studies.recall): would each finalist have been a success?
                rec["finalist_success"] = [
                    evaluate(pair, True, m)["success"] for m in extra["finalists"]
                ]
            rec.update(method=name, seconds=seconds, matrix=matrix.tolist(), **extra)
            records.append(to_json(rec))
            line.append(f"{name} {mark(rec['success'], accepted)} {seconds:.2f}s")
        elapsed = time.perf_counter() - t_start
        _log(
            f"[merge] {i}/{len(entries)} {pair.name} {entry.set}/{entry.kind} "
            f"ov={pair.overlap:.2f}: " + " | ".join(line) + f"  ({elapsed:.0f} s)"
        )
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
    scans = read_carmen(INTEL_LOG)
    base = make_pair(
        scans, (0.0, 0.55), (0.45, 1.0), seed, resolution=SCALE_RESOLUTION, name="intel-scale"
    )
    records = []
    for factor in (1, 2, 4):
        pair = upsample(base, factor)
        cells = int(np.sqrt(pair.a.logodds.size))
        times: dict[str, list[tuple[float, float]]] = {name: [] for name in table}
        results = {}
        # the methods in turn, repeat after repeat, so that a drift of the
        # machine's speed falls on all of them and their ratios hold
        for _ in range(repeats):
            for name, method in table.items():
                t0, c0 = time.perf_counter(), time.process_time()
                results[name] = method(pair.a, pair.b)
                times[name].append((time.perf_counter() - t0, time.process_time() - c0))
        for name, (accepted, matrix, _) in results.items():
            # Success judged in cells of the ~500^2 base map: upsampling scales pixel errors.
            rec = evaluate(pair, accepted, matrix, cell_scale=factor)
            wall, cpu = np.median(times[name], axis=0)
            rec.update(method=name, cells=cells, seconds=float(wall), cpu_seconds=float(cpu))
            records.append(rec)
            _log(f"[scale] {cells}^2 {name}: {rec['seconds']:.2f} s success={rec['success']}")
    return records


def add_output_arguments(parser: argparse.ArgumentParser, data: str) -> None:
    """``--held-out`` (run on the ``data`` the shared data keeps for evaluation) and
    ``--out``, whose default follows it (:func:`output_dir`)."""
    parser.add_argument(
        "--held-out",
        action="store_true",
        help=f"the {data} the shared data keeps for evaluation, not the development ones "
        "(default --out: bench/results/held-out)",
    )
    parser.add_argument("--out", type=Path, help="default: bench/results")


def output_dir(args: argparse.Namespace) -> Path:
    """Where a report goes: ``--out``, else ``bench/results/held-out`` with ``--held-out``,
    else ``bench/results``."""
    return args.out or (HELD_OUT if args.held_out else RESULTS)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="a few pairs per source and set")
    parser.add_argument(
        "--methods",
        nargs="+",
        choices=METHOD_NAMES,
        help="default: pgvd (quick), pgvd m-explore hough (full)",
    )
    parser.add_argument(
        "--sources", nargs="+", choices=[s.name for s in SOURCES], help="default: all"
    )
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--exhaustive-step", type=float, default=1.0, help="degrees")
    parser.add_argument("--exhaustive-coarse", type=int, default=4, help="pooling factor")
    parser.add_argument("--no-scaling", action="store_true", help="skip the map-size run")
    parser.add_argument("--repeats", type=int, default=3, help="timing repeats per size")
    parser.add_argument("--cache", type=Path, default=CACHE, help="generated runs and pairs")
    parser.add_argument("--no-cache", action="store_true")
    add_output_arguments(parser, "laser logs")
    parser.add_argument(
        "--unknown",
        choices=("drawn", "free"),
        default="drawn",
        help="free: every pair's unknown cells painted free, as a map image without unknown",
    )
    parser.add_argument(
        "--speckle",
        type=float,
        default=0.0,
        metavar="D",
        help="turn this share of each map's free cells into lone walls (raw maps)",
    )
    args = parser.parse_args(argv)
    if not 0 <= args.speckle < 1:
        parser.error(f"--speckle must be in [0, 1), got {args.speckle}")
    if args.held_out and args.sources:
        parser.error("--held-out and --sources: the held-out logs are not development sources")
    out = output_dir(args)
    command = "python3 -m bench merge " + " ".join(argv if argv is not None else sys.argv[1:])
    names = tuple(args.methods or (("pgvd",) if args.quick else ("pgvd", "m-explore", "hough")))
    counts = QUICK if args.quick else FULL
    table = methods(args.exhaustive_step, args.exhaustive_coarse, names)
    t0 = time.perf_counter()
    if args.held_out:
        sources = held_out_logs()
    else:
        sources = tuple(s for s in SOURCES if args.sources is None or s.name in args.sources)
    cache = None if args.no_cache else args.cache
    gmapping = args.sources is None and not args.held_out
    entries = build(counts, args.seed, cache, sources, gmapping=gmapping)
    if args.unknown == "free":
        entries = [dataclasses.replace(e, pair=painted_pair(e.pair)) for e in entries]
    if args.speckle > 0:
        entries = [
            dataclasses.replace(e, pair=speckled_pair(e.pair, args.speckle, args.seed))
            for e in entries
        ]
    _log(f"[pairs] {len(entries)} pairs ready in {time.perf_counter() - t0:.0f} s")
    records = run_pairs(entries, table)
    scaling = [] if args.no_scaling else run_scaling(table, args.seed, args.repeats)
    summary = tables.summarise(records, list(table))
    env = environment()
    notes = [
        describe(env),
        f"Pairs per source: {dataclasses.asdict(counts)} (seed {args.seed}); overlap of the "
        f"standard and drifted sets in {list(STANDARD_BAND)} (half of the standard pairs drawn "
        f"in {list(MIDDLE_BAND)}), of the low set in {list(LOW_BAND)}.",
        f"Drifted: random-walk odometry drift {DRIFT.json()} (bench.data.drift: sigmas per "
        "sqrt(metre) travelled and per sqrt(radian) turned) "
        "on both robots; truth = the least-squares rigid alignment of the walls both robots "
        "saw (bench.data.drift.overlap_fit); a drifted pair's cell tolerance is 3 cells plus its "
        "residual distortion there (info.drift_rms_m, in cells; record field cell_tolerance).",
        "Success: accepted, heading within 2 deg and mean error of B's occupied cells within "
        "3 cells. Errors are medians over successes. Times: wall clock, one process.",
        "Wrong accepts: accepted on an overlapping pair with a pose outside those bounds. "
        "False accepts: accepted on a negative pair.",
    ]
    if args.held_out:
        notes.append(
            "Held out: the laser logs of the buildings the shared data keeps for evaluation "
            "(bench.data.sources.held_out_logs: every log no development source reads), cut as "
            "the development logs are. No parameter was set on them."
        )
    if args.unknown == "free":
        notes.append(
            "Unknown painted free: every cell of both maps of each pair that a saved map draws "
            "unknown reads free (bench.data.pairs.painted_free), as in a map image whose "
            "unexplored area was painted white; the scaling pair is not painted."
        )
    if args.speckle > 0:
        notes.append(
            f"Speckle: {args.speckle:g} of each map's free cells turned into lone walls, "
            "drawn independently for the two maps of a pair (bench.data.pairs.speckled_pair, "
            f"seed {args.seed}): raw maps saved without cleaning; the scaling pair is not "
            "speckled."
        )
    if scaling:
        notes.append(
            f"Scaling: one intel pair at {SCALE_RESOLUTION} m (~500^2), upsampled x2 and x4 "
            "(nearest: same content, more cells); success there in cells of the base map. "
            f"Seconds: median of {args.repeats} runs, the methods in turn at each repeat; "
            "the speed table gives pgvd's time over each peer's, from the same run, in wall "
            "clock and in CPU time (all threads of this process: the one to read on a busy "
            "machine)."
        )
    out.mkdir(parents=True, exist_ok=True)
    text = tables.markdown(summary, scaling, command.strip(), notes)
    (out / "merge.md").write_text(text)
    doc = {
        "command": command.strip(),
        "environment": env,
        "summary": summary,
        "records": records,
        "scaling": to_json(scaling),
    }
    (out / "merge.json").write_text(json.dumps(to_json(doc), indent=1) + "\n")
    tables.chart(summary, records, scaling, out / "merge.png")
    if "pgvd" in table:
        acceptance.write(records, out, str(out / "merge.json"))
        covariance_wide.write(records, out, str(out / "merge.json"))
    _log(text)
    _log(f"wrote {out / 'merge.md'}, merge.json, merge.png")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
