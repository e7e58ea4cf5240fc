"""The simulator's registrations: real merge and check outcomes, drawn by true overlap.

A cache of real outcomes is built once (:func:`load_outcomes`) from the development Intel log
as ``pgvd demo`` and :mod:`bench.fleet` split it: for 4, 8, 16, 32 and 64 robots, segment maps
in random frames; pairs of neighbours, of second neighbours and of robots half the circle
apart, and at 8 every pair.  Then the first maps a robot publishes, before its segment is
done: the first half, quarter and tenth of each segment at 8 robots and the first quarter at
16, pairs of neighbours and second neighbours.  A real search rejects most of those (41 of
61 when made): without them a fleet's first, small maps would draw whole maps' outcomes,
which a search mostly accepts, and the searches that follow a rejection would go missing.
For each pair the real :func:`agent.worker.merge_registration` (the full search) and the real
:func:`agent.worker.verify_check` at the true transform (the check a correct chain asks for)
are run, timed in CPU seconds (``time.thread_time``), and stored with the pair's true
overlap and size.  The cache is pickled under the bench's cache directory, versioned
(:data:`CACHE_VERSION`, and the libraries' suffix of :func:`bench.environment.cache_suffix`).

In the simulation a pair of robots ``i, j`` at whatever versions they hold is matched to
the cached outcome nearest in (true overlap of their footprints, known area of the smaller
map): distance ``|overlap - overlap'| / 0.1 + |ln(area / area')|``, ties to the first cached.
The footprint is the set of 0.5 m world cells under the known cells of the map, placed by
the robot's true frame; overlap is the shared cells over the smaller footprint.

A drawn registration carries its real pose error along with its outcome.  The cache keeps,
for each search and each check, the error of its matrix against the pair's truth,
``E = T^-1 M`` (a B-pixel -> B-pixel transform: every map is drawn in 0.1 m cells, so it
applies to any pair alike); the simulation returns ``T_ij E`` with ``T_ij`` the true
transform of ``i, j``.  A search thus answers with that outcome's decision, score, margin,
reason and covariance at the real merge's own error, a near miss included, and the checks
that chain on its link later see the error it left.  A check returns the cached check's
outcome (confirmed, rejected, or inconclusive) at the cached check's own error;
inconclusive also when the predicted transform is outside the check's basin around the
truth (:data:`pgvd.verify.BASIN_M`, :data:`pgvd.verify.BASIN_DEG`), as the real check is
when the chained prediction it starts from has drifted.  Either is charged at the cached
outcome's measured CPU seconds, as measured, unscaled.  ``bench.fleetsim --exact-poses``
leaves the errors out (:meth:`PairOutcome.exact`), to measure what they change.
"""

from __future__ import annotations

import math
import pickle
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from agent.sources import CarmenSource, SourceSpec
from agent.worker import CheckFn, RegisterFn, Registration, merge_registration, verify_check
from bench.environment import cache_suffix
from pgvd.grid import Grid

#: Bump when the pairs or what is stored of them change: caches are then made again.
CACHE_VERSION = 3
#: Side of the world cells a footprint is made of, metres.
FOOTPRINT_CELL_M = 0.5
#: Weight of the overlap in the distance between pairs: 0.1 of overlap counts as e in area.
OVERLAP_SCALE = 0.1


@dataclass(frozen=True)
class RobotTruth:
    """Where a robot's map pixels lie in the log's world: ``world_to_pixel`` (3x3)."""

    world_to_pixel: np.ndarray

    def footprint(self, grid: Grid) -> np.ndarray:
        """Sorted ids of the :data:`FOOTPRINT_CELL_M` world cells under known cells."""
        rows, cols = np.nonzero(grid.logodds[::2, ::2])
        px = np.stack([cols * 2.0, rows * 2.0, np.ones(rows.size)])
        world = np.linalg.solve(self.world_to_pixel, px)[:2] / FOOTPRINT_CELL_M
        cells = np.floor(world).astype(np.int64)
        return np.unique(cells[0] * 1_000_003 + cells[1])


def relative(a: RobotTruth, b: RobotTruth) -> np.ndarray:
    """The true B-pixel -> A-pixel transform."""
    return a.world_to_pixel @ np.linalg.inv(b.world_to_pixel)


