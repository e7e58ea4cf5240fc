"""The acceptance decision (pgvd.decision) and the residual distortion, on real maps."""

from __future__ import annotations

import numpy as np
import pytest

from pgvd.agreement import local_agreement, local_agreements, map_agreement
from pgvd.alignment import residual_distortion
from pgvd.decision import Scored, decide, describe_rival, restate, same_pose, shifted
from pgvd.grid import Grid, relative_matrix, rigid_matrix
from pgvd.io import read_map
from pgvd.merge import merge
from pgvd.overlay import Agreement
from pgvd.params import MergeParams
from pgvd.walls import WallMap

WEIGHT = MergeParams().disagreement_weight


@pytest.fixture(scope="module")
def intel(shared):
    a = read_map(shared / "maps" / "intel_split_gt" / "intel_partA.yaml")
    b = read_map(shared / "maps" / "intel_split_gt" / "intel_partB.yaml")
    fine_a = WallMap(a.probability(), 0.65, 0.3)
    fine_b = WallMap(b.probability(), 0.65, 0.3)
    return fine_a, fine_b, relative_matrix(a, b)


def _scored(intel, matrix: np.ndarray) -> Scored:
    fine_a, fine_b, _ = intel
    return Scored(matrix, map_agreement(fine_a, fine_b, matrix, max_points=1500))


def _moved(truth: np.ndarray, dx: float) -> np.ndarray:
    return rigid_matrix(0.0, dx, 0.0) @ truth


def test_true_pose_stands_out_and_a_rival_as_good_cancels_it(intel):
    _, fine_b, truth = intel
    centre = fine_b.walls.mean(axis=0)
    true, off = _scored(intel, truth), _scored(intel, _moved(truth, 60.0))
    d = decide([off, true], WEIGHT, centre)
    assert d.winner is true
    assert d.margin >= MergeParams().min_margin, d
    assert d.rival < true.evidence(WEIGHT)
    # the same pose reached twice is not a rival of itself
    again = Scored(_moved(truth, 1.0), true.agreement)
    assert same_pose(again.matrix, truth, centre, 2.0, 20.0)
    assert decide([true, again], WEIGHT, centre).rival == -np.inf
    # a look-alike: another pose scoring as well as the winner leaves no margin
    twin = Scored(_moved(truth, 200.0), true.agreement)
    assert decide([true, twin], WEIGHT, centre).margin == pytest.approx(0.0)


def test_the_best_rival_is_kept_and_described(intel):
    _, fine_b, truth = intel
    centre = fine_b.walls.mean(axis=0)
    true = _scored(intel, truth)
    # a quarter turn about A's origin: B lands beside A, no wall on a wall and none on free
    turned = _scored(intel, rigid_matrix(np.radians(90.0), 0.0, 0.0) @ truth)
    probes = [_scored(intel, m) for m in shifted(truth, (30.0, 60.0))]
    alone = decide([true], WEIGHT, centre)
    assert alone.best is None and alone.rival == -np.inf
    assert describe_rival(alone, centre, 0.05) == "none"
    d = decide([true, turned], WEIGHT, centre)
    assert d.best is turned and d.rival == d.other == turned.evidence(WEIGHT)
    assert d.shifted == -np.inf
    assert describe_rival(d, centre, 0.05) == "another pose 27.6 m and 90 deg away"
    # the probes alone: the intel lab puts each shifted copy's walls on free space, and the
    # least contradicted one (1.5 m) is the best rival
    shift = decide([true], WEIGHT, centre, probes=probes)
    assert shift.best is max(probes, key=lambda s: s.evidence(WEIGHT))
    assert shift.rival == shift.shifted < 0 and shift.other == -np.inf
    assert describe_rival(shift, centre, 0.05) == "the pose shifted 1.5 m"
    # both kinds: the margin is measured against the larger evidence, the turned pose's
    both = decide([true, turned], WEIGHT, centre, probes=probes)
    assert (both.other, both.shifted, both.best) == (d.other, shift.shifted, turned)
    assert both.margin == d.margin
    # the copies alone, contradicted by the maps, count as no rival at all
    assert shift.margin == decide([true], WEIGHT, centre).margin


def test_shifted_probes_are_rivals_only(intel):
    _, fine_b, truth = intel
    centre = fine_b.walls.mean(axis=0)
    true = _scored(intel, truth)
    probes = [_scored(intel, m) for m in shifted(truth, (30.0, 60.0))]
    assert len(probes) == 8
    d = decide([true], WEIGHT, centre, probes=probes)
    # the intel lab pins the pose: 1.5 and 3 m away it scores far less
    assert d.winner is true and d.margin >= MergeParams().min_margin, d
    # a probe as good as the winner (a corridor alike along its length) leaves no margin
    alike = Scored(shifted(truth, (30.0,))[0], true.agreement)
    assert decide([true], WEIGHT, centre, probes=[alike]).margin == pytest.approx(0.0)


