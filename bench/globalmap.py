"""Global-map rebuild time with the fusion cache warm against cold, at 8 and 16 robots.

Usage::

    python3 -m bench globalmap [--robots 8 16] [--logs intel freiburg-079] [--repeat 3]
                               [--shared ../shared] [--out bench/results]

Each robot's map is its segment of a development building's log, rendered as the agents
render it (:class:`agent.sources.CarmenSource`, 0.1 m, the fleet bench's segments and
random frames), first from 90 % of the segment's scans.  Robots are linked to the next
two (a chain with triangles, so the pose graph solves cycles) by their true transforms,
each with the covariance ``diag(1 px^2, 1 px^2, (0.3 deg)^2)``.  Rebuilds
(:func:`agent.globalmap.build_components`, the worker's ``_rebuild``), CPU time of this
process on one thread, median of ``--repeat``:

* ``in turn``: the same placements, then every map fused into the growing canvas in turn
  with :func:`pgvd.fusion.fuse_maps` (warped, then blurred on that canvas), the rebuild
  before the cache, as a baseline (:func:`fuse_in_turn`);
* ``cold``: every map blurred in its own frame, warped into the anchor's pixels and the
  layers fused, empty cache, the pose graph solved afresh (:func:`cold_build`);
* ``new version``: the cache warm and one robot (a different one each repeat) at its next
  map version, the rest of its scans added, its links unchanged (a new minor version within
  its registration epoch): that robot's map alone is warped again;
* ``unchanged``: the cache warm, the same inputs (a preview rebuilt beside no new map);
  this and ``new version`` find the pose graph's solution held, as an agent does when
  no link changed (:func:`pgvd.posegraph.solve`);
* ``re-solved``: the cache warm and one link (a different one each repeat) replaced by an
  estimate a hair away (:data:`HAIR`), as a re-check that confirms it gives: the pose
  graph re-solves every cycle it lies on and moves every placement of the component by a
  rounding-size amount, which the snapped placements (:mod:`agent.placement`) absorb.
  Also reported: the layers it warped again, on average;
* ``moved``: the cache warm and one link (a different one each repeat) replaced by an
  estimate :data:`MOVE` away, a real move as a new registration gives: the robots whose
  placement moved are warped again, but their maps blurred in their own frames are
  reused where their covariance there stayed on the same lattice point.  Also reported:
  the layers warped and the maps blurred again, on average.

The ratios to ``cold`` in the same run are what to compare across machines.  The JSON
also gives why the warm cache blurred each map it blurred, over all these rebuilds
(:attr:`agent.fusecache.LayerCache.blur_causes`).  Also
reported: the bytes of layers and blurred maps the cache holds, the peak memory Python and
numpy allocate during one rebuild in turn and one cold (tracemalloc: scipy's FFT work
buffers are not counted), and the fused map's cells.  Writes
``globalmap.md`` and ``globalmap.json`` in ``--out``.
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import dataclasses  # noqa: E402
import json  # noqa: E402
import math  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
import tracemalloc  # noqa: E402
from collections.abc import Callable  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

from agent.fusecache import LayerCache  # noqa: E402
from agent.globalmap import build_components  # noqa: E402
from agent.links import LinkRecord  # noqa: E402
from agent.scenario import random_frames, segments  # noqa: E402
from agent.sources import CarmenSource, SourceSpec  # noqa: E402
from pgvd.fusion import fuse_maps  # noqa: E402
from pgvd.grid import Grid, relative_matrix, rigid_matrix  # noqa: E402
from pgvd.integrate import integrate_scan  # noqa: E402
from pgvd.posegraph import forget_solutions  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results"
SHARED = Path(__file__).resolve().parents[2] / "shared"
RESOLUTION = 0.1
COVARIANCE = np.diag([1.0, 1.0, math.radians(0.3) ** 2])
#: Each robot is linked to this many robots after it.
NEIGHBOURS = 2
#: The share of its segment's scans a robot's first map version holds.
FIRST_VERSION_SHARE = 0.9
#: How far a re-solved link's estimate moves: far below what a registration resolves.
HAIR = rigid_matrix(1e-9, 1e-7, -1e-7)
#: How far a moved link's estimate moves: about the median move of a placement in a fleet.
MOVE = rigid_matrix(math.radians(0.05), 0.6, -0.4)


class Fleet:
    """``n`` robots' maps of ``log`` and their true links to the next robots.

    Each map holds the first :data:`FIRST_VERSION_SHARE` of its segment's scans at version
    1; :meth:`next_version` adds the rest, as the robot's next minor version (same canvas,
    so its links hold).
    """

    def __init__(self, log: Path, n: int) -> None:
        self.sources, to_pixel = {}, {}
        for i, (seg, frame) in enumerate(zip(segments(n), random_frames(n, 7), strict=True)):
            robot = f"r{i + 1:02d}"
            src = CarmenSource(SourceSpec("carmen", log, seg), frame, RESOLUTION, math.inf)
            self.sources[robot] = src
            to_pixel[robot] = np.asarray(src.describe()["world_to_pixel"])
            self._integrate(robot, int(FIRST_VERSION_SHARE * len(src.scans)))
        self.maps = {r: (1, s.grid()) for r, s in self.sources.items()}
        robots = sorted(self.maps)
        self.links = [
            LinkRecord(
                a, 1, b, 1, True, to_pixel[a] @ np.linalg.inv(to_pixel[b]), COVARIANCE, 0.9, a
            )
            for i, a in enumerate(robots)
            for b in robots[i + 1 : i + 1 + NEIGHBOURS]
        ]

    def _integrate(self, robot: str, cursor: int) -> None:
        src = self.sources[robot]
        for scan in src.scans[src.cursor : cursor]:
            integrate_scan(src.logodds, scan, src.map_frame)
        src.cursor = max(src.cursor, cursor)

    def next_version(self, robot: str) -> None:
        """``robot``'s map with every scan of its segment, at the next version."""
        self._integrate(robot, len(self.sources[robot].scans))
        self.maps[robot] = (self.maps[robot][0] + 1, self.sources[robot].grid())


