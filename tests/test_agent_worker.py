"""The fusion worker: whose turn a pair is, links published once, rebuilds when settled."""

from __future__ import annotations

import importlib
import json
import math
from pathlib import Path

import numpy as np
import pytest
from numpy.linalg import inv

from agent.book import FleetBook, Snapshot
from agent.links import EPOCH_SHIFT, GATED, LinkRecord, open_keys
from agent.trust import CANDIDATE, CONFIRMED, REJECTED, WITHDRAWN
from agent.worker import (
    APART,
    CHECKS_PREVIEW_SHARE,
    GATE_HOLD_S,
    PREVIEW_SHARE,
    RESOLVE_AFTER,
    Chains,
    FusionWorker,
    GlobalState,
    Registration,
    _current_pairs,
    _joins,
    _registration,
    _rejection_stands,
    merge_registration,
    placements,
    predict,
    verify_check,
)
from pgvd.grid import Grid, rigid_matrix, world_pose_to_pixel_matrix
from pgvd.io import read_map
from pgvd.merge import merge
from pgvd.params import MergeParams


def V(epoch: int, minor: int = 0) -> int:
    return epoch << EPOCH_SHIFT | minor


def tiny(seed: int) -> Grid:
    lo = np.zeros((20, 20), np.float32)
    lo[seed : seed + 5, 3:15] = 2.0
    return Grid(lo, 0.1)


class Harness:
    def __init__(self, me: str) -> None:
        self.book = FleetBook()
        self.calls: list[tuple[int, int]] = []
        self.links: list[LinkRecord] = []
        self.globals: list[GlobalState] = []
        self.worker = FusionWorker(
            me, self.book, self.register, self.links.append, self.globals.append, 4.0
        )  # fmt: skip

    def register(self, a: Grid, b: Grid) -> Registration:
        self.calls.append((int(a.logodds.sum()), int(b.logodds.sum())))
        return Registration(True, rigid_matrix(0.0, 1.0, 2.0), np.eye(3) * 0.1, 0.9)


def test_lower_robot_registers_at_once_and_publishes_the_link() -> None:
    h = Harness("r1")
    h.book.put_map("r1", V(1), tiny(1))
    h.book.put_map("r2", V(1), tiny(2))
    assert h.worker.step(now=0.0)
    assert len(h.calls) == 1 and [ln.key for ln in h.links] == [("r1", 1, "r2", 1)]
    assert h.links[0].decided_by == "r1"
    assert not h.worker.step(now=0.1)  # nothing due: rebuild instead
    (state,) = h.globals
    assert state.settled and state.components[0].members == ("r1", "r2")
    assert not h.worker.step(now=0.2) and len(h.globals) == 1  # same inputs: no rebuild


def test_higher_robot_waits_for_the_link_then_computes_it_itself() -> None:
    h = Harness("r2")
    h.book.put_map("r1", V(1), tiny(1))
    h.book.put_map("r2", V(1), tiny(2))
    assert not h.worker.step(now=10.0) and h.calls == []
    (interim,) = h.globals
    assert not interim.settled and [c.anchor for c in interim.components] == ["r1", "r2"]
    assert h.worker.step(now=14.0) and len(h.calls) == 1


def test_a_received_link_saves_the_registration() -> None:
    h = Harness("r3")
    h.book.put_map("r1", V(1), tiny(1))
    h.book.put_map("r2", V(1), tiny(2))
    h.worker.step(now=0.0)
    other = LinkRecord("r1", V(1), "r2", V(1), True, rigid_matrix(0, 1, 2), np.eye(3), 0.9, "r1")
    assert h.book.add_link(other)
    assert not h.worker.step(now=100.0) and h.calls == []
    assert h.globals[-1].settled and h.links == []


def test_a_failing_registration_becomes_a_rejected_link(caplog) -> None:
    caplog.set_level("INFO", logger="pgvd.agent")
    h = Harness("r1")

    def boom(a: Grid, b: Grid) -> Registration:
        raise ValueError("map without occupied cells")

    h.worker.register = boom
    h.book.put_map("r1", V(1), tiny(1))
    h.book.put_map("r2", V(1), tiny(2))
    h.worker.step(now=0.0)
    assert [ln.accepted for ln in h.links] == [False]
    # the log says why the robots were not linked
    (line,) = [r.getMessage() for r in caplog.records if r.getMessage().startswith("link ")]
    assert "pair=r1/r2 versions=1.0/1.0 outcome=rejected" in line, line
    assert 'reason="registration failed: map without occupied cells"' in line, line
    h.worker.step(now=0.1)
    assert [c.members for c in h.globals[-1].components] == [("r1",), ("r2",)]


def test_a_superseded_link_is_not_cached() -> None:
    book = FleetBook()
    book.put_map("r1", V(3), tiny(1))
    book.put_map("r2", V(1), tiny(2))
    old = LinkRecord("r1", V(2), "r2", V(1), True, np.eye(3), np.eye(3), 0.9, "r1")
    assert not book.add_link(old)


def test_timeout_grows_with_the_fleet_and_the_cost_of_a_registration() -> None:
    h = Harness("r1")
    assert h.worker.effective_timeout(8) == 4.0  # nothing measured yet
    h.worker.merges, h.worker.merge_seconds = 4, 6.0  # 1.5 s each
    assert h.worker.effective_timeout(8) == 4.0 + 1.5 * 3.5
    assert h.worker.effective_timeout(1) == 4.0


def test_a_new_minor_version_needs_no_registration_a_new_epoch_does() -> None:
    h = Harness("r1")
    h.book.put_map("r1", V(1), tiny(1))
    h.book.put_map("r2", V(1), tiny(2))
    h.worker.step(now=0.0)
    h.worker.step(now=0.1)
    h.book.put_map("r2", V(1, 1), tiny(3))  # more detail, same epoch
    assert not h.worker.step(now=0.2) and len(h.calls) == 1
    assert h.globals[-1].settled and h.globals[-1].components[0].versions["r2"] == V(1, 1)
    h.book.put_map("r2", V(2), tiny(4))  # changed enough: a new epoch
    assert h.worker.step(now=0.3) and len(h.calls) == 2


def test_unsettled_previews_are_rate_limited_settled_maps_are_not() -> None:
    h = Harness("r3")  # registers nothing itself for a while: r1-r2 is not its pair
    h.book.put_map("r1", V(1), tiny(1))
    h.book.put_map("r2", V(1), tiny(2))
    h.worker.step(now=0.0)
    h.book.put_map("r2", V(2), tiny(3))
    h.worker.step(now=1.0)
    assert len(h.globals) == 1  # a second preview within 3 s is skipped
    h.worker.step(now=3.5)
    assert len(h.globals) == 2 and not h.globals[-1].settled
    h.book.add_link(LinkRecord("r1", V(1), "r2", V(2), True, np.eye(3), np.eye(3), 0.9, "r1"))
    h.worker.step(now=3.6)
    assert len(h.globals) == 3 and h.globals[-1].settled


