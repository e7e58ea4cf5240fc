"""pgvd.lidar and pgvd.trajectory: a simulated LMS200 driven through a real map image."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage
from scipy.spatial import cKDTree

from pgvd.grid import Grid
from pgvd.io import read_map
from pgvd.lidar import LMS200, RayCaster, Scanner, close_diagonals, scan_at
from pgvd.trajectory import CLEARANCE, tour


@pytest.fixture(scope="module")
def caster(shared):
    grid = read_map(shared / "maps" / "intel" / "intel.yaml")
    return RayCaster(Grid(grid.logodds, grid.resolution))


@pytest.fixture(scope="module")
def poses(caster):
    return tour(caster, np.random.default_rng(0))[::10]


def _endpoints(caster: RayCaster, scans, max_range: float) -> np.ndarray:
    pts = []
    for s in scans:
        hit = s.ranges < max_range
        ang = s.beam_angles()[hit]
        r = s.ranges[hit].astype(np.float64)
        pts.append(s.pose[:2] + np.column_stack([r * np.cos(ang), r * np.sin(ang)]))
    return caster.world_to_pixel(np.concatenate(pts))


def test_route_stays_in_free_space_away_from_walls(caster, poses):
    px = np.rint(caster.world_to_pixel(poses[:, :2])).astype(int)
    clear_m = ndimage.distance_transform_edt(~(caster.wall | caster.unknown)) * caster.resolution
    # Smoothing may cut a corner by a few centimetres, never into a wall.
    assert clear_m[px[:, 1], px[:, 0]].min() > 0.6 * CLEARANCE
    travel = np.hypot(*np.diff(poses[:, :2], axis=0).T).sum()
    assert travel > 50.0  # the robot explores the building, it does not sit still


def test_hits_land_on_walls(caster, poses):
    exact = Scanner(range_sigma=0.0)
    scans = scan_at(caster, poses, np.random.default_rng(1), exact)
    ranges = np.concatenate([s.ranges for s in scans])
    assert ranges.shape == (len(poses) * 181,)
    hits = ranges < exact.max_range
    assert hits.mean() > 0.8  # an indoor map: most beams hit something
    assert np.all(ranges[~hits] == exact.no_return)
    px = _endpoints(caster, scans, exact.max_range)
    rows, cols = np.nonzero(caster.wall)
    d, _ = cKDTree(np.column_stack([cols, rows])).query(px)
    # A hit is on the edge of a wall cell: at most half a diagonal from its centre.
    assert np.mean(d <= np.sqrt(0.5) + 0.01) > 0.99


def test_range_noise_has_the_scanner_sigma(caster, poses):
    exact = scan_at(caster, poses, np.random.default_rng(1), Scanner(range_sigma=0.0))
    noisy = scan_at(caster, poses, np.random.default_rng(1), LMS200)
    r0 = np.concatenate([s.ranges for s in exact]).astype(np.float64)
    r1 = np.concatenate([s.ranges for s in noisy]).astype(np.float64)
    hit = r0 < LMS200.max_range
    err = r1[hit] - r0[hit]
    assert abs(err.mean()) < 0.002
    assert err.std() == pytest.approx(LMS200.range_sigma, rel=0.05)


def test_max_range_gives_no_return(caster, poses):
    short = Scanner(max_range=2.0, range_sigma=0.0)
    scans = scan_at(caster, poses, np.random.default_rng(1), short)
    ranges = np.concatenate([s.ranges for s in scans])
    assert np.all(ranges[ranges >= 2.0] == np.float32(short.no_return))
    assert (ranges < 2.0).any()


def test_a_diagonal_wall_stops_every_beam():
    wall = np.eye(40, dtype=bool)  # one-cell diagonal staircase: corners touch only
    closed = close_diagonals(wall)
    assert closed.sum() == 2 * 40 - 1
    p = np.where(wall, 0.95, 0.05).astype(np.float32)
    caster = RayCaster(Grid.from_probability(p, 1.0))
    # From below the diagonal (rows grow downwards), beams in every upward direction.
    origin = caster.pixel_to_world(np.array([[10.0, 30.0]]))
    angles = np.linspace(0.05, np.pi / 2 - 0.05, 500)
    ranges = caster.cast(np.repeat(origin, 500, axis=0), angles, 100.0)
    assert np.isfinite(ranges).all()
    # ...and every hit is on the diagonal, not beyond it.
    ends = caster.world_to_pixel(
        origin + ranges[:, None] * np.column_stack([np.cos(angles), np.sin(angles)])
    )
    assert np.all(np.abs(ends[:, 0] - ends[:, 1]) < 1.5)