def cpu_seconds(run: Callable[[], object]) -> float:
    t = time.process_time()
    run()
    return time.process_time() - t


def peak_mb(run: Callable[[], object]) -> float:
    """Peak of the memory Python and numpy allocate during ``run`` (tracemalloc), MB."""
    tracemalloc.start()
    try:
        run()
        return tracemalloc.get_traced_memory()[1] / 1e6
    finally:
        tracemalloc.stop()


def fuse_in_turn(maps: dict[str, tuple[int, Grid]], links: list[LinkRecord]) -> Grid:
    """The one component's map fused in turn on a growing canvas: the placements of
    :func:`agent.globalmap.build_components`, then each map fused into the canvas so far
    in robot id order by :func:`pgvd.fusion.fuse_maps` (the rebuild before the cache)."""
    (comp,) = build_components(maps, links, fuse=False)
    base = fused = maps[comp.anchor][1]
    for robot in comp.members:
        if robot != comp.anchor:
            # the canvas grew: anchor px -> canvas px, then compose
            to_fused = relative_matrix(fused, base) @ comp.transforms[robot]
            fused = fuse_maps(fused, maps[robot][1], to_fused, comp.covariances[robot])
    return fused


def cold_build(maps: dict[str, tuple[int, Grid]], links: list[LinkRecord]) -> None:
    """A rebuild with nothing held: no layer, and no pose-graph solution either
    (:func:`pgvd.posegraph.forget_solutions`), as a fresh agent builds."""
    forget_solutions()
    build_components(maps, links)