def _link(a: str, b: str, m: np.ndarray, by: str = "r9") -> LinkRecord:
    return LinkRecord(a, V(1), b, V(1), True, m, np.eye(3) * 0.1, 0.95, by)


class Checking(Harness):
    """A harness whose worker checks predictions; ``verdict`` is what the check answers."""

    def __init__(self, me: str, verdict: Registration | None) -> None:
        super().__init__(me)
        self.checked: list[np.ndarray] = []
        self.verdict = verdict
        self.worker.check = self.check

    def check(self, a: Grid, b: Grid, predicted: np.ndarray) -> Registration | None:
        self.checked.append(predicted)
        return self.verdict


def _chain(h: Harness) -> None:
    """r1 - r2 - r3 linked; r1 - r3 still needed, and r3's to register first."""
    for r in ("r1", "r2", "r3"):
        h.book.put_map(r, V(1), tiny(int(r[1])))
    h.book.add_link(_link("r1", "r2", rigid_matrix(0.0, 10.0, 0.0)))
    h.book.add_link(_link("r2", "r3", rigid_matrix(np.pi / 2, 0.0, 5.0)))


def test_a_chained_pair_is_checked_on_the_composed_prediction_not_searched() -> None:
    confirmed = Registration(True, rigid_matrix(0.1, 1.0, 1.0), np.eye(3) * 0.2, 0.97)
    h = Checking("r3", confirmed)
    _chain(h)
    assert h.worker.step(now=0.0)
    expected = rigid_matrix(0.0, 10.0, 0.0) @ rigid_matrix(np.pi / 2, 0.0, 5.0)
    (predicted,) = h.checked
    np.testing.assert_allclose(predicted, expected, atol=1e-9)
    assert h.calls == []  # no full search
    (rec,) = h.links
    assert rec.pair == ("r1", "r3") and rec.accepted
    np.testing.assert_array_equal(rec.matrix, confirmed.matrix)
    counts = h.worker.counters.snapshot()["counts"]
    assert counts == {"checks": 1, "checks_confirmed": 1}


def test_an_inconclusive_check_falls_back_to_the_full_search() -> None:
    h = Checking("r3", None)
    _chain(h)
    assert h.worker.step(now=0.0)
    assert len(h.checked) == 1 and len(h.calls) == 1
    assert h.links[0].matrix[0, 2] == 1.0  # the search's answer (Harness.register)
    assert h.worker.counters.snapshot()["counts"] == {"checks": 1, "searches": 1}


def test_a_disjoint_verdict_is_searched_the_first_time() -> None:
    h = Checking("r3", Registration(False, np.eye(3), np.zeros((3, 3)), 0.0))
    _chain(h)
    assert h.worker.step(now=0.0)
    assert len(h.checked) == 1 and len(h.calls) == 1
    assert h.worker.counters.snapshot()["counts"] == {"checks": 1, "searches": 1}


def _rejected_in_epoch_0(h: Harness, a: str, b: str) -> None:
    """``a`` and ``b`` held at epoch 0, whose search rejected the pair."""
    h.book.put_map(a, V(0), tiny(int(a[1])))
    h.book.put_map(b, V(0), tiny(int(b[1])))
    h.book.add_link(LinkRecord(a, V(0), b, V(0), False, np.eye(3), np.zeros((3, 3)), 0.1, b))


def test_a_disjoint_verdict_on_a_pair_rejected_before_rejects_without_search() -> None:
    h = Checking("r3", Registration(False, np.eye(3), np.zeros((3, 3)), 0.0))
    _rejected_in_epoch_0(h, "r1", "r3")
    _chain(h)  # epoch 1 of every map: r1-r3 needs a link again
    assert h.worker.step(now=0.0)
    assert h.calls == [] and [ln.accepted for ln in h.links] == [False]
    assert h.worker.counters.snapshot()["counts"] == {"checks": 1, "checks_rejected": 1}


def test_a_pair_no_chain_reaches_is_searched_unchecked() -> None:
    h = Checking("r1", None)
    h.book.put_map("r1", V(1), tiny(1))
    h.book.put_map("r2", V(1), tiny(2))
    assert h.worker.step(now=0.0)
    assert h.checked == [] and len(h.calls) == 1
    assert h.worker.counters.snapshot()["counts"] == {"searches": 1}


def test_a_prior_goes_before_the_chain_and_confirms_alone() -> None:
    confirmed = Registration(True, rigid_matrix(0.1, 1.0, 1.0), np.eye(3) * 0.2, 0.97)
    h = Checking("r3", confirmed)
    _chain(h)
    h.worker.poses = {"r1": (0.0, 0.0, 0.0), "r3": (0.5, 0.0, 0.0)}  # 0.5 m = 5 px apart
    assert h.worker.step(now=0.0)
    (at_prior,) = h.checked  # the chain's prediction (10 px, then 90 deg) is not needed
    np.testing.assert_allclose(at_prior, rigid_matrix(0.0, 5.0, 0.0), atol=1e-9)
    assert h.calls == [] and [ln.accepted for ln in h.links] == [True]
    assert h.worker.counters.snapshot()["counts"] == {"prior_checks": 1, "prior_confirmed": 1}


def test_a_prior_the_check_rejects_is_searched_even_for_a_pair_rejected_before() -> None:
    """A chain's rejection of a pair rejected before stands; a prior's never does."""
    h = Checking("r1", Registration(False, np.eye(3), np.zeros((3, 3)), 0.0))
    _rejected_in_epoch_0(h, "r1", "r2")
    h.book.put_map("r1", V(1), tiny(1))
    h.book.put_map("r2", V(1), tiny(2))
    h.worker.poses = {"r1": (0.0, 0.0, 0.0), "r2": (1.0, 2.0, 0.3)}
    assert h.worker.step(now=0.0)
    assert len(h.checked) == 1 and len(h.calls) == 1
    assert [ln.accepted for ln in h.links] == [True]  # the search's (Harness.register)
    counts = h.worker.counters.snapshot()["counts"]
    assert counts == {"prior_checks": 1, "prior_failed": 1, "searches": 1}


def test_a_link_inconsistent_around_cycles_does_not_enter_the_prediction() -> None:
    """r1..r4 all linked consistently except r1-r3, 40 px and 20 deg off: r1-r5 via r4."""
    truth = {f"r{i}": rigid_matrix(0.3 * i, 50.0 * i, -20.0 * i) for i in range(1, 6)}
    maps = {r: (V(1), tiny(i + 1)) for i, r in enumerate(truth)}

    def rel(a: str, b: str) -> np.ndarray:
        return np.linalg.inv(truth[a]) @ truth[b]

    pairs = [("r1", "r2"), ("r1", "r4"), ("r2", "r3"), ("r2", "r4"), ("r3", "r4"), ("r4", "r5")]
    links = [_link(a, b, rel(a, b)) for a, b in pairs]
    links.append(_link("r1", "r3", rigid_matrix(np.radians(20), 40.0, 0.0) @ rel("r1", "r3")))
    sol = placements(maps, links)
    np.testing.assert_allclose(predict(sol, "r1", "r5"), rel("r1", "r5"), atol=1e-6)
    assert predict(placements(maps, links[:1]), "r1", "r5") is None