def overlap(fa: np.ndarray, fb: np.ndarray) -> float:
    """Shared cells of two footprints over the smaller one's (0 if either is empty)."""
    small = min(fa.size, fb.size)
    return 0.0 if small == 0 else np.intersect1d(fa, fb, assume_unique=True).size / small


@dataclass(frozen=True)
class Outcome:
    """A registration's result, its matrix kept as its error against the truth.

    ``error`` is ``T^-1 M``: the true transform ``T`` of the pair it was measured on,
    inverted, times the matrix ``M`` the registration returned (module docstring).
    """

    accepted: bool
    error: np.ndarray
    covariance: np.ndarray
    score: float
    reason: str
    margin: float | None

    @classmethod
    def of(cls, res: Registration, truth: np.ndarray) -> Outcome:
        """``res``, measured on a pair whose true transform is ``truth``."""
        error = np.linalg.inv(truth) @ np.asarray(res.matrix, np.float64)
        return cls(res.accepted, error, res.covariance, res.score, res.reason, res.margin)

    def at(self, truth: np.ndarray) -> Registration:
        """This result on a pair whose true transform is ``truth``, with this error."""
        return Registration(
            self.accepted, truth @ self.error, self.covariance, self.score, self.reason,
            self.margin,
        )  # fmt: skip


@dataclass(frozen=True)
class PairOutcome:
    """One real pair: its true overlap and smaller known area (m^2), and what the full search
    and the check at the truth decided (None: inconclusive), with their CPU seconds."""

    overlap: float
    area_m2: float
    search: Outcome
    search_cpu: float
    check: Outcome | None
    check_cpu: float

    def exact(self) -> PairOutcome:
        """This pair with its pose errors left out: a search or check lands on the truth."""
        check = None if self.check is None else replace(self.check, error=np.eye(3))
        return replace(self, search=replace(self.search, error=np.eye(3)), check=check)


def known_area(grid: Grid) -> float:
    """Square metres of known cells."""
    return float(np.count_nonzero(grid.logodds)) * grid.resolution**2


def render(log: Path, segment: tuple[float, float], frame: tuple[float, float, float]) -> tuple:
    """The map of one segment of ``log`` in ``frame`` (0.1 m cells), and its truth."""
    src = CarmenSource(SourceSpec("carmen", log, segment), frame, 0.1, 1e9)
    src.step(0.0)
    src.step(1e6)  # the replay's clock starts at the first step; the second takes all
    return src.grid(), RobotTruth(np.asarray(src.describe()["world_to_pixel"]))


#: (robots, share of each segment mapped, pairs of robot indices): which pairs are measured.
Plan = list[tuple[int, float, list[tuple[int, int]]]]