def test_decide_needs_a_hypothesis():
    with pytest.raises(ValueError, match="at least one"):
        decide([], WEIGHT, np.zeros(2))


def test_distortion_grows_when_part_of_b_is_displaced(intel):
    fine_a, fine_b, truth = intel
    rigid = residual_distortion(fine_a.tree, fine_b.walls, truth)
    # bend B: walls right of its middle move by 6 px along y, as drift would move them
    bent = fine_b.walls.copy()
    moved_x = (bent @ truth[:2, :2].T + truth[:2, 2])[:, 0]
    bent[moved_x > np.median(moved_x), 1] += 6.0
    drifted = residual_distortion(fine_a.tree, bent, truth)
    assert rigid < 3.0 and drifted > rigid + 3.0, (rigid, drifted)


def test_a_building_against_its_mirror_image_is_rejected(shared):
    a = read_map(shared / "maps" / "fr079_split_gt" / "fr079_partA.yaml")
    mirror = Grid(np.ascontiguousarray(a.logodds[:, ::-1]), a.resolution)
    r = merge(a, mirror, MergeParams(diagnostics=False))
    assert not r.accepted, r.reason
    assert r.margin < MergeParams().min_margin


def _bent(b: WallMap, truth: np.ndarray, prob: np.ndarray, px: int) -> WallMap:
    """B's map with the part that lands right of the middle of A moved ``px`` rows down,
    as odometry drift moves the far end of a map."""
    h, w = prob.shape
    cols, rows = np.meshgrid(np.arange(w), np.arange(h))
    ax = truth[0, 0] * cols + truth[0, 1] * rows + truth[0, 2]
    middle = np.median(b.walls @ truth[0, :2] + truth[0, 2])
    moved = np.full_like(prob, 0.5)
    moved[px:] = prob[:-px]
    return WallMap(np.where(ax > middle, moved, prob), 0.65, 0.3)


def test_local_agreement_forgives_drift_not_a_wrong_pose(shared, intel):
    fine_a, fine_b, truth = intel
    b = read_map(shared / "maps" / "intel_split_gt" / "intel_partB.yaml")
    bent = _bent(fine_b, truth, b.probability(), 6)
    block, shift = 100.0, 10.0

    def evidence(ag: Agreement) -> float:
        return ag.agree - WEIGHT * ag.disagree

    straight = local_agreement(fine_a, fine_b, truth, block, shift, max_points=1500)
    rigid = map_agreement(fine_a, bent, truth, max_points=1500)
    local = local_agreement(fine_a, bent, truth, block, shift, max_points=1500)
    # rigidly, half of the bent map's walls run 6 px beside A's: the true pose loses
    assert evidence(rigid) < 0, rigid
    # re-aligned per 5 m square, the bent map agrees nearly as well as the straight one
    assert evidence(local) > 0.8 * evidence(straight), (local, straight)
    # a pose 3 m or 3 degrees off keeps its walls on A's free space: still contradicted
    for wrong in (rigid_matrix(0.0, 60.0, 0.0) @ truth, rigid_matrix(0.05, 0.0, 0.0) @ truth):
        off = local_agreement(fine_a, bent, wrong, block, shift, max_points=1500)
        assert evidence(off) < 0 < evidence(local), off


def test_poses_scored_together_count_as_one_by_one(shared, intel):
    # the decision scores its finalists and probes in one pass: the truth, poses off by a
    # few cells, by 3 m and by 3 degrees, on the straight and on the bent map, with a lookup
    # table for A as the merge has
    fine_a, fine_b, truth = intel
    b = read_map(shared / "maps" / "intel_split_gt" / "intel_partB.yaml")
    lookup_a = WallMap(
        read_map(shared / "maps" / "intel_split_gt" / "intel_partA.yaml").probability(),
        0.65,
        0.3,
        lookup=True,
    )
    poses = [truth, *(rigid_matrix(0.0, dx, 0.0) @ truth for dx in (3.0, -7.0, 60.0))]
    poses.append(rigid_matrix(0.05, 0.0, 0.0) @ truth)
    for map_a, map_b in ((lookup_a, fine_b), (fine_a, _bent(fine_b, truth, b.probability(), 6))):
        together = local_agreements(map_a, map_b, poses, 100.0, 10.0, max_points=1500)
        alone = [local_agreement(map_a, map_b, m, 100.0, 10.0, max_points=1500) for m in poses]
        assert together == alone
        assert len({(ag.agree, ag.disagree) for ag in alone}) == len(poses)