def test_pairs_a_check_can_decide_go_before_searches() -> None:
    """r1-r3 (predicted through r2) is checked before r0-r1, which nothing predicts."""
    h = Checking("r1", Registration(True, np.eye(3), np.eye(3) * 0.1, 0.95))
    _chain(h)
    h.book.put_map("r0", V(1), tiny(0))
    h.worker.link_timeout = 0.0  # every pair is due for r1 at once
    assert h.worker.step(now=0.0)
    assert [ln.pair for ln in h.links] == [("r1", "r3")] and h.calls == []


def test_a_preferred_candidate_for_a_held_key_rebuilds_the_global_map() -> None:
    h = Harness("r1")
    h.book.put_map("r1", V(1), tiny(1))
    h.book.put_map("r2", V(1), tiny(2))
    h.book.add_link(_link("r1", "r2", rigid_matrix(0.0, 1.0, 2.0), by="r2"))
    assert not h.worker.step(now=0.0) and len(h.globals) == 1
    moved = rigid_matrix(0.0, 5.0, 2.0)
    assert h.book.add_link(_link("r1", "r2", moved, by="r0"))  # same key, preferred
    assert not h.worker.step(now=0.1) and len(h.globals) == 2
    np.testing.assert_array_equal(h.globals[-1].components[0].transforms["r2"], moved)


@pytest.fixture(scope="module")
def intel_pair() -> tuple[Grid, Grid, np.ndarray]:
    """The bundled Intel pair and its true B->A matrix."""
    root = Path(__file__).resolve().parents[1] / "examples"
    truth = np.array(json.loads((root / "truth.json").read_text())["matrix"])
    return read_map(root / "intel_a.yaml"), read_map(root / "intel_b.yaml"), truth


def test_verify_check_on_real_maps(intel_pair, monkeypatch) -> None:
    a, b, truth = intel_pair
    check = verify_check()
    confirmed = check(a, b, truth)
    assert confirmed is not None and confirmed.accepted
    assert np.abs(confirmed.matrix - truth)[:2, 2].max() < 2.0
    far = rigid_matrix(0.0, 5000.0, 0.0) @ truth  # the chain puts B far outside A
    rejected = check(a, b, far)
    assert rejected is not None and not rejected.accepted and rejected.score == 0.0
    assert rejected.reason == "the predicted pose overlaps 0.0 m of walls < 3.0 m"
    off = rigid_matrix(np.radians(20.0), 60.0, 0.0) @ truth  # overlapping, disagreeing
    verdict = check(a, b, off)
    assert verdict is not None and not verdict.accepted and verdict.reason, verdict
    # any correction leaves the basin
    monkeypatch.setattr(importlib.import_module("pgvd.verify"), "BASIN_M", 1e-3)
    assert verify_check()(a, b, off) is None


def test_a_chain_check_reads_each_map_once(intel_pair, monkeypatch) -> None:
    """A rejected prediction is verified, then measured where it put the maps: both on one
    reading of the maps, not one each."""
    module = importlib.import_module("pgvd.verify")  # pgvd.verify is the function
    a, b, truth = intel_pair
    read: list[int] = []
    reading = module.registration_probability

    def counted(grid: Grid, params: MergeParams) -> np.ndarray:
        read.append(id(grid))
        return reading(grid, params)

    monkeypatch.setattr(module, "registration_probability", counted)
    off = rigid_matrix(np.radians(20.0), 60.0, 0.0) @ truth  # overlapping, disagreeing
    verdict = verify_check()(a, b, off)
    assert verdict is not None and not verdict.accepted
    assert sorted(read) == sorted([id(a), id(b)])


def test_a_canvas_that_moved_lets_no_older_epochs_chain_reject_a_true_link(intel_pair) -> None:
    """r2's SLAM grew its map 10 m to the left and up (a new origin, new pixels): a new
    epoch. The links of the old epoch, which stand in meanwhile, map the old pixels, so
    the chain's prediction for r1-r2 is 10 m off and its check rejects the true overlap.
    That rejection once stood (the chain ran over a triangle) and the pair was published
    as disjoint with no search."""
    a, b, truth = intel_pair
    pad = 200
    lo = np.zeros((b.shape[0] + pad, b.shape[1] + pad), np.float32)
    lo[pad:, pad:] = b.logodds
    grown = Grid(lo, b.resolution, (b.origin[0] - pad * b.resolution, *b.origin[1:]))
    to_old = np.array([[1.0, 0.0, -pad], [0.0, 1.0, -pad], [0.0, 0.0, 1.0]])  # new px -> old
    cov = np.diag([0.5, 0.5, 1e-5])
    searches = []

    def search(x: Grid, y: Grid) -> Registration:
        searches.append((x, y))
        return Registration(True, truth @ to_old, cov, 0.9)

    book, decided = FleetBook(), []
    worker = FusionWorker(
        "r1", book, search, decided.append, lambda state: None, 4.0,
        check=verify_check(),
    )  # fmt: skip
    for robot, grid in (("r1", a), ("r2", b), ("r3", a)):
        book.put_map(robot, V(1), grid)
    for x, y, m in (("r1", "r2", truth), ("r1", "r3", np.eye(3)), ("r2", "r3", inv(truth))):
        book.add_link(LinkRecord(x, V(1), y, V(1), True, m, cov, 0.9, "r1"))
    book.put_map("r2", V(2), grown)
    assert worker.step(now=0.0)
    (link,) = [ln for ln in decided if ln.pair == ("r1", "r2")]
    assert link.version_b == V(2) and link.accepted and searches == [(a, grown)]


def test_a_merge_registration_carries_the_merges_reason(intel_pair) -> None:
    a, b, _ = intel_pair
    register = merge_registration()
    assert register(a, b).accepted
    # B against its mirror image, a building that does not exist: rejected, and the
    # registration says why in the merge's own words
    mirrored = Grid(b.logodds[::-1].copy(), b.resolution, b.origin)
    rejected = register(a, mirrored)
    assert not rejected.accepted
    assert rejected.reason == merge(a, mirrored, MergeParams(diagnostics=False)).reason
    assert rejected.reason.startswith(("the best pose does not stand out", "no ")), rejected


def test_an_accepted_merge_without_a_finite_pose_is_rejected_with_its_own_reason() -> None:
    nan = np.full((3, 3), np.nan)
    res = _registration(True, nan, np.eye(3), 0.9, "accepted")
    assert not res.accepted and res.reason == "no finite pose or covariance"
    res = _registration(False, nan, nan, 0.4, "overlap too small")
    assert not res.accepted and res.reason == "overlap too small"


