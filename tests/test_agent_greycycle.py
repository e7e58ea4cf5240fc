"""A cycle of grey-zone candidates (:mod:`agent.greycycle`), on three parts of the intel log.

The searches are stubbed to land where a building whose right poses score at the bar puts
them (the grey zone, at the true pose or at a wrong one); the maps, the re-checks, the pose
graph and the global map are the agent's own.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from agent import trust
from agent.book import FleetBook
from agent.greycycle import CYCLE_FLOOR
from agent.links import EPOCH_SHIFT, LinkRecord
from agent.worker import FusionWorker, GlobalState, Registration, verify_check
from pgvd.grid import Grid, rigid_matrix
from pgvd.params import DecisionParams

ROBOTS = ("r1", "r2", "r3")
PAIRS = (("r1", "r2"), ("r1", "r3"), ("r2", "r3"))
#: Where ritsumeikan's right poses scored on the fleet bench's final maps.
GREY = 0.5


@pytest.fixture(scope="module")
def three_parts(shared: Path) -> tuple[dict[str, Grid], dict[tuple[str, str], np.ndarray]]:
    """Three overlapping parts of the intel log, each in a random frame of its own, and the
    true B-pixel -> A-pixel matrix of every pair."""
    from bench.data.pairs import random_frame, true_matrix
    from pgvd.carmen import read_carmen
    from pgvd.integrate import frame_for, integrate

    scans = read_carmen(shared / "logs" / "intel-corrected.log.gz")
    rng = np.random.default_rng(7)
    parts = {"r1": scans[100:300], "r2": scans[200:450], "r3": scans[150:380]}
    frames = {r: random_frame(rng) for r in ROBOTS}
    maps = {r: integrate(p, frame_for(p, 0.05, frames[r])) for r, p in parts.items()}
    assert len({m.shape for m in maps.values()}) == 3  # the stub tells the maps by shape
    truth = {(a, b): true_matrix(maps[a], frames[a], maps[b], frames[b]) for a, b in PAIRS}
    return maps, truth


#: A pose covariance (x px, y px, psi rad) as tight as a real search's on these maps: it pins
#: their corners within 0.02 m (:func:`agent.trust.corner_spread`).
TIGHT = np.diag([0.04, 0.04, 1e-7])
#: One as loose as a near miss's on a map still small: 0.3 m or more at the corners.
LOOSE = np.diag([0.25, 0.25, 1e-4])


def grey_search(
    maps: dict[str, Grid],
    poses: dict[tuple[str, str], tuple[np.ndarray, float]],
    cov: np.ndarray = TIGHT,
):
    """A search that finds each pair at the given (pose, margin), with covariance ``cov``."""
    by_shape = {(maps[a].shape, maps[b].shape): found for (a, b), found in poses.items()}

    def register(a: Grid, b: Grid) -> Registration:
        matrix, margin = by_shape[(a.shape, b.shape)]
        accepted = margin >= DecisionParams.min_margin
        return Registration(accepted, matrix, cov, 0.5, f"margin {margin:.2f}", margin)

    return register


class Agent:
    """One robot's book and fusion worker, with the check of a real agent."""

    def __init__(self, me: str, register) -> None:
        self.book = FleetBook()
        self.links: list[LinkRecord] = []
        self.globals: list[GlobalState] = []
        self.worker = FusionWorker(
            me, self.book, register, self.links.append, self.globals.append,
            check=verify_check(),
        )  # fmt: skip

    def hold(self, maps: dict[str, Grid]) -> None:
        for robot, grid in maps.items():
            self.book.put_map(robot, 1 << EPOCH_SHIFT, grid, final=True)

    def run(self) -> None:
        """Step until idle, then past every other agent's turn, so this one decides all."""
        for now in (0.0, 100.0, 200.0, 300.0):
            while self.worker.step(now=now):
                pass

    def record(self, pair: tuple[str, str]) -> LinkRecord:
        return next(ln for ln in self.book.snapshot().links if ln.pair == pair)

    def placed(self, a: str, b: str) -> np.ndarray | None:
        """B -> A as r1's global map places them, None when not together."""
        for comp in self.globals[-1].components:
            if a in comp.members and b in comp.members:
                return np.linalg.inv(comp.transforms[a]) @ comp.transforms[b]
        return None


