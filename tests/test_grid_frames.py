"""Map frames: where a pixel matrix puts one map's ROS map frame in another's."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from pgvd.grid import (
    Grid,
    map_frame_covariance,
    map_frame_pose,
    pixel_to_world,
    relative_matrix,
    rigid_matrix,
)

coords = st.floats(-50.0, 50.0, allow_nan=False)
yaws = st.floats(-np.pi, np.pi, allow_nan=False)
poses = st.tuples(coords, coords, yaws)
sizes = st.integers(2, 40)


def _se2(x: float, y: float, yaw: float) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s, x], [s, c, y], [0.0, 0.0, 1.0]])


def _grid(h: int, w: int, origin: tuple[float, float, float], res: float = 0.05) -> Grid:
    return Grid(np.zeros((h, w), np.float32), res, origin)


@given(poses, poses, poses, sizes, sizes, st.sampled_from([0.05, 0.1, 0.025]))
def test_the_pose_carries_b_where_the_matrix_carries_its_cells(
    oa: tuple, ob: tuple, pixel: tuple, h: int, w: int, res_b: float
) -> None:
    """Checked through pgvd.pixel_to_world, the other conversion: B's cells placed in A's
    metric frame by the pixel matrix (rigid, times the scale between the cells) are B's
    metric coordinates moved by the pose."""
    a, b = _grid(h, w, oa), _grid(w, h, ob, res=res_b)
    scale = res_b / a.resolution
    matrix = rigid_matrix(pixel[2], pixel[0], pixel[1]) @ np.diag([scale, scale, 1.0])
    cells = np.array([[0.0, 0.0], [w - 1.0, 0.0], [0.0, h - 1.0], [3.0, 7.0]])
    in_a = pixel_to_world(a, (matrix @ np.column_stack([cells, np.ones(4)]).T)[:2].T)
    x, y, yaw = map_frame_pose(a, b, matrix)
    moved = pixel_to_world(b, cells) @ _se2(0.0, 0.0, yaw)[:2, :2].T + (x, y)
    assert np.allclose(moved, in_a, atol=1e-6)


def test_a_matrix_with_a_scale_has_no_map_frame_covariance() -> None:
    a, b = _grid(30, 20, (0.0, 0.0, 0.0)), _grid(15, 10, (0.0, 0.0, 0.0), res=0.1)
    with pytest.raises(ValueError, match="rigid"):
        map_frame_covariance(a, b, relative_matrix(a, b), np.eye(3))


@given(poses, poses, poses, sizes, sizes)
def test_a_map_frame_moved_in_the_world_is_found_where_it_was_put(
    oa: tuple, ob: tuple, frame: tuple, h: int, w: int
) -> None:
    """B's pixels stay where they were in the world, but its YAML origin is written in
    another frame F (placed in the world at ``frame``): F is B's map frame now, and the
    pixel matrix between the contents puts it at ``frame`` in A's (world) frame."""
    a, b = _grid(h, w, oa), _grid(w, h, ob)
    moved = np.linalg.inv(_se2(*frame)) @ _se2(*ob)
    b_in_f = _grid(w, h, (moved[0, 2], moved[1, 2], np.arctan2(moved[1, 0], moved[0, 0])))
    x, y, yaw = map_frame_pose(a, b_in_f, relative_matrix(a, b))
    assert np.allclose([x, y], frame[:2], atol=1e-7)
    assert abs(np.angle(np.exp(1j * (yaw - frame[2])))) < 1e-9


def test_the_map_frame_covariance_is_the_spread_of_the_poses_it_stands_for() -> None:
    """Pixel poses drawn from a merge covariance, each carried to the map frames: their
    spread is the propagated covariance (20000 draws: a few per cent of sampling error)."""
    a = _grid(300, 200, (4.0, -7.0, 0.6))
    b = _grid(250, 350, (-12.0, 3.0, -1.9), res=0.05)
    psi, tx, ty = 0.8, 120.0, -40.0
    cov = np.array([[4.0, 1.5, 0.004], [1.5, 2.0, -0.002], [0.004, -0.002, 1e-4]])
    rng = np.random.default_rng(7)
    draws = rng.multivariate_normal([tx, ty, psi], cov, size=20000)
    poses = np.array([map_frame_pose(a, b, rigid_matrix(p, x, y)) for x, y, p in draws])
    poses[:, 2] = np.unwrap(poses[:, 2])
    want = map_frame_covariance(a, b, rigid_matrix(psi, tx, ty), cov)
    sd = np.sqrt(np.diag(want))
    assert np.allclose(np.sqrt(np.diag(np.cov(poses.T))), sd, rtol=0.03)
    got_corr = np.corrcoef(poses.T)
    assert np.allclose(got_corr, want / np.outer(sd, sd), atol=0.03)