def cache_plan() -> Plan:
    """The pairs of the cache (module docstring)."""
    plan = []
    for n in (4, 8, 16, 32, 64):
        step = max(1, n // 8)
        pairs = {(i, i + d) for i in range(0, n - 2, step) for d in (1, 2)}
        pairs |= {(i, i + n // 2) for i in range(0, n // 2, step)}
        if n == 8:
            pairs |= {(i, j) for i in range(n) for j in range(i + 1, n)}
        plan.append((n, 1.0, sorted(pairs)))
    early = [(8, 0.5), (8, 0.25), (8, 0.1), (16, 0.25)]
    for n, share in early:
        plan.append((n, share, [(i, i + d) for i in range(n) for d in (1, 2) if i + d < n]))
    return plan


def measure_outcomes(log: Path, plan: Plan) -> list[PairOutcome]:
    """Run the real search and check on every pair of ``plan`` (minutes for the cache's)."""
    from agent.scenario import random_frames, segments

    register, check = merge_registration(), verify_check()
    out = []
    for n, share, pairs in plan:
        segs = [(s, s + share * (e - s)) for s, e in segments(n)]
        maps = [render(log, seg, fr) for seg, fr in zip(segs, random_frames(n, 7), strict=True)]
        for i, j in pairs:
            (ga, ta), (gb, tb) = maps[i], maps[j]
            truth = relative(ta, tb)
            t0 = time.thread_time()
            searched = register(ga, gb)
            t1 = time.thread_time()
            checked = check(ga, gb, truth)
            t2 = time.thread_time()
            out.append(
                PairOutcome(
                    overlap(ta.footprint(ga), tb.footprint(gb)),
                    min(known_area(ga), known_area(gb)),
                    Outcome.of(searched, truth),
                    t1 - t0,
                    None if checked is None else Outcome.of(checked, truth),
                    t2 - t1,
                )
            )
        print(f"[fleetsim] cache: {n} robots x{share:g}: {len(pairs)} pairs", file=sys.stderr)
    return out


def load_outcomes(cache: Path, log: Path) -> list[PairOutcome]:
    """The cached outcomes (made by :func:`measure_outcomes` on first use)."""
    path = cache / f"fleetsim-outcomes-v{CACHE_VERSION}{cache_suffix()}.pkl"
    if path.exists():
        return pickle.loads(path.read_bytes())
    outcomes = measure_outcomes(log, cache_plan())
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(pickle.dumps(outcomes))
    return outcomes


class DrawnMerges:
    """The :data:`RegisterFn` and :data:`CheckFn` of the simulated fleet (module docstring).

    Parameters
    ----------
    outcomes : the real outcomes to draw from.
    truths : each robot's :class:`RobotTruth`, by robot id.
    charge : called with the CPU seconds each registration costs its worker, and its kind
        (``"search"`` or ``"check"``).
    """

    def __init__(
        self, outcomes: Sequence[PairOutcome], truths: dict[str, RobotTruth], charge
    ) -> None:
        if not outcomes:
            raise ValueError("no cached registration outcomes to draw from")
        self.outcomes = list(outcomes)
        self.truths = truths
        self.charge = charge
        #: A robot's canvas (shape, origin) is fixed for its whole replay: it names the robot.
        self._by_canvas: dict[tuple[object, ...], str] = {}
        self._footprints: dict[tuple[str, int], np.ndarray] = {}

    def add_robot(self, robot: str, grid: Grid) -> None:
        """Know ``robot``'s maps by the canvas of ``grid``."""
        canvas = self._canvas(grid)
        if canvas in self._by_canvas:
            raise ValueError(f"robots {self._by_canvas[canvas]} and {robot} share a canvas")
        self._by_canvas[canvas] = robot

    @staticmethod
    def _canvas(grid: Grid) -> tuple[object, ...]:
        return (grid.shape, tuple(np.round(grid.origin, 6)), grid.resolution)

    def _footprint(self, grid: Grid) -> tuple[str, np.ndarray]:
        robot = self._by_canvas[self._canvas(grid)]
        key = (robot, int(np.count_nonzero(grid.logodds)))
        held = self._footprints.get(key)
        if held is None:
            held = self._footprints[key] = self.truths[robot].footprint(grid)
        return robot, held

    def nearest(self, a: Grid, b: Grid) -> tuple[PairOutcome, np.ndarray]:
        """The cached outcome standing for ``a, b``, and their true transform."""
        (ra, fa), (rb, fb) = self._footprint(a), self._footprint(b)
        ov, area = overlap(fa, fb), max(min(known_area(a), known_area(b)), 1e-6)
        best = min(
            self.outcomes,
            key=lambda o: abs(ov - o.overlap) / OVERLAP_SCALE + abs(math.log(area / o.area_m2)),
        )
        return best, relative(self.truths[ra], self.truths[rb])

    def register(self) -> RegisterFn:
        """The full search."""

        def search(a: Grid, b: Grid) -> Registration:
            drawn, truth = self.nearest(a, b)
            self.charge(drawn.search_cpu, "search")
            return drawn.search.at(truth)

        return search

    def check(self) -> CheckFn:
        """The check of a predicted transform."""
        from pgvd.verify import BASIN_DEG, BASIN_M

        def check(a: Grid, b: Grid, predicted: np.ndarray) -> Registration | None:
            drawn, truth = self.nearest(a, b)
            self.charge(drawn.check_cpu, "check")
            off = np.linalg.inv(truth) @ np.asarray(predicted, np.float64)
            shift_m = float(np.hypot(off[0, 2], off[1, 2])) * a.resolution
            turn_deg = abs(math.degrees(math.atan2(off[1, 0], off[0, 0])))
            if drawn.check is None or shift_m > BASIN_M or turn_deg > BASIN_DEG:
                return None
            return drawn.check.at(truth)

        return check