def decide(three_parts, poses, cov: np.ndarray = TIGHT) -> Agent:
    maps, _ = three_parts
    agent = Agent("r1", grey_search(maps, poses, cov))
    agent.hold(maps)
    agent.run()
    return agent


def test_a_right_cycle_of_grey_candidates_on_final_maps_enters_on_every_agent(
    three_parts,
) -> None:
    maps, truth = three_parts
    r1 = decide(three_parts, {p: (truth[p], GREY) for p in PAIRS})
    states = {p: r1.record(p).state for p in PAIRS}
    assert set(states.values()) == {trust.CONFIRMED}, states
    assert any("consistent cycle of candidates" in r1.record(p).reason for p in PAIRS)
    for a, b in PAIRS:
        shift, turn = trust.pose_change(truth[(a, b)], r1.placed(a, b), maps[b])
        assert trust.within_hold(shift, turn), (a, b, shift, turn)
    # another agent follows r1's records: the same global map, bit for bit
    r2 = Agent("r2", grey_search(maps, {}))
    r2.hold(maps)
    for rec in r1.links:
        r2.book.add_link(rec)
    while r2.worker.step(now=0.0):
        pass
    assert r2.links == []  # it decided nothing
    digests = {tuple(c.digest for c in a.globals[-1].components) for a in (r1, r2)}
    assert len(digests) == 1, digests


def test_a_right_cycle_of_loose_candidates_waits(three_parts) -> None:
    """The same right cycle, each pose loose at its map's corners: a near miss would close
    it as well, so no candidate enters."""
    maps, truth = three_parts
    assert all(trust.corner_spread(truth[p], LOOSE, maps[p[1]]) > trust.HOLD_M for p in PAIRS)
    r1 = decide(three_parts, {p: (truth[p], GREY) for p in PAIRS}, LOOSE)
    for p in PAIRS:
        assert r1.record(p).state == trust.CANDIDATE, r1.record(p)
    assert all(len(c.members) == 1 for c in r1.globals[-1].components)


@pytest.mark.parametrize(("cov", "state"), [(TIGHT, trust.CONFIRMED), (LOOSE, trust.CANDIDATE)])
def test_a_grey_pose_on_a_cycle_of_accepted_links_enters_only_if_pinned(
    three_parts, cov: np.ndarray, state: str
) -> None:
    """(r1, r2) and (r2, r3) found at the high bar, (r1, r3) at the truth in the grey zone:
    it closes a right cycle, and enters only if its own covariance pins r3's corners."""
    _, truth = three_parts
    poses = {p: (truth[p], trust.HIGH_BAR + 0.05) for p in PAIRS}
    poses[("r1", "r3")] = (truth[("r1", "r3")], GREY)
    r1 = decide(three_parts, poses, cov)
    assert r1.record(("r1", "r2")).state == trust.ACCEPTED
    assert r1.record(("r1", "r3")).state == state, r1.record(("r1", "r3"))


def test_a_look_alike_grey_candidate_breaks_the_cycle_and_nothing_enters(three_parts) -> None:
    """(r2, r3) found 180 degrees off, as in a building symmetric under a half turn: the
    cycle does not close, and no candidate enters."""
    maps, truth = three_parts
    b = maps["r3"]
    centre = np.array([(b.shape[1] - 1) / 2.0, (b.shape[0] - 1) / 2.0])
    half = rigid_matrix(np.pi, 0.0, 0.0)
    half[:2, 2] = centre - half[:2, :2] @ centre
    poses = {p: (truth[p], GREY) for p in PAIRS}
    poses[("r2", "r3")] = (truth[("r2", "r3")] @ half, GREY)
    r1 = decide(three_parts, poses)
    for p in PAIRS:
        assert r1.record(p).state == trust.CANDIDATE, r1.record(p)
    assert all(len(c.members) == 1 for c in r1.globals[-1].components)


def test_a_candidate_below_the_cycle_floor_closes_no_cycle(three_parts) -> None:
    _, truth = three_parts
    poses = {p: (truth[p], GREY) for p in PAIRS}
    poses[("r2", "r3")] = (truth[("r2", "r3")], CYCLE_FLOOR - 0.05)
    r1 = decide(three_parts, poses)
    assert r1.record(("r2", "r3")).state == trust.CANDIDATE  # in the grey zone, held
    assert not any(r1.record(p).state in trust.IN_MAP for p in PAIRS)
    assert all(len(c.members) == 1 for c in r1.globals[-1].components)