def test_a_later_wave_waits_for_the_first_and_becomes_a_check() -> None:
    """r1 searches its neighbour r2 at once, but its opposite r3 only once the first wave is
    decided, and then as a check: the links r2-r3-r4 placed r3 beside r1."""
    h = Checking("r1", Registration(True, np.eye(3), np.eye(3) * 0.1, 0.95))
    for i in range(1, 5):
        h.book.put_map(f"r{i}", V(1), tiny(i))
    assert h.worker.step(now=0.0)
    assert [ln.pair for ln in h.links] == [("r1", "r2")] and len(h.calls) == 1
    # r1-r3 is r1's turn, but r2-r3, r3-r4 and r1-r4 of the first wave are still to search
    assert not h.worker.step(now=0.1) and len(h.links) == 1
    h.book.add_link(_link("r2", "r3", np.eye(3)))
    h.book.add_link(_link("r3", "r4", np.eye(3)))
    assert h.worker.step(now=0.2)
    assert [ln.pair for ln in h.links] == [("r1", "r2"), ("r1", "r3")]
    assert len(h.calls) == 1 and len(h.checked) == 1  # checked, not searched


def test_a_disjoint_verdict_over_a_chain_on_triangles_rejects_without_search() -> None:
    """r1-r2-r3 and r1-r3-r4 linked consistently: r2-r4's chain runs over links on
    triangles, so the check's rejection stands; over the bridge r4-r5, r2-r5 is still
    searched."""
    h = Checking("r2", Registration(False, np.eye(3), np.zeros((3, 3)), 0.0))
    for i in range(1, 6):
        h.book.put_map(f"r{i}", V(1), tiny(i))
    links = [("r1", "r2"), ("r2", "r3"), ("r1", "r3"), ("r3", "r4"), ("r1", "r4"), ("r4", "r5")]
    for a, b in links:
        h.book.add_link(_link(a, b, np.eye(3)))
    for a in ("r1", "r3"):  # decided: r2-r5 has no other check to wait for
        h.book.add_link(LinkRecord(a, V(1), "r5", V(1), False, *_NOTHING, 0.0, "r9"))
    h.worker.link_timeout = 0.0
    # r2's own pairs go first: r2-r4, then r2-r5 (once past any timeout)
    assert h.worker.step(now=0.0) and h.worker.step(now=100.0)
    assert [(ln.pair, ln.accepted) for ln in h.links[:2]] == [
        (("r2", "r4"), False), (("r2", "r5"), True),
    ]  # fmt: skip
    assert len(h.calls) == 1  # r2-r5 searched (the harness's search accepts), r2-r4 not


_NOTHING = (np.eye(3), np.zeros((3, 3)))


def test_a_rejection_that_needs_a_search_waits_for_the_rounds_other_checks() -> None:
    """Links as above, r2's check rejects r2-r5 (over the bridge r4-r5: a search would
    decide) and confirms r1-r5.  r2-r5 waits; r1-r5 puts r4-r5 on the triangle r1-r4-r5,
    and r2-r5 checked again is rejected with no search at all."""
    h = Checking("r2", None)
    grids = {f"r{i}": tiny(i) for i in range(1, 6)}
    for r, g in grids.items():
        h.book.put_map(r, V(1), g)
    links = [("r1", "r2"), ("r2", "r3"), ("r1", "r3"), ("r3", "r4"), ("r1", "r4"), ("r4", "r5")]
    for a, b in links:
        h.book.add_link(_link(a, b, np.eye(3)))
    for a in ("r3",):  # decided; r2-r4 is on triangles, its rejection stands
        h.book.add_link(LinkRecord(a, V(1), "r5", V(1), False, *_NOTHING, 0.0, "r9"))
    h.book.add_link(LinkRecord("r2", V(1), "r4", V(1), False, *_NOTHING, 0.0, "r9"))

    def check(a: Grid, b: Grid, predicted: np.ndarray) -> Registration:
        h.checked.append(predicted)
        return Registration(a is grids["r1"], np.eye(3), np.eye(3) * 0.1, 0.95)

    h.worker.check = check
    h.worker.link_timeout = 0.0
    now = 0.0
    while h.worker.step(now=now):
        now += 100.0  # past any wait for the pair's other robot
    assert sorted((ln.pair, ln.accepted) for ln in h.links) == [
        (("r1", "r5"), True), (("r2", "r5"), False),
    ]  # fmt: skip
    assert h.calls == []  # no search
    counts = h.worker.counters.snapshot()["counts"]
    assert counts["checks_deferred"] == 1 and counts["checks"] == 3


def test_slow_rebuilds_space_previews_out() -> None:
    """A preview that took 2 s waits 2 / PREVIEW_SHARE s for the next; a settled map not."""
    h = Harness("r3")
    h.book.put_map("r1", V(1), tiny(1))
    h.book.put_map("r2", V(1), tiny(2))
    h.worker._rebuild_seconds = 2.0  # as measured by the last rebuild
    assert h.worker.preview_gap() == 2.0 / PREVIEW_SHARE > h.worker.preview_interval
    h.worker._rebuilt_at = 0.0
    h.book.put_map("r2", V(2), tiny(3))
    gap = h.worker.preview_gap()
    h.worker.step(now=gap - 0.1)
    assert h.globals == []
    h.worker.step(now=gap)
    assert len(h.globals) == 1 and not h.globals[-1].settled
    h.book.add_link(LinkRecord("r1", V(1), "r2", V(2), True, np.eye(3), np.eye(3), 0.9, "r1"))
    h.worker.step(now=gap + 0.1)
    assert len(h.globals) == 2 and h.globals[-1].settled


def test_links_alone_preview_less_than_new_maps() -> None:
    """A link that only re-places the maps of the last preview waits
    rebuild / CHECKS_PREVIEW_SHARE; a new map version previews after rebuild / PREVIEW_SHARE."""
    h = Harness("r3")  # no pair of r1, r2, r4 is r3's, and it never steps in
    h.worker.link_timeout = 1000.0
    for robot in ("r1", "r2", "r4"):
        h.book.put_map(robot, V(1), tiny(int(robot[1])))
    h.worker.step(now=0.0)
    assert len(h.globals) == 1 and not h.globals[-1].settled
    h.worker._rebuild_seconds = 1.0
    h.book.add_link(LinkRecord("r1", V(1), "r2", V(1), True, np.eye(3), np.eye(3), 0.9, "r1"))
    assert h.worker.preview_gap(maps_moved=False) == 1.0 / CHECKS_PREVIEW_SHARE
    h.worker.step(now=1.0 / PREVIEW_SHARE + 1.0)
    assert len(h.globals) == 1  # links alone: not yet
    h.worker.step(now=1.0 / CHECKS_PREVIEW_SHARE + 1.0)
    assert len(h.globals) == 2 and h.globals[-1].components[0].members == ("r1", "r2")
    h.book.put_map("r4", V(1, 1), tiny(5))  # more detail: the map moved
    h.worker.step(now=1.0 / CHECKS_PREVIEW_SHARE + 1.0 / PREVIEW_SHARE + 2.0)
    assert len(h.globals) == 3 and h.globals[-1].components[1].versions == {"r4": V(1, 1)}


