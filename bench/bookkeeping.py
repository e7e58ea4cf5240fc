"""One agent's bookkeeping per worker step against the fleet's size, as ratios to 16 robots.

A real :class:`agent.book.FleetBook` holds N robots' maps and the links of every pair but
those of the last three robots; a real :class:`agent.worker.FusionWorker` then steps once
after each of those links but one arrives, as an agent's worker does at every wake.  Nothing is
registered (the turns' timeout is never reached) and nothing rebuilt (the preview interval
is never reached): what is timed is the snapshot, the choice of keys and the chains of
accepted links, the work that grows with the pairs rather than with the maps.  CPU time is
printed as a ratio to 16 robots measured in the same run: the machine is shared.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from agent.book import FleetBook
from agent.links import EPOCH_SHIFT, LinkRecord
from agent.worker import FusionWorker, Registration
from pgvd.grid import Grid

#: The robots whose pairs arrive while the worker steps.
LATE = 3


def _links(robots: list[str]) -> list[LinkRecord]:
    """A link per pair, one in three accepted, at a few distinct offsets."""
    version = 5 << EPOCH_SHIFT
    out = []
    for i, a in enumerate(robots):
        for j, b in enumerate(robots[i + 1 :], i + 1):
            m = np.eye(3)
            m[0, 2] = 0.5 * ((i * 7 + j) % 5)
            accepted = (i + j) % 3 == 0
            out.append(LinkRecord(a, version, b, version, accepted, m, np.eye(3), 1.0, a))
    return out


def _never(a: Grid, b: Grid) -> Registration:
    raise AssertionError("the bench registers nothing")


def step_cpu(n: int, steps: int) -> float:
    """CPU seconds of one worker step at ``n`` robots, after one link arrived."""
    book = FleetBook()
    grid = Grid(np.zeros((4, 4), np.float32), 0.1)
    robots = [f"r{i:03d}" for i in range(n)]
    for r in robots:
        book.put_map(r, 5 << EPOCH_SHIFT, grid)
    links = _links(robots)
    late = set(robots[-LATE:])
    for rec in links:
        if rec.b not in late:
            book.add_link(rec)
    worker = FusionWorker(
        robots[0], book, _never, lambda rec: None, lambda state: None,
        link_timeout=1e9, check=lambda a, b, predicted: None,
    )  # fmt: skip
    worker.preview_interval = 1e9
    worker.step(0.0)
    # one pair stays needed: a settled book would rebuild the global map
    arriving = [rec for rec in links if rec.b in late][:-1][:steps]
    start = time.process_time()
    for k, rec in enumerate(arriving):
        book.add_link(rec)
        worker.step(1.0 + k)
    return (time.process_time() - start) / len(arriving)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--robots", type=int, nargs="+", default=[16, 32, 64, 128])
    ap.add_argument("--steps", type=int, default=60, help="steps timed at each N")
    args = ap.parse_args(argv)
    if min(args.robots) < LATE + 2 or args.steps < 1:
        ap.error(f"--robots must be >= {LATE + 2} and --steps >= 1")
    step_cpu(16, args.steps)  # the first run pays for imports and caches warming up
    base = step_cpu(16, args.steps)
    print("| N | CPU per step (ms) | vs 16 |\n|---|---|---|")
    for n in args.robots:
        cpu = step_cpu(n, args.steps)
        print(f"| {n} | {cpu * 1e3:.2f} | {cpu / base:.1f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
