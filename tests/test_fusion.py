"""Fusion (33)-(37): the entropy filter, fuse_maps and the layers on the real intel split pair."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy import ndimage

from pgvd.fusion import entropy, fuse, fuse_layers, fuse_many, fuse_maps, warp_layer
from pgvd.grid import Grid, logodds_to_probability, relative_matrix, rigid_matrix
from pgvd.io import read_map
from pgvd.transform import warp


def test_entropy_eq35() -> None:
    p = np.array([0.0, 0.5, 1.0, 0.1, 0.9])
    h = entropy(p)
    assert h[0] == 0.0 and h[2] == 0.0 and h[1] == pytest.approx(np.log(2))
    assert h[3] == pytest.approx(-(0.1 * np.log(0.1) + 0.9 * np.log(0.9))) and h[3] == h[4]


def test_fuse_equals_the_literal_entropy_filter() -> None:
    rng = np.random.default_rng(0)
    base = rng.normal(0, 3, 10_000).astype(np.float32)
    other = rng.normal(0, 3, 10_000).astype(np.float32)
    fused = base + other  # (33)
    info = entropy(logodds_to_probability(base)) - entropy(logodds_to_probability(fused))  # (36)
    literal = np.where(info >= 0, fused, base)  # (37)
    got = fuse(base, other)
    clear = np.abs(info) > 1e-6  # away from float ties of (35)
    np.testing.assert_array_equal(got[clear], literal[clear])
    assert (got != base).any() and (got == base).any()


def test_an_update_that_raises_entropy_is_refused() -> None:
    base = np.array([2.2, 3.0, -2.2, 0.0, -1.0], np.float32)
    other = np.array([-2.2, -1.0, 1.0, -2.2, 3.0], np.float32)
    out = fuse(base, other)
    # contradicting evidence would move the cell toward p = 0.5: refused, base kept
    np.testing.assert_array_equal(out[:3], base[:3])
    assert (
        entropy(logodds_to_probability(base[:3] + other[:3]))
        > entropy(logodds_to_probability(base[:3]))
    ).all()
    # into an unknown cell, or strong enough to flip a weak one: accepted
    assert out[3] == pytest.approx(-2.2) and out[4] == pytest.approx(2.0)


def test_agreeing_evidence_sharpens_and_unknown_changes_nothing() -> None:
    base = np.array([2.2, -2.2, 0.4], np.float32)
    out = fuse(base, base)
    np.testing.assert_allclose(out, 2 * base)
    assert (entropy(logodds_to_probability(out)) < entropy(logodds_to_probability(base))).all()
    np.testing.assert_array_equal(fuse(base, np.zeros(3, np.float32)), base)
    with pytest.raises(ValueError, match="same shape"):
        fuse(base, np.zeros(4))


def test_fuse_many_folds_in_the_given_order() -> None:
    rng = np.random.default_rng(1)
    maps = [rng.normal(0, 2, (20, 20)).astype(np.float32) for _ in range(4)]
    np.testing.assert_array_equal(
        fuse_many(maps[0], maps[1:]), fuse(fuse(fuse(maps[0], maps[1]), maps[2]), maps[3])
    )
    # the entropy filter is not commutative: the order is part of the result
    assert not np.array_equal(fuse_many(maps[0], maps[1:]), fuse_many(maps[0], maps[1:][::-1]))


def test_fuse_maps_on_the_intel_split_pair(shared: Path) -> None:
    d = shared / "maps/intel_split_gt"
    a, b = read_map(d / "intel_partA.yaml"), read_map(d / "intel_partB.yaml")
    m = relative_matrix(a, b)
    cov = np.diag([0.25, 0.25, 1e-6])
    fused = fuse_maps(a, b, m, cov)
    # A's world frame is kept: A sits in the fused map at a whole-cell offset
    to_a = relative_matrix(fused, a)
    np.testing.assert_allclose(to_a[:2, :2], np.eye(2), atol=1e-9)
    np.testing.assert_allclose(to_a[:2, 2], np.rint(to_a[:2, 2]), atol=1e-6)
    dx, dy = np.rint(to_a[:2, 2]).astype(int)
    pf = fused.probability()
    pa, pb = a.probability(), b.probability()
    in_a = pf[dy : dy + a.shape[0], dx : dx + a.shape[1]]
    # where B says nothing, A is unchanged; agreeing walls got sharper
    b_in_a = warp(pb, m, a.shape, order=0, cval=0.5)
    far = ndimage.distance_transform_edt(b_in_a == 0.5) > 8  # beyond the blur's reach
    np.testing.assert_allclose(in_a[far], pa[far], atol=1e-6)
    both_walls = (pa > 0.65) & (b_in_a > 0.65)
    assert both_walls.sum() > 1000 and (in_a[both_walls] > pa[both_walls]).mean() > 0.5
    # B's part that A never saw is now in the map, walls in place
    b_in_f = warp(pb, relative_matrix(fused, b), fused.shape, order=0, cval=0.5)
    a_in_f = warp(pa, to_a, fused.shape, order=0, cval=0.5)
    new_walls = (b_in_f > 0.65) & (a_in_f == 0.5)
    assert new_walls.sum() > 200 and (pf[new_walls] > 0.6).mean() > 0.9
    assert not ((b_in_f > 0.65) & (pf == 0.5)).any()
    # known cells: at least as many as either map alone
    assert (pf != 0.5).sum() >= max((pa != 0.5).sum(), (pb != 0.5).sum())


def test_fuse_maps_blurs_by_the_covariance(shared: Path) -> None:
    d = shared / "maps/intel_split_gt"
    a, b = read_map(d / "intel_partA.yaml"), read_map(d / "intel_partB.yaml")
    m = relative_matrix(a, b)
    sharp = fuse_maps(a, b, m, np.zeros((3, 3)))
    loose = fuse_maps(a, b, m, np.diag([4.0, 4.0, 0.02**2]))
    to_b = relative_matrix(sharp, b)
    pb = warp(b.probability(), to_b, sharp.shape, order=0, cval=0.5)
    pa = warp(a.probability(), relative_matrix(sharp, a), sharp.shape, order=0, cval=0.5)
    new_walls = (pb > 0.65) & (pa == 0.5)
    # uncertain B contributes weaker, wider walls where A is unknown
    assert sharp.logodds[new_walls].mean() > loose.logodds[new_walls].mean() + 0.5
    with pytest.raises(ValueError, match="finite"):
        fuse_maps(a, b, m, np.full((3, 3), np.nan))


def test_propagation_does_work_with_a_calibrated_covariance(shared: Path) -> None:
    from pgvd.merge import merge
    from pgvd.params import MergeParams

    # two gmapping runs of one building: independently built maps, a real merge
    d = shared / "maps/fr079_albertB"
    a, b = read_map(d / "map312.yaml"), read_map(d / "map371.yaml")
    r = merge(a, b, MergeParams(diagnostics=False))
    assert r.accepted, r.reason
    plain = fuse_maps(a, b, r.matrix, r.covariance, propagation=False)
    # the ablation switch is a plain warp: the same as an exact transform
    zero = fuse_maps(a, b, r.matrix, np.zeros((3, 3)))
    np.testing.assert_array_equal(plain.logodds, zero.logodds)
    # with the calibrated covariance the blurs of (8) are no longer below their skip
    # threshold (with the Laplace covariance they changed no cell by more than 1.5e-8)
    blurred = fuse_maps(a, b, r.matrix, r.covariance)
    assert blurred.shape == plain.shape
    change = np.abs(blurred.probability() - plain.probability())
    assert change.max() > 0.1 and (change > 0.05).sum() > 100


def test_fuse_maps_names_a_bad_matrix() -> None:
    a = Grid.from_probability(np.full((8, 8), 0.5), 0.05)
    with pytest.raises(ValueError, match=r"matrix must be a finite 3x3 array, got shape \(2, 2\)"):
        fuse_maps(a, a, np.eye(2), np.zeros((3, 3)))
    nan = np.eye(3)
    nan[0, 2] = np.nan
    with pytest.raises(ValueError, match="matrix must be a finite 3x3 array, got NaN"):
        fuse_maps(a, a, nan, np.zeros((3, 3)))


def test_layers_without_a_blur_fuse_as_fuse_maps(shared: Path) -> None:
    """Shifted by whole cells and exact, B's layer is B itself: the two fusions agree bit
    for bit, and the layer holds only the cells B knows."""
    d = shared / "maps/intel_split_gt"
    a, b = read_map(d / "intel_partA.yaml"), read_map(d / "intel_partB.yaml")
    m = rigid_matrix(0.0, 37.0, -52.0)
    layer = warp_layer(b, m, np.zeros((3, 3)))
    fused = fuse_layers(a, [layer])
    pair = fuse_maps(a, b, m, np.zeros((3, 3)))
    assert fused.origin == pair.origin
    np.testing.assert_array_equal(fused.logodds, pair.logodds)
    known = np.argwhere(b.logodds != 0)
    assert layer.corner == (37 + known[:, 1].min(), -52 + known[:, 0].min())
    assert layer.bounds == (37, -52, 37 + b.shape[1] - 1, -52 + b.shape[0] - 1)


def test_a_map_that_knows_nothing_leaves_the_base_as_it_was(shared: Path) -> None:
    a = read_map(shared / "maps/intel_split_gt/intel_partA.yaml")
    blank = Grid(np.zeros((40, 60), np.float32), a.resolution)
    layer = warp_layer(blank, rigid_matrix(0.3, -20.0, 10.0), np.diag([1.0, 1.0, 1e-4]))
    assert layer.logodds.size == 0
    fused = fuse_layers(a, [layer])
    assert fused.shape[0] > a.shape[0] and fused.shape[1] > a.shape[1]  # the canvas holds it
    assert np.count_nonzero(fused.logodds) == np.count_nonzero(a.logodds)
    assert fuse_layers(a, []) is a


def test_fuse_layers_names_a_resolution_that_differs() -> None:
    a = Grid(np.zeros((8, 8), np.float32), 0.05)
    layer = warp_layer(Grid(np.ones((8, 8), np.float32), 0.1), np.eye(3), np.zeros((3, 3)))
    with pytest.raises(ValueError, match=r"resolutions differ \(0.05 vs 0.1\)"):
        fuse_layers(a, [layer])
