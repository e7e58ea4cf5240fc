"""pgvd.integrate: log-odds ray casting of real CARMEN scans."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage

from pgvd.carmen import LaserScan, read_carmen
from pgvd.grid import pixel_to_world, relative_matrix
from pgvd.integrate import (
    InverseSensorModel,
    MapFrame,
    frame_for,
    integrate,
    integrate_scan,
    perturb_odometry,
    se2,
    select_segment,
)
from pgvd.io import read_map


@pytest.fixture(scope="module")
def intel(shared):
    return read_carmen(shared / "logs" / "intel-corrected.log.gz")


def _scan(pose, ranges, fov=np.pi):
    r = np.asarray(ranges, np.float32)
    return LaserScan(0.0, r, np.asarray(pose, float), np.asarray(pose, float), fov)


def test_single_beam_lands_where_the_geometry_says():
    """A 3 m beam along +x from (1, 2, 0): hit cell at world (4, 2), carried by the frame."""
    scan = _scan([1.0, 2.0, 0.0], [3.0])
    transform = se2(5.0, -7.0, 0.7)
    frame = frame_for([scan], 0.05, transform)
    grid = integrate([scan], frame)
    model = InverseSensorModel()
    (hit,) = np.argwhere(grid.logodds == np.float32(model.l_occ))
    expected = (transform @ [4.0, 2.0, 1.0])[:2]
    np.testing.assert_allclose(pixel_to_world(grid, hit[::-1])[0], expected, atol=0.05)
    free = np.argwhere(grid.logodds < 0)
    assert len(free) >= 3.0 / 0.05 - 2  # every cell along the beam, each once
    assert np.all(grid.logodds[grid.logodds < 0] == np.float32(model.l_free))


def test_max_range_and_no_return_rays():
    model = InverseSensorModel(max_range=2.0, no_return=80.0)
    frame = MapFrame(0.1, (100, 100), se2(5.0, 5.0, 0.0))
    no_hit = integrate([_scan([0.0, 0.0, 0.0], [3.0])], frame, model)
    assert no_hit.logodds.max() == 0 and (no_hit.logodds < 0).sum() == pytest.approx(20, abs=1)
    nothing = integrate([_scan([0.0, 0.0, 0.0], [81.83])], frame, model)
    assert not nothing.logodds.any()


def test_clamps_and_hit_wins_over_free():
    model = InverseSensorModel(l_occ=1.0, l_free=-0.5, l_min=-1.2, l_max=2.5)
    scan = _scan([0.0, 0.0, 0.0], [1.0])
    frame = MapFrame(0.1, (40, 40), se2(2.0, 2.0, 0.0))
    grid = integrate([scan] * 10, frame, model)
    assert grid.logodds.max() == pytest.approx(2.5) and grid.logodds.min() == pytest.approx(-1.2)
    assert (grid.logodds > 0).sum() == 1


def test_incremental_equals_batch_and_bbox_covers_changes(intel):
    scans = select_segment(intel, slice(100, 160))
    frame = frame_for(scans, 0.05, se2(3.0, -4.0, 2.1))
    canvas = frame.empty()
    for scan in scans:
        before = canvas.copy()
        rows, cols = integrate_scan(canvas, scan, frame)
        changed = canvas != before
        inside = np.zeros_like(changed)
        inside[rows, cols] = True
        assert changed.any() and not (changed & ~inside).any()
    np.testing.assert_array_equal(canvas, integrate(scans, frame).logodds)


def test_frame_holds_every_ray(intel):
    scans = select_segment(intel, (0.2, 0.3))
    model = InverseSensorModel()
    ident = integrate(scans, frame_for(scans, 0.05, model=model), model)
    turned = integrate(scans, frame_for(scans, 0.05, se2(40.0, 9.0, 2.5), model=model), model)
    # Nothing is clipped by the canvas, so the same evidence exists in any frame (up to
    # how rays fall on a rotated lattice): unknown borders on every side.
    for g in (ident, turned):
        lo = g.logodds
        assert not (lo[0].any() or lo[-1].any() or lo[:, 0].any() or lo[:, -1].any())
    assert (turned.logodds > 0).sum() == pytest.approx((ident.logodds > 0).sum(), rel=0.1)


def test_agrees_with_the_split_gt_render(shared, intel):
    """Our render of intel 0.00-0.55 (the yaml comment of intel_partA) matches that map."""
    gt = read_map(shared / "maps" / "intel_split_gt" / "intel_partA.yaml")
    scans = select_segment(intel, (0.0, 0.55))
    assert len(scans) == 500  # "scans 0.00-0.55 of 500 used"
    ours = integrate(scans, frame_for(scans, gt.resolution))
    occ_ours, occ_gt = ours.logodds > 0, gt.logodds > 0
    # Both grids live in the log's world frame: relative_matrix is the exact overlay.
    m = relative_matrix(ours, gt)
    rows, cols = np.nonzero(occ_gt)
    pts = m @ np.vstack([cols, rows, np.ones_like(cols)])
    x, y = np.rint(pts[:2]).astype(int)
    assert np.allclose(m[:2, :2], np.eye(2))
    inside = (x >= 0) & (x < ours.shape[1]) & (y >= 0) & (y < ours.shape[0])
    assert inside.mean() > 0.99
    dist = ndimage.distance_transform_edt(~occ_ours)[y[inside], x[inside]]
    assert np.mean(dist <= 1.5) > 0.97, np.mean(dist <= 1.5)
    # ...and the overlay is sharp: three cells off, far fewer walls coincide.
    shifted = ndimage.distance_transform_edt(~occ_ours)[y[inside], np.clip(x[inside] + 3, 0, None)]
    assert np.mean(shifted <= 1.5) < 0.75


def test_select_segment_conventions(intel):
    assert len(select_segment(intel, (0.45, 1.0))) == 501  # intel_partB's yaml comment
    assert select_segment(intel, slice(5, 8)) == intel[5:8]
    with pytest.raises(ValueError, match="fractions"):
        select_segment(intel, (0.6, 0.5))


def test_odometry_noise_is_seeded_drift(intel):
    scans = intel[:200]
    a = perturb_odometry(scans, (0.05, 0.05), seed=1)
    b = perturb_odometry(scans, (0.05, 0.05), seed=1)
    c = perturb_odometry(scans, (0.05, 0.05), seed=2)
    zero = perturb_odometry(scans, (0.0, 0.0), seed=1)
    pa, pc = (np.array([s.pose for s in x]) for x in (a, c))
    truth = np.array([s.pose for s in scans])
    np.testing.assert_array_equal(pa, np.array([s.pose for s in b]))
    assert not np.allclose(pa, pc)
    np.testing.assert_allclose(np.array([s.pose for s in zero])[:, :2], truth[:, :2], atol=1e-9)
    np.testing.assert_array_equal(pa[0], truth[0])
    drift = np.hypot(*(pa[:, :2] - truth[:, :2]).T)
    assert drift[-1] > drift[10] > 0


@pytest.mark.parametrize(
    "kwargs",
    [dict(l_occ=-1.0), dict(l_free=0.1), dict(l_min=0.5), dict(max_range=0.0)],
)
def test_model_validation(kwargs):
    with pytest.raises(ValueError):
        InverseSensorModel(**kwargs)


def test_frame_validation():
    with pytest.raises(ValueError, match="SE\\(2\\)"):
        MapFrame(0.05, (10, 10), np.diag([2.0, 1.0, 1.0]))
    frame = MapFrame(0.05, (10, 10))
    with pytest.raises(ValueError, match="C-contiguous"):
        integrate_scan(np.zeros((10, 11), np.float32), _scan([0, 0, 0], [1.0]), frame)