def test_a_contradicted_rival_counts_as_no_rival(intel):
    # being contradicted less than a rival is no evidence: with contradicted rivals
    # counting for it, a willow disjoint pair passed at 0.97 (bench/results/merge-turned.md)
    _, fine_b, truth = intel
    centre = fine_b.walls.mean(axis=0)
    win = Scored(truth, Agreement(900, 100))
    alone = decide([win], WEIGHT, centre).margin
    assert alone == pytest.approx((900 - WEIGHT * 100) / 1000)
    far = Scored(_moved(truth, 200.0), Agreement(100, 400))
    assert decide([win, far], WEIGHT, centre).margin == alone
    close = Scored(_moved(truth, 200.0), Agreement(450, 0))
    assert decide([win, close], WEIGHT, centre).margin == pytest.approx(0.05)


def test_a_contradicted_winner_has_no_margin_whatever_its_rivals(shared, intel):
    fine_a, fine_b, truth = intel
    b = read_map(shared / "maps" / "intel_split_gt" / "intel_partB.yaml")
    bent = _bent(fine_b, truth, b.probability(), 6)
    centre = fine_b.walls.mean(axis=0)
    # scored rigidly, half of the bent map's walls lie beside A's: even the true pose is
    # contradicted, and a pose 3 m off is contradicted more
    win, rival = (
        Scored(m, map_agreement(fine_a, bent, m, max_points=1500))
        for m in (truth, _moved(truth, 60.0))
    )
    assert rival.evidence(WEIGHT) < win.evidence(WEIGHT) < 0, (win, rival)
    d = decide([rival, win], WEIGHT, centre)
    assert d.winner is win and d.rival == rival.evidence(WEIGHT)
    # being contradicted less than a rival is no evidence for a pose
    points = win.agreement.agree + win.agreement.disagree
    assert d.margin == pytest.approx(win.evidence(WEIGHT) / points)
    assert d.margin < 0


def test_local_agreement_refuses_bad_squares(intel):
    fine_a, fine_b, truth = intel
    for block, shift in ((0.0, 10.0), (-5.0, 10.0), (100.0, -1.0), (float("nan"), 1.0)):
        with pytest.raises(ValueError, match="block must be"):
            local_agreement(fine_a, fine_b, truth, block, shift)
    # no shift at all is the rigid count
    rigid = map_agreement(fine_a, fine_b, truth, max_points=1500)
    assert local_agreement(fine_a, fine_b, truth, 100.0, 0.0, max_points=1500) == rigid


def test_restate_measures_the_returned_pose_against_the_same_rival(intel):
    _, fine_b, truth = intel
    centre = fine_b.walls.mean(axis=0)
    # the finalists' quick refinement left the winner 4 px and 0.5 degrees off
    off = _scored(intel, rigid_matrix(np.radians(0.5), 4.0, -4.0) @ truth)
    rival = _scored(intel, _moved(truth, 200.0))
    first = decide([off, rival], WEIGHT, centre)
    assert first.winner is off
    final = _scored(intel, truth)
    again = restate(first, final, WEIGHT)
    assert again.winner is final and again.rival == first.rival
    points = final.agreement.agree + final.agreement.disagree
    against = max(first.rival, 0.0)
    assert again.margin == pytest.approx((final.evidence(WEIGHT) - against) / points)
    # the refined pose puts more walls on walls: its margin, not the rough one's, decides
    assert again.margin > first.margin, (again, first)


def test_a_small_overlap_must_stand_out_more(intel):
    fine_a, fine_b, truth = intel
    centre = fine_b.walls.mean(axis=0)
    noise = MergeParams().margin_noise
    drops = []
    # the same true pose and rival counted on ~150 and ~1500 walls a map: about the same
    # margin per wall, but the small count's margin is the less certain
    for points in (150, 1500):
        win, rival = (
            Scored(m, map_agreement(fine_a, fine_b, m, max_points=points))
            for m in (truth, _moved(truth, 60.0))
        )
        plain = decide([win, rival], WEIGHT, centre)
        lowered = decide([win, rival], WEIGHT, centre, noise=noise)
        n = win.agreement.agree + win.agreement.disagree
        assert lowered.margin == pytest.approx(plain.margin - noise / np.sqrt(n))
        # the returned pose's margin is lowered the same way
        assert restate(plain, win, WEIGHT, noise).margin == pytest.approx(lowered.margin)
        drops.append(plain.margin - lowered.margin)
    assert drops[0] > 2.5 * drops[1] > 0, drops