def test_a_round_of_checks_only_previews_less() -> None:
    """r1-r3 is the only pair needed and a check (r1-r2-r3 linked): previews wait
    rebuild / CHECKS_PREVIEW_SHARE, not rebuild / PREVIEW_SHARE."""
    h = Checking("r2", None)  # r1-r3 is not r2's pair: it only watches
    _chain(h)
    h.worker.link_timeout = 1000.0
    h.worker._rebuild_seconds = 1.0
    h.worker._rebuilt_at = 0.0
    assert h.worker.preview_gap(checks_only=True) == 1.0 / CHECKS_PREVIEW_SHARE
    assert h.worker.preview_gap() == 1.0 / PREVIEW_SHARE < 1.0 / CHECKS_PREVIEW_SHARE
    assert not h.worker.step(now=1.0 / PREVIEW_SHARE + 1.0)
    assert h.globals == [] and h.checked == []
    h.worker.step(now=1.0 / CHECKS_PREVIEW_SHARE + 1.0)
    assert len(h.globals) == 1 and not h.globals[-1].settled


class Superseding(Checking):
    """r2 starts a new epoch while the search of r1-r2 runs."""

    def register(self, a: Grid, b: Grid) -> Registration:
        self.book.put_map("r2", V(2), tiny(3))
        return super().register(a, b)


@pytest.mark.parametrize("confirms", [True, False])
def test_a_search_superseded_meanwhile_is_checked_on_the_new_maps(confirms: bool) -> None:
    verdict = Registration(True, rigid_matrix(0.0, 1.5, 2.0), np.eye(3) * 0.1, 0.97)
    h = Superseding("r1", verdict if confirms else None)
    h.book.put_map("r1", V(1), tiny(1))
    h.book.put_map("r2", V(1), tiny(2))
    assert h.worker.step(now=0.0)
    assert len(h.calls) == 1
    np.testing.assert_array_equal(h.checked[0], rigid_matrix(0.0, 1.0, 2.0))  # the search's
    if confirms:
        assert [ln.key for ln in h.links] == [("r1", 1, "r2", 2)]
        np.testing.assert_array_equal(h.links[0].matrix, verdict.matrix)
        assert h.book.snapshot().needed == []
    else:
        assert h.links == [] and h.book.snapshot().needed == [("r1", 1, "r2", 2)]
    counts = h.worker.counters.snapshot()["counts"]
    assert counts == {"searches": 1, "checks": 1, **({"checks_confirmed": 1} if confirms else {})}


def _known_pose_of_b(a: Grid, b: Grid, truth: np.ndarray) -> tuple[float, float, float]:
    """B's map-frame pose in A's map frame (the world here): the pose the truth implies."""
    m = np.linalg.inv(world_pose_to_pixel_matrix(a)) @ truth @ world_pose_to_pixel_matrix(b)
    return float(m[0, 2]), float(m[1, 2]), math.atan2(m[1, 0], m[0, 0])


class Searching:
    """The worker with the real check and the real full search, which it counts."""

    def __init__(self, a: Grid, b: Grid, pose_b: tuple[float, float, float]) -> None:
        self.book = FleetBook()
        self.book.put_map("r1", V(1), a)
        self.book.put_map("r2", V(1), b)
        self.links: list[LinkRecord] = []
        self.searches = 0
        search = merge_registration()

        def register(a: Grid, b: Grid) -> Registration:
            self.searches += 1
            return search(a, b)

        self.worker = FusionWorker(
            "r1", self.book, register, self.links.append, lambda _: None, 4.0,
            check=verify_check(), poses={"r1": (0.0, 0.0, 0.0), "r2": pose_b},
        )  # fmt: skip


def test_a_right_known_pose_links_real_maps_with_the_check_alone(intel_pair) -> None:
    a, b, truth = intel_pair
    s = Searching(a, b, _known_pose_of_b(a, b, truth))
    assert s.worker.step(now=0.0)
    (rec,) = s.links
    assert rec.accepted and s.searches == 0
    assert np.abs(rec.matrix - truth)[:2, 2].max() < 2.0  # pixels
    counts = s.worker.counters.snapshot()["counts"]
    assert counts == {"prior_checks": 1, "prior_confirmed": 1}


def test_a_wrong_known_pose_is_not_taken_and_the_search_finds_the_true_link(intel_pair) -> None:
    """B's known pose 3 m and 20 degrees off: the check fails it, the full search decides."""
    a, b, truth = intel_pair
    x, y, yaw = _known_pose_of_b(a, b, truth)
    s = Searching(a, b, (x + 3.0, y, yaw + math.radians(20.0)))
    assert s.worker.step(now=0.0)
    (rec,) = s.links
    assert rec.accepted and s.searches == 1
    assert np.abs(rec.matrix - truth)[:2, 2].max() < 2.0
    counts = s.worker.counters.snapshot()["counts"]
    assert counts == {"prior_checks": 1, "prior_failed": 1, "searches": 1}


def test_a_recent_solution_keeps_predicting_while_it_joins_the_pair(monkeypatch) -> None:
    """Links r1-r2-r3-r4: r1-r3 solves the pose graph; r4-r5 arrives, and r1-r4 (still joined
    by that solution) reuses it; r1-r5 (not joined) solves anew, as does anything after
    RESOLVE_AFTER seconds."""
    import agent.worker as worker

    solves: list[int] = []
    solve = worker.solve

    def counting(maps, links, *args, **kwargs):
        solves.append(len(links))  # the accepted links solved over
        return solve(maps, links, *args, **kwargs)

    monkeypatch.setattr(worker, "solve", counting)
    h = Checking("r1", Registration(True, np.eye(3), np.eye(3) * 0.1, 0.95))
    for i in range(1, 6):
        h.book.put_map(f"r{i}", V(1), tiny(i))
    for a, b in [("r1", "r2"), ("r2", "r3"), ("r3", "r4")]:
        h.book.add_link(_link(a, b, np.eye(3)))
    h.worker.link_timeout = 0.0
    assert h.worker.step(now=0.0) and h.links[-1].pair == ("r1", "r3")
    assert solves == [3]
    h.book.add_link(_link("r4", "r5", np.eye(3)))
    assert h.worker.step(now=0.5) and h.links[-1].pair == ("r1", "r4")
    assert solves == [3]  # the solution of 0 s still joins r1 and r4
    assert h.worker.step(now=1.0) and h.links[-1].pair == ("r1", "r5")
    assert solves == [3, 6]  # it does not join r5: solved with r4-r5 and the checks' links
    h.book.add_link(_link("r3", "r5", np.eye(3)))
    assert h.worker.step(now=1.0 + RESOLVE_AFTER) and h.links[-1].pair == ("r2", "r4")
    assert solves == [3, 6, 8]  # too old: solved anew
    assert h.calls == [] and len(h.checked) == 4


