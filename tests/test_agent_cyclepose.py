"""A worker's cycle poses (:meth:`agent.worker.FusionWorker._cycle_pose`) kept per pair while
what they read stands: the answer is the fresh one's, and the signature moves exactly when
an input of the prediction does.

Four robots on a square of links: r1-r2 and r2-r3 accepted, r3-r4 and r1-r4 grey-zone
candidates; r1's candidate (r1, r4) is predicted by the accepted links and the other
candidate, around the cycle.  The maps are never read by the prediction (only their robots
and versions), so they are blank.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from agent.book import FleetBook
from agent.links import EPOCH_SHIFT, LinkRecord
from agent.trust import CANDIDATE, CONFIRMED, REJECTED
from agent.worker import CycleLinks, FusionWorker, cycle_pose
from pgvd.grid import Grid, rigid_matrix

V1 = 1 << EPOCH_SHIFT
COV = np.diag([0.25, 0.25, 1e-5])
#: Each robot's pixels in a world frame: the links are the true relative poses.
FRAMES = {
    "r1": rigid_matrix(0.0, 0.0, 0.0),
    "r2": rigid_matrix(0.3, 40.0, -10.0),
    "r3": rigid_matrix(-0.5, 90.0, 35.0),
    "r4": rigid_matrix(1.1, 20.0, 80.0),
}


def link(a: str, b: str, state: str, margin: float = 0.5, by: str = "r1") -> LinkRecord:
    matrix = np.linalg.inv(FRAMES[a]) @ FRAMES[b]
    accepted = state == CONFIRMED
    return LinkRecord(a, V1, b, V1, accepted, matrix, COV, 0.5, by, state=state, margin=margin)


def square() -> tuple[FusionWorker, FleetBook]:
    book = FleetBook()
    for robot in FRAMES:
        book.put_map(robot, V1, Grid(np.zeros((8, 8), np.float32)))
    for rec in (
        link("r1", "r2", CONFIRMED),
        link("r2", "r3", CONFIRMED),
        link("r3", "r4", CANDIDATE, by="r3"),
        link("r1", "r4", CANDIDATE),
    ):
        assert book.add_link(rec)
    worker = FusionWorker("r1", book, lambda a, b: None, lambda r: None, lambda s: None)
    return worker, book


def pose_of(worker: FusionWorker, book: FleetBook) -> tuple[np.ndarray | None, np.ndarray | None]:
    """The worker's cycle pose of (r1, r4) and a fresh one, on the book as it stands."""
    snap = book.snapshot()
    held = next(ln for ln in snap.links if ln.pair == ("r1", "r4"))
    versions = {r: v for r, (v, _) in snap.maps.items()}
    return worker._cycle_pose(snap, held, versions), cycle_pose(snap, held, versions)


def signature(book: FleetBook) -> tuple[object, ...]:
    snap = book.snapshot()
    versions = {r: v for r, (v, _) in snap.maps.items()}
    return CycleLinks.empty().of(snap, versions).signature(("r1", "r4"))


def test_the_kept_cycle_pose_is_the_fresh_one_and_closes_the_square() -> None:
    worker, book = square()
    kept, fresh = pose_of(worker, book)
    assert kept is not None and fresh is not None
    assert np.array_equal(kept, fresh)
    truth = np.linalg.inv(FRAMES["r1"]) @ FRAMES["r4"]
    assert np.allclose(kept, truth, atol=1e-6)
    again, _ = pose_of(worker, book)  # kept: the same answer, a copy of it
    assert np.array_equal(again, kept) and again is not kept


def test_a_rejection_moves_no_input_of_the_cycle_pose() -> None:
    worker, book = square()
    before = signature(book)
    kept, _ = pose_of(worker, book)
    book.add_link(link("r2", "r4", REJECTED, by="r2"))
    assert signature(book) == before
    after, fresh = pose_of(worker, book)
    assert np.array_equal(after, kept) and np.array_equal(after, fresh)


def test_an_accepted_link_a_candidate_or_a_new_epoch_moves_the_signature() -> None:
    worker, book = square()
    seen = [signature(book)]
    book.add_link(link("r1", "r3", CONFIRMED))
    seen.append(signature(book))
    book.add_link(link("r2", "r4", CANDIDATE, by="r2"))
    seen.append(signature(book))
    book.put_map("r2", 2 * V1, Grid(np.zeros((8, 8), np.float32)))
    seen.append(signature(book))
    assert len(set(seen)) == len(seen)
    kept, fresh = pose_of(worker, book)  # r2's links are of its old epoch now
    assert (kept is None and fresh is None) or np.array_equal(kept, fresh)


def test_a_new_revision_of_the_pairs_own_candidate_is_not_read() -> None:
    """The pair predicted is left out of the links counted: its own record changing (a new
    revision of the same candidate) leaves the signature as it was."""
    _, book = square()
    before = signature(book)
    assert book.add_link(replace(link("r1", "r4", CANDIDATE, margin=0.3), revision=1))
    assert signature(book) == before