def bench_fleet(log: Path, n: int, repeat: int) -> dict:
    """The six rebuilds of the module's docstring on ``n`` robots of ``log``."""
    fleet = Fleet(log, n)
    maps, links = fleet.maps, fleet.links
    robots = sorted(maps)
    cache = LayerCache()
    in_turn = [cpu_seconds(lambda: fuse_in_turn(maps, links)) for _ in range(repeat)]
    cold = [cpu_seconds(lambda: cold_build(maps, links)) for _ in range(repeat)]
    build_components(maps, links, layers=cache)
    new_version = []
    for k in range(repeat):
        fleet.next_version(robots[1 + (k * 5 + 2) % (n - 1)])  # spread out, not the anchor
        warps = cache.warps
        new_version.append(cpu_seconds(lambda: build_components(maps, links, layers=cache)))
        assert cache.warps - warps == 1, "a new version of one robot re-warped others"
    unchanged = [
        cpu_seconds(lambda: build_components(maps, links, layers=cache)) for _ in range(repeat)
    ]
    re_solved, re_warps = [], []
    for k in range(repeat):
        i = (k * 7 + 3) % len(links)
        links[i] = dataclasses.replace(links[i], matrix=HAIR @ links[i].matrix)
        warps = cache.warps
        re_solved.append(cpu_seconds(lambda: build_components(maps, links, layers=cache)))
        re_warps.append(cache.warps - warps)
    moved, moved_warps, moved_blurs = [], [], []
    for k in range(repeat):
        i = (k * 5 + 1) % len(links)
        links[i] = dataclasses.replace(links[i], matrix=MOVE @ links[i].matrix)
        warps, blurs = cache.warps, cache.blurs
        moved.append(cpu_seconds(lambda: build_components(maps, links, layers=cache)))
        moved_warps.append(cache.warps - warps)
        moved_blurs.append(cache.blurs - blurs)
    (comp,) = build_components(maps, links, layers=cache)
    peaks = {
        "in_turn": peak_mb(lambda: fuse_in_turn(maps, links)),
        "cold": peak_mb(lambda: cold_build(maps, links)),
    }
    med = {
        name: float(np.median(v))
        for name, v in (
            ("in_turn", in_turn),
            ("cold", cold),
            ("new_version", new_version),
            ("unchanged", unchanged),
            ("re_solved", re_solved),
            ("moved", moved),
        )
    }
    return {
        "log": log.name.split("-corrected")[0],
        "robots": n,
        "members": len(comp.members),
        "map_cells": int(np.mean([g.logodds.size for _, g in maps.values()])),
        "fused_shape": list(comp.grid.shape),
        "held_mb": cache.held_bytes() / 1e6,
        "re_solved_warps": float(np.mean(re_warps)),
        "moved_warps": float(np.mean(moved_warps)),
        "moved_blurs": float(np.mean(moved_blurs)),
        "blur_causes": dict(sorted(cache.blur_causes.items())),
        "peak_mb": peaks,
        "cpu_s": med,
        "ratio_to_cold": {k: v / med["cold"] for k, v in med.items()},
    }


def table(rows: list[dict]) -> str:
    out = [
        "| log | robots | in turn (s) | cold (s) | new version (s) | unchanged (s) "
        "| re-solved (s) | moved (s) | new version / cold | unchanged / cold | re-solved / cold "
        "| moved / cold | re-solved warps | moved warps / blurs | cold / in turn "
        "| held (MB) | peak in turn / cold (MB) | fused map |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        s, q = r["cpu_s"], r["ratio_to_cold"]
        out.append(
            f"| {r['log']} | {r['robots']} | {s['in_turn']:.2f} | {s['cold']:.2f} "
            f"| {s['new_version']:.3f} | {s['unchanged']:.3f} | {s['re_solved']:.3f} "
            f"| {s['moved']:.3f} | {q['new_version']:.3f} | {q['unchanged']:.3f} "
            f"| {q['re_solved']:.3f} | {q['moved']:.3f} | {r['re_solved_warps']:.1f} "
            f"| {r['moved_warps']:.1f} / {r['moved_blurs']:.1f} "
            f"| {s['cold'] / s['in_turn']:.2f} | {r['held_mb']:.1f} "
            f"| {r['peak_mb']['in_turn']:.0f} / {r['peak_mb']['cold']:.0f} "
            f"| {r['fused_shape'][0]} x {r['fused_shape'][1]} |"
        )
    return "\n".join(out)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--robots", type=int, nargs="+", default=[8, 16])
    ap.add_argument("--logs", nargs="+", default=["intel", "freiburg-079"])
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--shared", type=Path, default=SHARED)
    ap.add_argument("--out", type=Path, default=RESULTS)
    args = ap.parse_args(argv)
    logs = [args.shared / "logs" / f"{name}-corrected.log.gz" for name in args.logs]
    missing = next((p for p in logs if not p.is_file()), None)
    if missing is not None:
        print(f"globalmap: no log {missing}", file=sys.stderr)
        return 2
    if args.repeat < 1 or min(args.robots) < 2:
        print("globalmap: --repeat must be >= 1 and --robots >= 2", file=sys.stderr)
        return 2
    rows = []
    for log in logs:
        for n in args.robots:
            rows.append(bench_fleet(log, n, args.repeat))
            print(table(rows[-1:]).splitlines()[-1], flush=True)
    command = "python3 -m bench globalmap " + " ".join(
        [f"--robots {' '.join(map(str, args.robots))}", f"--logs {' '.join(args.logs)}",
         f"--repeat {args.repeat}"]
    )  # fmt: skip
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "globalmap.json").write_text(json.dumps(rows, indent=2) + "\n")
    (args.out / "globalmap.md").write_text(
        "# Global-map rebuild: the fusion cache warm against cold\n\n"
        f"`{command}`: CPU seconds of one rebuild on one thread, median of {args.repeat}; "
        "see `bench/globalmap.py` for the fleets and the six rebuilds.\n\n"
        f"{table(rows)}\n"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