def test_a_rejection_on_a_recent_solution_is_checked_again_on_the_links_held() -> None:
    """r2-r4 is joined over the bridge r3-r4: its rejection needs a search.  Then r4-r5 and
    r3-r5 arrive (r3-r4 now on a triangle) while the solution is still recent: the check is
    made again on the links held, and its rejection stands."""
    h = Checking("r2", Registration(False, *_NOTHING, 0.0))
    for i in range(1, 6):
        h.book.put_map(f"r{i}", V(1), tiny(i))
    for a, b in [("r1", "r2"), ("r2", "r3"), ("r1", "r3"), ("r3", "r4")]:
        h.book.add_link(_link(a, b, np.eye(3)))
    h.worker._now = 0.0
    first = h.worker._checked(h.book.snapshot(), "r2", "r4")
    assert first is not None and not isinstance(first, Registration)  # unproven
    assert len(h.checked) == 1  # the solution was the links held: nothing to check again
    for a, b in [("r4", "r5"), ("r3", "r5")]:
        h.book.add_link(_link(a, b, np.eye(3)))
    h.worker._now = 0.5
    res = h.worker._checked(h.book.snapshot(), "r2", "r4")
    assert isinstance(res, Registration) and not res.accepted
    assert len(h.checked) == 3


def test_a_disjoint_verdict_over_a_lone_long_cycle_is_searched() -> None:
    """r1-r2-r3-r4-r5-r1, a lone cycle with no triangle: a wrong link on it would spread its
    error thin, so r1-r3's first rejection by a check still needs a search."""
    h = Checking("r1", Registration(False, np.eye(3), np.zeros((3, 3)), 0.0))
    for i in range(1, 6):
        h.book.put_map(f"r{i}", V(1), tiny(i))
    for a, b in [("r1", "r2"), ("r2", "r3"), ("r3", "r4"), ("r4", "r5"), ("r1", "r5")]:
        h.book.add_link(_link(a, b, np.eye(3)))
    assert h.worker.step(now=0.0)
    assert h.links[0].pair == ("r1", "r3") and len(h.checked) == 1 and len(h.calls) == 1


def test_a_link_records_soundness_is_judged_once(monkeypatch) -> None:
    """The pose graph's input checks run once per link record held, not once per step
    nor once more per rebuild (the rebuild at 0.1 s shares the worker's verdicts)."""
    import agent.globalmap as globalmap

    judged: list[tuple[str, str]] = []
    problem = globalmap.link_problem

    def counting(ln, nodes):
        judged.append(ln.pair)
        return problem(ln, nodes)

    monkeypatch.setattr(globalmap, "link_problem", counting)
    h = Checking("r3", Registration(True, np.eye(3), np.eye(3) * 0.1, 0.95))
    _chain(h)  # r1-r2, r2-r3 linked: r1-r3 is checked
    assert h.worker.step(now=0.0)
    assert sorted(judged) == [("r1", "r2"), ("r2", "r3")]
    assert not h.worker.step(now=0.1)  # r1-r3 added: a new Chains, only it judged
    assert sorted(judged) == [("r1", "r2"), ("r1", "r3"), ("r2", "r3")]
    assert h.globals[-1].settled and h.globals[-1].components[0].members == ("r1", "r2", "r3")


def _far_chain(h: Harness) -> None:
    """r1 - r2 - r3 linked, each 50 m (500 px) beyond the last: r1 and r3 100 m apart."""
    for r in ("r1", "r2", "r3"):
        h.book.put_map(r, V(1), tiny(int(r[1])))
    h.book.add_link(_link("r1", "r2", rigid_matrix(0.0, 500.0, 0.0)))
    h.book.add_link(_link("r2", "r3", rigid_matrix(0.0, 500.0, 0.0)))


def test_a_pair_placed_apart_is_not_checked_and_rejected_if_it_was_before() -> None:
    h = Checking("r3", Registration(True, np.eye(3), np.eye(3) * 0.1, 0.95))
    _rejected_in_epoch_0(h, "r1", "r3")
    _far_chain(h)
    assert h.worker.step(now=0.0)
    assert h.checked == [] and h.calls == []
    (rec,) = h.links
    assert rec.pair == ("r1", "r3") and not rec.accepted and rec.reason == APART
    np.testing.assert_allclose(rec.matrix, rigid_matrix(0.0, 1000.0, 0.0), atol=1e-9)
    assert h.worker.counters.snapshot()["counts"] == {"checks_skipped": 1}


def test_a_first_rejection_of_a_pair_placed_apart_is_searched() -> None:
    """As a check's: the chain may be wrong on a bridge, and the search finds the true link."""
    h = Checking("r3", None)
    _far_chain(h)
    assert h.worker.step(now=0.0)
    assert h.checked == [] and len(h.calls) == 1 and [ln.accepted for ln in h.links] == [True]
    assert h.worker.counters.snapshot()["counts"] == {"checks_skipped": 1, "searches": 1}


def _placed_apart_in_epoch_1(h: Harness, links: list[tuple[str, str]]) -> None:
    """r1-r4 accepted in epoch 0; in epoch 1, ``links`` place r1..r4 50 m (500 px) apart
    in a row, r1 and r4 150 m."""
    for i in range(1, 5):
        h.book.put_map(f"r{i}", V(0), tiny(i))
    old = LinkRecord("r1", V(0), "r4", V(0), True, np.eye(3), np.eye(3) * 0.1, 0.9, "r9")
    h.book.add_link(old)
    for i in range(1, 5):
        h.book.put_map(f"r{i}", V(1), tiny(i))
    for a, b in links:
        shift = 500.0 * (int(b[1]) - int(a[1]))
        h.book.add_link(_link(a, b, rigid_matrix(0.0, shift, 0.0)))


def test_an_accepted_pair_placed_apart_by_current_triangles_is_withdrawn_unchecked() -> None:
    """Epoch 1's links join r1 and r4 over triangles: the pair's own older link, which
    stands in meanwhile, does not hold the rejection back."""
    h = Checking("r4", None)
    _placed_apart_in_epoch_1(
        h, [("r1", "r2"), ("r1", "r3"), ("r2", "r3"), ("r2", "r4"), ("r3", "r4")]
    )
    assert h.worker.step(now=0.0)
    (rec,) = h.links
    assert rec.pair == ("r1", "r4") and rec.state == WITHDRAWN and rec.reason.endswith(APART)
    assert h.checked == [] and h.calls == []
    assert h.worker.counters.snapshot()["counts"] == {"checks_skipped": 1}


def test_an_accepted_pair_placed_apart_over_a_bridge_is_withdrawn_after_a_search() -> None:
    """Over a chain of bridges (and the pair's older link, which closes a lone cycle with
    them) no rejection may stand: the search decides, and contradicts the link."""
    h = Checking("r4", None)
    _placed_apart_in_epoch_1(h, [("r1", "r2"), ("r2", "r3"), ("r3", "r4")])

    def no_overlap(a: Grid, b: Grid) -> Registration:
        h.calls.append((0, 0))
        return Registration(False, np.eye(3), np.zeros((3, 3)), 0.0, "no overlap")

    h.worker.register = no_overlap
    assert h.worker.step(now=0.0)
    (rec,) = h.links
    assert rec.pair == ("r1", "r4") and rec.state == WITHDRAWN and len(h.calls) == 1


