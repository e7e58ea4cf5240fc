"""Per-stage timings of one PGVD merge on real ~1000x1000 maps, with same-run baselines.

Usage::

    python3 -m bench stages [--repeat 7] [--shared ../shared] [--json OUT.json] [--plot OUT.png]

Pairs:

* ``fr079_albertB`` map312 vs map371 (800 x 1184 cells, two gmapping runs);
* ``intel_split_gt`` A vs B, B turned by 37 degrees and both embedded in a
  1000 x 1000 canvas (the size of the 50 ms wire-format target).

Baselines measured in the same run, so the ratios do not depend on the machine:

* ``fft_xcorr``: ONE full-resolution FFT cross-correlation of the two maps
  (real FFTs of both padded to the sum of their sizes, product, inverse);
  a brute-force search would need one of these per candidate heading, and
  several hundred for a 1-degree heading sweep;
* ``read_map``: reading one map from disk (YAML + PGM).

Timings are medians on one thread (BLAS/OpenMP pinned to 1).  The machine
this runs on is often shared, so each stage is measured in *CPU time of
this process* (``time.process_time``, substituted for the merge's clock):
for single-threaded code that is what the wall time would be on an idle
core.  The wall-clock total is reported next to it.  Baselines are measured
the same way.
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import importlib  # noqa: E402
import json  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
from scipy import fft as sfft  # noqa: E402

from pgvd.grid import Grid, rigid_matrix  # noqa: E402
from pgvd.io import read_map  # noqa: E402
from pgvd.merge import merge  # noqa: E402
from pgvd.params import MergeParams  # noqa: E402
from pgvd.transform import warp  # noqa: E402

# the module of the merge's stage clock
merge_module = importlib.import_module("pgvd.stage_clock")

STAGES = ("rotation", "coarsen", "pgvd", "graph", "gamma", "verify", "refine", "covariance")


def _embed(g: Grid, side: int, psi: float) -> Grid:
    """``g`` turned by ``psi`` about its centre, centred on a ``side x side`` canvas."""
    h, w = g.shape
    m = rigid_matrix(psi, 0.0, 0.0)
    m[:2, 2] = (side - 1) / 2.0 - m[:2, :2] @ np.array([(w - 1) / 2.0, (h - 1) / 2.0])
    return Grid.from_probability(
        warp(g.probability(), m, (side, side), order=0, cval=0.5), g.resolution
    )


def _fft_xcorr(a: np.ndarray, b: np.ndarray) -> float:
    size = tuple(sfft.next_fast_len(sa + sb) for sa, sb in zip(a.shape, b.shape, strict=True))
    t0 = time.process_time()
    fa = sfft.rfft2(a, s=size)
    fb = sfft.rfft2(b, s=size)
    sfft.irfft2(fa * np.conj(fb), s=size)
    return 1e3 * (time.process_time() - t0)


class _CpuClock:
    """The merge's stage clock, switched to this process's CPU time while active."""

    def __enter__(self) -> None:
        self._saved = merge_module.time
        merge_module.time = type("cpu_time", (), {"perf_counter": staticmethod(time.process_time)})

    def __exit__(self, *exc: object) -> None:
        merge_module.time = self._saved


def _median(values: list[float]) -> float:
    return float(np.median(values))


def bench_pair(name: str, a: Grid, b: Grid, repeat: int, yaml_path: Path) -> dict:
    """Median stage timings of ``repeat`` merges of ``a`` and ``b``, and the baselines."""
    params = MergeParams(diagnostics=False)
    first = merge(a, b, params)  # warm-up (imports, caches), also the reported result
    walls = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        merge(a, b, params)
        walls.append(1e3 * (time.perf_counter() - t0))
    with _CpuClock():
        runs = [merge(a, b, params).timings_ms for _ in range(repeat)]
    stages = {s: _median([r.get(s, 0.0) for r in runs]) for s in (*STAGES, "total")}
    pa = (a.probability() > 0.65).astype(np.float64)
    pb = (b.probability() > 0.65).astype(np.float64)
    xcorr = _median([_fft_xcorr(pa, pb) for _ in range(repeat)])
    reads = []
    for _ in range(repeat):
        t0 = time.process_time()
        read_map(yaml_path)
        reads.append(1e3 * (time.process_time() - t0))
    read = _median(reads)
    return {
        "pair": name,
        "shape_a": list(a.shape),
        "shape_b": list(b.shape),
        "accepted": first.accepted,
        "rotation_deg": round(first.rotation_deg, 3),
        "translation_px": [round(v, 2) for v in first.translation_px],
        "score": round(first.score, 4),
        "stages_cpu_ms": {k: round(v, 1) for k, v in stages.items()},
        "total_wall_ms": round(_median(walls), 1),
        "baseline_ms": {"fft_xcorr": round(xcorr, 1), "read_map": round(read, 1)},
        "ratio": {
            "total/fft_xcorr": round(stages["total"] / xcorr, 2),
            "total/read_map": round(stages["total"] / read, 2),
        },
    }


def _print(res: dict) -> None:
    print(
        f"\n{res['pair']}: A {res['shape_a']}  B {res['shape_b']}  accepted={res['accepted']}"
        f"  rot={res['rotation_deg']} deg  t={res['translation_px']} px  score={res['score']}"
    )
    total = res["stages_cpu_ms"]["total"]
    for s, v in res["stages_cpu_ms"].items():
        share = f"{100 * v / total:5.1f}%" if s != "total" else "      "
        print(f"  {s:<11} {v:8.1f} ms {share}")
    print(f"  (wall-clock total on this machine now: {res['total_wall_ms']:.1f} ms)")
    b = res["baseline_ms"]
    print(
        f"  baseline: one full-res FFT cross-correlation {b['fft_xcorr']:.1f} ms, "
        f"read_map {b['read_map']:.1f} ms"
    )
    r = res["ratio"]
    print(f"  ratio: merge = {r['total/fft_xcorr']} x FFT xcorr = {r['total/read_map']} x read_map")


def _plot(results: list[dict], path: Path) -> None:
    """Stacked horizontal bars: where the time of one merge goes, next to the baseline."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(9, 1.2 + 1.1 * len(results)))
    colours = plt.get_cmap("tab10").colors
    labels = []
    for row, res in enumerate(results):
        left = 0.0
        for i, stage in enumerate(STAGES):
            v = res["stages_cpu_ms"][stage]
            ax.barh(2 * row, v, left=left, color=colours[i], label=stage if row == 0 else None)
            left += v
        ax.barh(
            2 * row + 0.8,
            res["baseline_ms"]["fft_xcorr"],
            color="0.6",
            label="one full-res FFT xcorr" if row == 0 else None,
        )
        labels += [(2 * row, res["pair"]), (2 * row + 0.8, "baseline")]
    ax.set_yticks([y for y, _ in labels], [t for _, t in labels])
    ax.set_xlabel("CPU ms (median, one thread)")
    ax.legend(ncol=5, fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.3))
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--repeat", type=int, default=7)
    ap.add_argument("--shared", type=Path, default=Path(__file__).resolve().parents[2] / "shared")
    ap.add_argument("--json", type=Path, default=None, help="also write the results here")
    ap.add_argument("--plot", type=Path, default=None, help="bar chart of the stages (matplotlib)")
    args = ap.parse_args(argv)
    maps = args.shared / "maps"
    if not maps.is_dir():
        print(f"shared data not found at {args.shared}", file=sys.stderr)
        return 2
    results = []
    print("fr079_albertB map312 vs map371 ...", flush=True)
    y312 = maps / "fr079_albertB/map312.yaml"
    results.append(
        bench_pair(
            "fr079_albertB 312/371",
            read_map(y312),
            read_map(maps / "fr079_albertB/map371.yaml"),
            args.repeat,
            y312,
        )
    )
    _print(results[-1])
    print("\nintel_split_gt in 1000x1000 frames (B turned 37 deg) ...", flush=True)
    ya = maps / "intel_split_gt/intel_partA.yaml"
    a = _embed(read_map(ya), 1000, 0.0)
    b = _embed(read_map(maps / "intel_split_gt/intel_partB.yaml"), 1000, np.radians(37.0))
    results.append(bench_pair("intel_split_gt 1000x1000", a, b, args.repeat, ya))
    _print(results[-1])
    if args.json is not None:
        args.json.write_text(json.dumps(results, indent=2))
    if args.plot is not None:
        _plot(results, args.plot)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
