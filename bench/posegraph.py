"""The pose graph's solve, sparse against dense normal equations, at 16 to 128 maps.

    python3 -m bench posegraph [--nodes 16 64 128] [--links-per-node 2 8] [--repeats 3]

:func:`pgvd.posegraph.solve` on random consistent graphs (a chain of maps plus random chords,
one of them an outlier the robust solution drops, links with the errors of real merges),
once with every normal equation solved by a dense LU and once by a sparse one
(:data:`pgvd.posegraph.SPARSE_FROM` set to never and to always).  Each case is timed
``--repeats`` times, the two solvers alternating, and the median kept: on a shared machine
only the ratio sparse / dense of the same run means anything.  The solutions
:func:`pgvd.posegraph.solve` holds from one call to the next are dropped before each run.
The largest difference between the two solutions' placements is reported beside it.  Writes
``bench/results/posegraph.md`` and ``posegraph.json``.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pgvd import posegraph
from pgvd.grid import rigid_matrix

RESULTS = Path(__file__).resolve().parent / "results"


@dataclass(frozen=True)
class Edge:
    """A link as :class:`pgvd.posegraph.Link` reads it."""

    a: str
    b: str
    matrix: np.ndarray
    covariance: np.ndarray


def random_graph(
    n: int, seed: int, links_per_node: float = 2.0, wrong: bool = False
) -> tuple[list[str], list[Edge]]:
    """A connected graph of ``n`` maps: a chain plus random chords up to ``links_per_node *
    n`` links, with the errors of real merges (~1 px, ~0.1 deg) and varied covariances;
    ``wrong`` turns one chord by 25 degrees and 60 px, an outlier the solve must drop."""
    rng = np.random.default_rng(seed)
    nodes = [f"r{i:03d}" for i in range(n)]
    truth = {v: rigid_matrix(rng.uniform(-np.pi, np.pi), *rng.uniform(-400, 400, 2)) for v in nodes}
    pairs = {(nodes[i], nodes[i + 1]) for i in range(n - 1)}
    while len(pairs) < min(int(links_per_node * n), n * (n - 1) // 2):
        i, j = sorted(rng.choice(n, 2, replace=False))
        pairs.add((nodes[i], nodes[j]))
    edges = []
    for k, (a, b) in enumerate(sorted(pairs)):
        m = np.linalg.inv(truth[a]) @ truth[b]
        m = m @ rigid_matrix(math.radians(rng.normal(0, 0.1)), *rng.normal(0, 1.0, 2))
        if wrong and k == len(pairs) // 2:
            m = rigid_matrix(math.radians(25.0), 60.0, 0.0) @ m
        cov = np.diag([*rng.uniform(0.01, 0.5, 2), rng.uniform(1e-8, 1e-5)])
        edges.append(Edge(a, b, m, cov))
    return nodes, edges


def timed_solve(
    sparse_from: int, nodes: list[str], edges: list[Edge]
) -> tuple[float, posegraph.Solution]:
    """Seconds of one :func:`pgvd.posegraph.solve` with ``SPARSE_FROM`` set, and its result."""
    held = posegraph.SPARSE_FROM
    posegraph.SPARSE_FROM = sparse_from
    posegraph.forget_solutions()  # the other solver's run must not serve this one
    try:
        start = time.perf_counter()
        sol = posegraph.solve(nodes, edges)
        return time.perf_counter() - start, sol
    finally:
        posegraph.SPARSE_FROM = held


def measure(n: int, links_per_node: float, repeats: int) -> dict[str, object]:
    """One row: median dense and sparse seconds, their ratio, the largest difference."""
    nodes, edges = random_graph(n, seed=n, links_per_node=links_per_node, wrong=True)
    times: dict[str, list[float]] = {"dense": [], "sparse": []}
    for _ in range(repeats):
        dense_s, dense = timed_solve(10**9, nodes, edges)
        sparse_s, sparse = timed_solve(0, nodes, edges)
        times["dense"].append(dense_s)
        times["sparse"].append(sparse_s)
    diff = max(float(np.abs(sparse.transforms[v] - dense.transforms[v]).max()) for v in nodes)
    dense_med, sparse_med = (float(np.median(times[k])) for k in ("dense", "sparse"))
    return {
        "nodes": n,
        "links": len(edges),
        "dense_s": round(dense_med, 4),
        "sparse_s": round(sparse_med, 4),
        "sparse_over_dense": round(sparse_med / dense_med, 2),
        "max_difference_px": diff,
        "same_links_used": sparse.used == dense.used,
    }


def table(rows: list[dict[str, object]]) -> str:
    lines = [
        "| maps | links | dense (s, median) | sparse (s, median) | sparse / dense "
        "| largest difference (px) | same links kept |",
        "|---|---|---|---|---|---|---|",
    ]
    lines += [
        f"| {r['nodes']} | {r['links']} | {r['dense_s']} | {r['sparse_s']} "
        f"| {r['sparse_over_dense']} | {r['max_difference_px']:.1e} "
        f"| {'yes' if r['same_links_used'] else 'NO'} |"
        for r in rows
    ]
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--nodes", type=int, nargs="+", default=[16, 64, 128])
    ap.add_argument("--links-per-node", type=float, nargs="+", default=[2.0, 8.0])
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()
    if min(args.nodes) < 2 or args.repeats < 1 or min(args.links_per_node) < 1:
        ap.error("--nodes must be >= 2, --repeats >= 1, --links-per-node >= 1")
    rows = []
    for density in args.links_per_node:
        for n in args.nodes:
            row = measure(n, density, args.repeats)
            print(json.dumps(row), flush=True)
            rows.append(row)
    stamp = time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())
    load = os.getloadavg()[0]
    md = (
        "# Pose graph: sparse against dense normal equations\n\n"
        f"`python3 -m bench posegraph --nodes {' '.join(map(str, args.nodes))} "
        f"--links-per-node {' '.join(f'{d:g}' for d in args.links_per_node)} "
        f"--repeats {args.repeats}` on {os.cpu_count()} cores, {stamp} (load {load:.1f} "
        "after).\n\n"
        + table(rows)
        + "\n\nRandom consistent graphs with one outlier (:func:`bench.posegraph.random_graph`); "
        "each solve is the whole robust solution (GNC-TLS, then the placements and their "
        "covariances).  Times are medians of alternating runs; only the ratio is comparable "
        "across machines.  The agent switches to the sparse solve from "
        f"`SPARSE_FROM` = {posegraph.SPARSE_FROM} unknowns (3 per map).\n"
    )
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / "posegraph.md").write_text(md)
    (RESULTS / "posegraph.json").write_text(json.dumps(rows, indent=1))
    print(md)


if __name__ == "__main__":
    main()