def test_a_rejection_rests_on_current_links_only() -> None:
    """r1-r2-r3-r1 of epoch 1 and r3-r4 of epoch 0 (r4 moved on to epoch 1): r1-r2 placed
    apart is rejected at once, r1-r4 (only over r4's older link) needs a search."""
    h = Checking("r2", None)
    for i in range(1, 5):
        h.book.put_map(f"r{i}", V(0), tiny(i))
    h.book.add_link(LinkRecord("r3", V(0), "r4", V(0), True, *_far(1), 0.9, "r9"))
    for i in range(1, 5):
        h.book.put_map(f"r{i}", V(1), tiny(i))
    for a, b in [("r1", "r3"), ("r2", "r3")]:
        h.book.add_link(_link(a, b, _far(int(b[1]) - int(a[1]))[0]))
    h.book.add_link(_link("r1", "r2", _far(1)[0]))
    snap = h.book.snapshot()
    kept = h.worker._solved_for(snap, "r1", "r4")[1]
    joins = _joins(_current_pairs(snap, kept))
    assert _rejection_stands(joins, snap.links, "r1", "r2")
    assert not _rejection_stands(joins, snap.links, "r1", "r4")


def _far(steps: int) -> tuple[np.ndarray, np.ndarray]:
    """A link's matrix and covariance, ``steps`` times 50 m along x."""
    return rigid_matrix(0.0, 500.0 * steps, 0.0), np.eye(3) * 0.1


@pytest.mark.parametrize("me, at_once", [("r2", False), ("r8", True)])
def test_whose_turn_a_pair_is_counts_the_robots_alive_before_their_maps(me, at_once) -> None:
    """Of eight robots up, r2 and r8 hold only each other's maps so far: r8 registers the pair
    at once, as every agent of the fleet reckons, and r2 waits for its link."""
    h = Harness(me)
    h.book.set_alive({f"r{i}" for i in range(1, 9)})
    h.book.put_map("r2", V(1), tiny(2))
    h.book.put_map("r8", V(1), tiny(8))
    assert h.worker.step(now=0.0) == at_once
    assert len(h.calls) == int(at_once)


def test_a_robot_newly_placed_with_the_agents_own_is_shown_before_more_registrations() -> None:
    h = Harness("r1")
    h.book.put_map("r1", V(1), tiny(1))
    assert not h.worker.step(now=0.0) and len(h.globals) == 1  # r1 alone
    h.book.put_map("r2", V(1), tiny(2))
    assert h.worker.step(now=5.0) and len(h.calls) == 1  # r1-r2 linked
    h.book.put_map("r2", V(2), tiny(3))  # a new epoch: r1-r2 is due again at once
    assert h.worker.step(now=5.1)
    assert len(h.calls) == 1 and len(h.globals) == 2  # shown first, registration put off
    assert h.globals[-1].components[0].members == ("r1", "r2")
    assert h.worker.step(now=5.2) and len(h.calls) == 2


@pytest.mark.parametrize("seed", range(3))
def test_cached_provisional_chains_are_a_fresh_build(seed: int) -> None:
    """Over a random sequence of link sets (accepts, provisional accepts, grey candidates,
    rejections, some sets met again), the provisional cycle test's cached pose graph is the
    one built from scratch: the same groups and placements, bit for bit."""
    rng = np.random.default_rng(seed)
    h = Harness("r1")
    robots = [f"r{i}" for i in range(1, 7)]
    maps = {r: (V(1), tiny(i)) for i, r in enumerate(robots)}
    bar = h.worker.min_margin
    kinds = [
        (True, CONFIRMED, bar + 0.5),
        (False, CANDIDATE, bar + 0.1),
        (False, CANDIDATE, bar - 0.2),
        (False, REJECTED, None),
    ]
    pool = []
    for i, a in enumerate(robots):
        for b in robots[i + 1 :]:
            accepted, state, margin = kinds[rng.integers(len(kinds))]
            m = rigid_matrix(rng.uniform(-3, 3), *rng.uniform(-50, 50, 2))
            pool.append(LinkRecord(a, V(1), b, V(1), accepted, m, np.eye(3) * 0.1, 0.9, "r1",
                                   state=state, margin=margin))  # fmt: skip
    sets = [list(rng.choice(pool, size=rng.integers(3, len(pool)), replace=False))
            for _ in range(4)]  # fmt: skip
    for k in rng.integers(len(sets), size=12):
        snap = Snapshot(maps, sets[k], False, [], None)
        pair = tuple(robots[j] for j in sorted(rng.choice(len(robots), 2, replace=False)))
        links, chains = h.worker._provisional_chains(snap, pair)
        fresh_links = [h.worker._as_accepted(ln, pair) for ln in sets[k]]
        fresh = Chains(maps, fresh_links)
        assert [ln.identity for ln in links] == [ln.identity for ln in fresh_links]
        assert chains.groups == fresh.groups
        got, want = chains.solved()[0], fresh.solved()[0]
        assert got.components == want.components and got.used == want.used
        for r in robots:
            assert got.transforms[r].tobytes() == want.transforms[r].tobytes()


class Gated(Checking):
    """A checking harness whose gate rejects the maps of ``small`` robots as map A."""

    def __init__(self, me: str, small: set[str]) -> None:
        super().__init__(me, None)
        self.small = {int(tiny(int(r[1:])).logodds.sum()) for r in small}
        self.gated: list[int] = []
        self.worker.gate = self.gate

    def gate(self, a: Grid) -> str | None:
        self.gated.append(int(a.logodds.sum()))
        return "map A has no GVD edge" if self.gated[-1] in self.small else None


def test_a_map_the_merge_rejects_as_a_is_not_searched_and_holds_the_next_wave() -> None:
    """r1's map is too small to search: r1-r2 is rejected without a search, said in the
    reason and counted, the gate asked once for r1's version; the second wave stays closed
    for GATE_HOLD_S, and r1's next epoch is searched."""
    h = Gated("r1", {"r1"})
    h.worker.link_timeout = 0.0  # r1 steps in for r4's turn at once
    for i in range(1, 5):
        h.book.put_map(f"r{i}", V(1), tiny(i))
    assert h.worker.step(now=0.0)
    (rec,) = h.links
    assert rec.pair == ("r1", "r2") and not rec.accepted and rec.reason.startswith(GATED)
    assert "r1 v1.0" in rec.reason and h.calls == []
    assert h.worker.counters.get("searches_gated") == 1
    h.worker.step(now=0.1)  # r1-r4, the other first-wave pair of r1's: gated too
    assert [ln.pair for ln in h.links] == [("r1", "r2"), ("r1", "r4")] and h.calls == []
    assert h.gated.count(h.gated[0]) == 1  # once per (robot, version)
    for a, b in (("r2", "r3"), ("r3", "r4"), ("r2", "r4")):  # the others, decided
        h.book.add_link(_link(a, b, np.eye(3)))
    assert not h.worker.step(now=1.0) and len(h.links) == 2  # r1-r3 waits: the wave is held
    assert h.worker.step(now=1.0 + GATE_HOLD_S)
    assert h.links[-1].pair == ("r1", "r3") and h.links[-1].reason.startswith(GATED)
    h.small.clear()  # r1's map grew into a new epoch: searched
    h.book.put_map("r1", V(2), tiny(1))
    assert h.worker.step(now=20.0) and len(h.calls) == 1


