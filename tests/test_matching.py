"""Edge matching (25)-(32), pair support, map agreement and refinement."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from pgvd.agreement import map_agreement
from pgvd.alignment import alignment_fit, refine, refine_point_to_line, residual_distortion
from pgvd.covariance import calibrated_covariance
from pgvd.edge_matching import EdgeCorrelator, PairSupport, rho_test, similarity
from pgvd.graph import build_graph
from pgvd.grid import rigid_matrix
from pgvd.io import read_map
from pgvd.overlay import MapView, OverlayScores, OverlayWeights
from pgvd.pooling import coarsen
from pgvd.walls import WallMap


def _shapes(offset: tuple[int, int], shape=(80, 90)) -> np.ndarray:
    """Three unlike skeleton edges (an L, a straight line, a hook), moved by ``offset`` (x, y)."""
    s = np.zeros(shape, bool)
    ox, oy = offset
    s[10 + oy, 10 + ox : 40 + ox] = True  # straight
    s[25 + oy : 45 + oy, 10 + ox] = True  # L: vertical part ...
    s[45 + oy, 10 + ox : 22 + ox] = True  # ... and foot
    s[30 + oy : 50 + oy, 60 + ox] = True  # hook
    s[30 + oy, 60 + ox : 66 + ox] = True
    s[30 + oy : 36 + oy, 66 + ox] = True
    return s


@pytest.fixture(scope="module")
def graphs():
    a = _shapes((0, 0))
    b = _shapes((7, -4))
    ga = build_graph(a, a * 0.9, min_edge_length=5)
    gb = build_graph(b, b * 0.9, min_edge_length=5)
    assert len(ga.edges) == len(gb.edges) == 3
    return ga, gb


@pytest.mark.parametrize("tolerance", [0, 1])
def test_gamma_of_shifted_copies_gives_the_shift(graphs, tolerance):
    ga, gb = graphs
    sim = similarity(ga.edges, gb.edges, tolerance)
    for i, e in enumerate(ga.edges):
        j = int(np.argmax(sim.gamma[i]))
        assert gb.edges[j].length == e.length
        assert sim.gamma[i, j] == pytest.approx(e.length * 0.81, rel=1e-4)
        # B = A moved by (+7, -4), so B -> A is (-7, +4)
        np.testing.assert_array_equal(sim.shift[i, j], [-7, 4])


def test_gamma_of_edge_with_itself_has_zero_shift(graphs):
    ga, _ = graphs
    sim = similarity(ga.edges, ga.edges, 0)
    np.testing.assert_array_equal(np.argmax(sim.gamma, axis=1), np.arange(3))
    np.testing.assert_array_equal(sim.shift[np.arange(3), np.arange(3)], 0)


def test_sparse_pair_support_matches_fft_gamma(graphs):
    ga, gb = graphs
    sim = similarity(ga.edges, gb.edges, 1)
    pairs = PairSupport(EdgeCorrelator(ga.edges, 1), ga.labels.shape, gb.edges)
    e = pairs.correlations([(-7, 4)])[0]
    for i in range(3):
        j = int(np.argmax(sim.gamma[i]))
        assert e[i, j] == pytest.approx(sim.gamma[i, j], rel=1e-5)


def test_pair_support_at_many_translations_is_each_one_alone(intel):
    from pgvd.gvd import pgvd

    c = coarsen(intel, 4)
    ga = build_graph(*pgvd(c), min_edge_length=5)
    gb = build_graph(*pgvd(c[10:90, 20:100]), min_edge_length=5)
    assert len(ga.edges) > 5 and len(gb.edges) > 5
    pairs = PairSupport(EdgeCorrelator(ga.edges, 1), c.shape, gb.edges)
    # the crop's true offset, translations beside it and some off the map
    ts = [(20, 10), (21, 10), (23, 8), (-5, 40), (500, -300), (20, 10)]
    batch = pairs.correlations(ts)
    assert batch.shape == (len(ts), len(ga.edges), len(gb.edges))
    for t, e in zip(ts, batch, strict=True):
        np.testing.assert_array_equal(e, pairs.correlations([t])[0])
    assert batch[0].sum() > batch[3].sum() and not batch[4].any()
    assert pairs.correlations([]).shape == (0, len(ga.edges), len(gb.edges))


def test_rho_test_rejects_a_weak_match():
    a = np.zeros((60, 60), bool)
    a[30, 10:50] = True  # horizontal
    b_same = a.copy()
    b_cross = np.zeros((60, 60), bool)
    b_cross[10:50, 30] = True  # vertical: crosses A's edge in a few cells only
    ea = build_graph(a, a * 0.9, 5).edges
    for b, expect in ((b_same, True), (b_cross, False)):
        eb = build_graph(b, b * 0.9, 5).edges
        sim = similarity(ea, eb, 1)
        assert bool(rho_test(sim.gamma, ea, eb, rho=0.7)[0, 0]) is expect
    with pytest.raises(ValueError):
        rho_test(sim.gamma, ea, eb, rho=0.0)


@pytest.fixture(scope="module")
def intel(shared):
    return read_map(shared / "maps/intel_split_gt/intel_partA.yaml").probability()


def test_map_agreement_of_real_map(intel):
    wm = WallMap(intel, 0.65, 0.3)
    same = map_agreement(wm, wm, np.eye(3))
    moved = map_agreement(wm, wm, rigid_matrix(0.0, 12.0, -9.0))
    assert same.ratio > 0.99 and same.disagree == 0
    assert moved.ratio < 0.6


def test_dense_overlay_scores_equal_direct_counts(intel):
    c = coarsen(intel, 4)
    va = MapView(c, 0.65, 0.3, 1)
    vb = MapView(c[10:90, 20:100], 0.65, 0.3, 1)
    ov = OverlayScores(va, free=True).overlay(vb)
    agree, disagree = ov.agree, ov.disagree
    size = agree.shape
    for tx, ty in [(20, 10), (23, 8), (-5, 40)]:
        rb, cb = np.nonzero(vb.occ)
        ra, ca_ = np.nonzero(va.occ)
        direct_agree = 0
        direct_dis = 0
        for (r, col), dst in (((rb + ty, cb + tx), va), ((ra - ty, ca_ - tx), vb)):
            ok = (r >= 0) & (r < dst.shape[0]) & (col >= 0) & (col < dst.shape[1])
            direct_agree += int(dst.near[r[ok], col[ok]].sum())
            direct_dis += int(dst.clear[r[ok], col[ok]].sum())
        assert ov.at((tx, ty)).agree == direct_agree
        assert ov.at((tx, ty)).disagree == direct_dis
        # cells free in both: B's free cells looked up in A, counted once
        rf, cf = np.nonzero(vb.free)
        r, col = rf + ty, cf + tx
        ok = (r >= 0) & (r < va.shape[0]) & (col >= 0) & (col < va.shape[1])
        direct_free = int(va.free[r[ok], col[ok]].sum())
        weights = OverlayWeights(conflict=12.0, free=0.5)
        expected = direct_agree + 0.5 * direct_free - 12.0 * direct_dis
        assert ov.evidence_at((tx, ty), weights) == pytest.approx(expected)
    walls_only = OverlayScores(va).overlay(vb)
    np.testing.assert_array_equal(walls_only.evidence(), ov.evidence())
    with pytest.raises(ValueError, match="free space was not counted"):
        walls_only.evidence(OverlayWeights(free=0.5))
    # the true offset of the crop is the best agreement, up to the one-cell tolerance
    best = np.unravel_index(np.argmax(agree - disagree), size)
    assert abs(int(best[0]) - 10) <= 1 and abs(int(best[1]) - 20) <= 1
    assert ov.best_near_each([(17, 13)], 5) == [(int(best[1]), int(best[0]))]


@pytest.mark.parametrize("radius", [0, 3, 12, 200])
def test_overlay_peaks_are_the_wrapped_local_maxima(intel, radius):
    from scipy import ndimage

    c = coarsen(intel, 4)
    ov = OverlayScores(MapView(c, 0.65, 0.3, 1)).overlay(MapView(c[10:90, 20:100], 0.65, 0.3, 1))
    ev = ov.evidence(OverlayWeights(4.0))
    # the definition: largest evidence within the radius, the overlay wrapping around
    top = ndimage.maximum_filter(ev, size=2 * radius + 1, mode="wrap")
    rows, cols = np.nonzero((ev == top) & (ev > 0))
    order = np.argsort(-ev[rows, cols], kind="stable")[:5]
    (ha, wa), (h, w) = ov.shape_a, ev.shape
    expected = [
        (int(c_) if c_ < wa else int(c_) - w, int(r) if r < ha else int(r) - h)
        for r, c_ in zip(rows[order], cols[order], strict=True)
    ]
    assert ov.peaks(5, radius, OverlayWeights(4.0)) == expected
    # the best peak is the crop's true offset (20, 10), up to the one-cell tolerance
    assert abs(expected[0][0] - 20) <= 1 and abs(expected[0][1] - 10) <= 1


def test_refine_and_covariance_on_real_walls(intel):
    wm = WallMap(intel, 0.65, 0.3)
    truth = rigid_matrix(np.radians(1.0), 3.0, -2.0)
    walls_b = (wm.walls - truth[:2, 2]) @ np.linalg.inv(truth[:2, :2]).T  # A = truth(B)
    m = refine(wm.tree, walls_b, np.eye(3))
    np.testing.assert_allclose(m, truth, atol=0.02)
    cov = calibrated_covariance(alignment_fit(wm.tree, walls_b, m), 0.05)
    assert np.all(np.isfinite(cov)) and np.all(np.linalg.eigvalsh(cov) > 0)
    assert np.sqrt(cov[0, 0]) < 1.0 and np.sqrt(cov[2, 2]) < np.radians(0.5)


def test_point_to_line_refinement_recovers_a_turn_that_slides_along_walls(intel):
    wm = WallMap(intel, 0.65, 0.3)
    truth = rigid_matrix(np.radians(1.0), 3.0, -2.0)
    walls_b = (wm.walls - truth[:2, 2]) @ np.linalg.inv(truth[:2, :2]).T  # A = truth(B)
    # start 0.4 deg and 1.5 px off, inside the capture radius
    start = rigid_matrix(np.radians(1.4), 4.5, -2.0)
    m = refine_point_to_line(wm.tree, walls_b, start)

    def error(mat: np.ndarray) -> float:
        """Mean displacement (px) of B's walls between ``mat`` and the truth."""
        return float(
            np.linalg.norm(
                (walls_b @ (mat - truth)[:2, :2].T) + (mat - truth)[:2, 2], axis=1
            ).mean()
        )

    assert error(m) < 0.2 < error(start), (error(start), error(m))
    # a third of B's walls displaced by 8 px (a drifted part) does not drag the pose
    bent = walls_b.copy()
    bent[: len(bent) // 3] += 8.0
    assert error(refine_point_to_line(wm.tree, bent, truth)) < 0.5


def test_covariance_is_large_along_a_corridor():
    xs = np.arange(0.0, 200.0)
    walls = np.vstack(
        [
            np.column_stack([xs, np.full_like(xs, 10.0)]),
            np.column_stack([xs, np.full_like(xs, 30.0)]),
        ]
    )
    from scipy.spatial import cKDTree

    cov = calibrated_covariance(alignment_fit(cKDTree(walls), walls, np.eye(3)), 0.05)
    # two straight parallel walls fix y and the heading, not x
    assert cov[0, 0] > 1e3 * cov[1, 1]
    assert np.sqrt(cov[1, 1]) < 0.1


def test_refine_and_covariance_of_an_empty_wall_set(intel):
    """No wall cells in B: their own guards answer (matrix kept, infinite covariance)."""
    wm = WallMap(intel, 0.65, 0.3)
    empty = np.empty((0, 2))
    start = rigid_matrix(0.2, 5.0, -3.0)
    np.testing.assert_array_equal(refine(wm.tree, empty, start), start)
    cov = calibrated_covariance(alignment_fit(wm.tree, empty, start), 0.05)
    assert np.all(np.isinf(np.diag(cov)))
    blank = WallMap(np.full((40, 50), 0.5), 0.65, 0.3)  # all unknown: no walls, nothing free
    assert blank.walls.shape == (0, 2)
    assert map_agreement(wm, blank, start, max_points=500).agree == 0


def test_wall_tree_keeps_normals_that_change_nothing(intel):
    from scipy.spatial import cKDTree

    wm = WallMap(intel, 0.65, 0.3)
    # built as WallTree builds it: equidistant wall cells are found in the same order
    plain = cKDTree(wm.walls, balanced_tree=False, compact_nodes=False)
    truth = rigid_matrix(np.radians(1.5), 4.0, -3.0)
    walls_b = (wm.walls - truth[:2, 2]) @ np.linalg.inv(truth[:2, :2]).T
    start = rigid_matrix(0.0, 2.0, -1.0)
    # twice on the cached tree (the second run reads the normals the first one kept)
    for _ in range(2):
        np.testing.assert_array_equal(
            refine_point_to_line(wm.tree, walls_b, start),
            refine_point_to_line(plain, walls_b, start),
        )
    assert residual_distortion(wm.tree, walls_b, truth) == residual_distortion(
        plain, walls_b, truth
    )


def test_nearest_wall_table_agrees_with_the_tree(intel):
    wm = WallMap(intel, 0.65, 0.3, lookup=True)
    h, w = intel.shape
    rng = np.random.default_rng(3)
    # on and near the walls, anywhere on the map, and up to 15 cells off it
    pts = np.vstack(
        [
            wm.walls[rng.integers(0, len(wm.walls), 20000)] + rng.normal(0, 3, (20000, 2)),
            rng.uniform([-15, -15], [w + 15, h + 15], (20000, 2)),
        ]
    )
    for reach in (2.0, 12.0):
        dist, idx = wm.nearest(pts, reach)
        exact, _ = wm.tree.query(pts, distance_upper_bound=reach)
        found = np.isfinite(dist)
        # a wall the table names is a real wall at the distance given, never nearer
        # than the nearest one, and beyond reach nothing is named
        np.testing.assert_allclose(dist[found], np.hypot(*(wm.walls[idx[found]] - pts[found]).T))
        assert np.all(idx[~found] == len(wm.walls))
        assert np.all(dist[found] >= exact[found] - 1e-9)
        both = found & np.isfinite(exact)
        assert np.mean(np.isclose(dist[both], exact[both])) > 0.99
        assert np.max(dist[both] - exact[both]) < 0.5
        assert np.mean(found != np.isfinite(exact)) < 1e-3


@settings(max_examples=60)
@given(
    walls=arrays(bool, st.tuples(st.integers(1, 12), st.integers(1, 12))),
    points=arrays(float, (16, 2), elements=st.floats(-4.0, 16.0)),
)
def test_nearest_wall_by_table_is_a_wall_near_the_nearest(walls, points):
    prob = np.where(walls, 0.9, 0.1)
    wm = WallMap(prob, 0.65, 0.3, lookup=True)
    dist, idx = wm.nearest(points, 100.0)
    if not walls.any():
        assert np.all(np.isinf(dist)) and np.all(idx == 0)
        return
    nearest = np.min(np.linalg.norm(points[:, None] - wm.walls[None], axis=2), axis=1)
    np.testing.assert_allclose(dist, np.linalg.norm(wm.walls[idx] - points, axis=1))
    assert np.all(dist >= nearest - 1e-9)
    # over the map a corner cell c of the point p is within 0.71 of it, and the table names
    # c's nearest wall (an exact transform): d <= (nearest + 0.71) + 0.71.
    # Off the map the cells read are those on its border, and the bound does not hold.
    h, w = walls.shape
    on = (points[:, 0] >= 0) & (points[:, 0] <= w - 1) & (points[:, 1] >= 0)
    on &= points[:, 1] <= h - 1
    assert np.all(dist[on] <= nearest[on] + 2 * 0.7072)


def test_refinement_from_the_wall_table_recovers_the_pose(intel):
    wm = WallMap(intel, 0.65, 0.3, lookup=True)
    truth = rigid_matrix(np.radians(1.0), 3.0, -2.0)
    walls_b = (wm.walls - truth[:2, 2]) @ np.linalg.inv(truth[:2, :2]).T  # A = truth(B)
    np.testing.assert_allclose(refine(wm, walls_b, np.eye(3)), truth, atol=0.02)
    start = rigid_matrix(np.radians(1.4), 4.5, -2.0)
    np.testing.assert_allclose(refine_point_to_line(wm, walls_b, start), truth, atol=0.02)


def test_subsampled_full_resolution_stages_estimate_all_walls(intel):
    wm = WallMap(intel, 0.65, 0.3)
    n = len(wm.walls)
    for m in (np.eye(3), rigid_matrix(0.0, 12.0, -9.0)):
        full = map_agreement(wm, wm, m)
        # a cap above the wall count changes nothing
        assert map_agreement(wm, wm, m, max_points=n, scaled=True) == full
        quarter = map_agreement(wm, wm, m, max_points=n // 4, scaled=True)
        assert abs(quarter.agree - full.agree) <= 0.05 * full.agree + 4
        assert abs(quarter.ratio - full.ratio) < 0.05
    bent = wm.walls + np.where(wm.walls[:, :1] > np.median(wm.walls[:, 0]), 3.0, 0.0)
    whole = residual_distortion(wm.tree, bent, np.eye(3), block=80.0)
    assert residual_distortion(wm.tree, bent, np.eye(3), block=80.0, max_points=n) == whole
    part = residual_distortion(wm.tree, bent, np.eye(3), block=80.0, max_points=n // 4)
    assert whole > 2.0 and abs(part - whole) < 0.5


def test_coarsen_keeps_walls_and_averages_the_rest(intel):
    part = intel[:155, :203]  # sides that k does not divide: the last blocks are padded
    for k in (3, 4):
        c = coarsen(part, k)
        h, w = part.shape
        assert c.shape == (-(-h // k), -(-w // k))
        padded = np.full((c.shape[0] * k, c.shape[1] * k), 0.5, np.float32)
        padded[:h, :w] = part
        want = np.empty_like(c)
        for r, col in np.ndindex(c.shape):
            block = padded[r * k : (r + 1) * k, col * k : (col + 1) * k]
            want[r, col] = block.max() if block.max() > 0.65 else block.mean()
        np.testing.assert_allclose(c, want, atol=1e-6)
        assert (want > 0.65).sum() > 100