@pytest.mark.parametrize("seed", range(3))
def test_memoised_open_keys_are_a_fresh_computation_over_a_replay(seed: int) -> None:
    """Maps, links (accepted, rejected, gated) and liveliness change at random; at each step
    the keys open and checkable, reused while nothing they depend on changed, are those
    computed from scratch."""
    rng = np.random.default_rng(seed)
    h = Checking("r1", None)
    robots = [f"r{i}" for i in range(1, 8)]
    epochs = dict.fromkeys(robots, 1)
    for i, r in enumerate(robots):
        h.book.put_map(r, V(1), tiny(i))
    for step in range(60):
        what = rng.integers(4)
        a, b = sorted(rng.choice(robots, 2, replace=False))
        if what == 0:
            r = robots[rng.integers(len(robots))]
            epochs[r] += int(rng.integers(2))
            h.book.put_map(r, V(epochs[r], step + 1), tiny(int(r[1:])))
        elif what == 1:
            ea, eb = (h.book.version(r) for r in (a, b))
            kind = rng.integers(3)
            reason = f"{GATED}map A has no GVD edge" if kind == 2 else ""
            h.book.add_link(LinkRecord(a, ea, b, eb, kind == 0, np.eye(3),
                                       np.eye(3) * 0.1 if kind == 0 else np.zeros((3, 3)),
                                       0.9, "r9", reason=reason))  # fmt: skip
        elif what == 2:
            h.book.set_alive(set(rng.choice(robots, rng.integers(1, 8), replace=False)))
        snap = h.book.snapshot()
        ring = sorted(set(snap.maps) | (snap.alive or frozenset()))
        checkable, opened = h.worker._open(snap, ring, now=0.0)
        chains = Chains(snap.maps, snap.links)
        versions = {r: v for r, (v, _) in snap.maps.items()}
        holding = [ln.pair for ln in snap.links
                   if not ln.accepted and GATED in ln.reason and ln.current(versions)]  # fmt: skip
        fresh = set(snap.rechecks) | {k for k in snap.needed if chains.linked(k[0], k[2])}
        assert checkable == fresh
        assert opened == open_keys(snap.needed, fresh, ring, holding)


@pytest.mark.parametrize(("margin", "carried"), [(0.6, False), (0.95, True)])
def test_only_an_accept_above_the_high_bar_is_carried_onto_a_newer_epoch(
    intel_pair, margin: float, carried: bool
) -> None:
    """Real maps; both start a new epoch while the search runs.  A provisional accept
    (below the high bar) is not checked from its own pose on the new maps, which converged
    on a near miss again and confirmed it: the newer epoch's own decision confirms it.  An
    accept above the high bar is carried, as before."""
    a, b, truth = intel_pair
    h = Checking("r1", Registration(True, truth, np.eye(3) * 0.1, 0.9, margin=0.9))

    def searched(grid_a: Grid, grid_b: Grid) -> Registration:
        h.book.put_map("r1", V(2), a)  # the maps move on meanwhile
        h.book.put_map("r2", V(2), b)
        return Registration(True, truth, np.eye(3) * 0.1, 0.9, margin=margin)

    h.worker.register = searched
    h.book.put_map("r1", V(1), a)
    h.book.put_map("r2", V(1), b)
    assert h.worker.step(now=0.0)
    newer = [ln for ln in h.links if ln.key == ("r1", 2, "r2", 2)]
    assert len(h.checked) == int(carried)
    assert [ln.state for ln in newer] == (["accepted"] if carried else [])


def test_a_grey_decision_superseded_while_searched_still_ends_a_provisional_accept(
    intel_pair,
) -> None:
    """Real maps.  A search's provisional accept (0.64) on epochs 1/1; the first search of
    epochs 2/1 lands in the grey zone (0.42), but r2 starts epoch 2 while it runs, so the
    book never holds that record; a search of 2/2 accepts the first pose again (0.58).  The
    grey decision was the newer epoch's first word on the pair: the 0.58 accept is only a
    provisional one, not a confirmation of the 0.64 accept (a look-alike in the fleet
    bench was confirmed so, and shown wrong for 3 s)."""
    a, b, pose = intel_pair
    h = Checking("r1", None)
    margins = iter([0.64, 0.42, 0.58])

    def searched(grid_a: Grid, grid_b: Grid) -> Registration:
        margin = next(margins)
        if margin == 0.42:
            h.book.put_map("r2", V(2), b)  # r2 moves on while the grey search runs
        return Registration(margin >= 0.57, pose, np.eye(3) * 0.1, 0.9, margin=margin)

    h.worker.register = searched
    h.book.put_map("r1", V(1), a)
    h.book.put_map("r2", V(1), b)
    for t, r1_epoch in ((0.0, 1), (1.0, 2), (2.0, 2)):
        h.book.put_map("r1", V(r1_epoch), a)
        assert h.worker.step(now=t)
    decided = [(ln.key, ln.state, ln.margin) for ln in h.links]
    assert decided == [(("r1", 1, "r2", 1), CANDIDATE, 0.64), (("r1", 2, "r2", 2), CANDIDATE, 0.58)]


def test_a_preview_is_fused_without_the_blur_and_the_settled_map_with_it() -> None:
    """Eq. (8)'s blur is spent on the settled map only; a preview of the same maps and
    links is the maps placed without it, and the settled map follows even when nothing
    but the round's end changed."""
    from agent.globalmap import build_components

    root = Path(__file__).resolve().parents[1] / "examples"
    a, b = read_map(root / "intel_a.yaml"), read_map(root / "intel_b.yaml")
    res = merge(a, b)
    assert res.accepted
    h = Harness("r3")  # r1-r4 and r2-r4 are r1's and r2's turns: r3 waits, unsettled
    for robot, grid in (("r1", a), ("r2", b), ("r4", Grid(tiny(1).logodds, a.resolution))):
        h.book.put_map(robot, V(1), grid)
    loose = np.diag([4.0, 4.0, np.radians(0.5) ** 2])  # wide enough to blur visibly
    joined = LinkRecord("r1", V(1), "r2", V(1), True, res.matrix, loose, 0.95, "r1")
    h.book.add_link(joined)
    for now in (0.0, 0.1, 0.2):
        h.worker.step(now=now)
    (preview,) = h.globals
    assert not preview.settled and not h.calls
    snap = h.book.snapshot()
    plain, blurred = (
        build_components(snap.maps, snap.links, firsts=snap.firsts, blur=blur)
        for blur in (False, True)
    )
    assert [c.digest for c in preview.components] == [c.digest for c in plain]
    assert plain[0].digest != blurred[0].digest  # the blur does change the map
    for other in ("r1", "r2"):  # the round ends: no new map, one more link each
        h.book.add_link(
            LinkRecord(other, V(1), "r4", V(1), False, np.eye(3), np.eye(3), 0.0, other)
        )
    h.worker.step(now=0.3)
    settled = h.globals[-1]
    assert settled.settled and len(h.globals) == 2
    assert settled.components[0].digest == blurred[0].digest
