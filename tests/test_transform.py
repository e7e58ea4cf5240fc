"""warp / resample / union_canvas: the pixel-frame convention x = col, y = row, B -> A."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from pgvd.grid import Grid, heading, pixel_to_world, relative_matrix, rigid_matrix
from pgvd.integrate import se2, se2_pose
from pgvd.io import read_map
from pgvd.transform import resample, scale_matrix, union_canvas, warp


def test_warp_moves_a_cell_to_matrix_times_its_xy() -> None:
    """A lone cell at B (x=7, y=3) lands at M (7, 3): x is the column, y the row."""
    b = np.zeros((20, 30), np.float32)
    b[3, 7] = 1.0
    for m in (
        rigid_matrix(0.0, 5.0, 2.0),
        rigid_matrix(np.pi / 2, 10.0, 25.0),
        rigid_matrix(np.pi, 40.0, 30.0),
    ):
        xa, ya, _ = np.rint(m @ [7.0, 3.0, 1.0]).astype(int)
        out = warp(b, m, (50, 60), order=0)
        assert out[ya, xa] == 1.0 and out.sum() == 1.0


def test_warp_bilinear_keeps_the_centroid_under_any_rotation() -> None:
    rng = np.random.default_rng(3)
    b = np.zeros((64, 64), np.float32)
    b[20:24, 40:43] = 1.0
    centroid_b = np.array([41.0, 21.5, 1.0])
    for _ in range(5):
        m = rigid_matrix(rng.uniform(-np.pi, np.pi), 0.0, 0.0)
        m[:2, 2] = rng.uniform(40, 80, 2) - m[:2, :2] @ centroid_b[:2]
        out = warp(b, m, (128, 128))
        ys, xs = np.mgrid[:128, :128]
        got = np.array([(xs * out).sum(), (ys * out).sum()]) / out.sum()
        np.testing.assert_allclose(got, (m @ centroid_b)[:2], atol=0.05)


def test_warp_real_split_pair_by_true_matrix_agrees(shared: Path) -> None:
    """intel_split_gt halves share a world frame: B warped by the true matrix matches A."""
    d = shared / "maps/intel_split_gt"
    a, b = read_map(d / "intel_partA.yaml"), read_map(d / "intel_partB.yaml")
    m = relative_matrix(a, b)
    pb = warp(b.probability(), m, a.shape, order=0, cval=0.5)
    pa = a.probability()
    both = (pa != 0.5) & (pb != 0.5)
    agree = ((pa > 0.5) == (pb > 0.5))[both].mean()
    assert both.sum() > 50_000 and agree > 0.97
    # a wrong matrix (shifted 3 cells) agrees clearly less
    shifted = rigid_matrix(0.0, 3.0, 0.0) @ m
    pb3 = warp(b.probability(), shifted, a.shape, order=0, cval=0.5)
    occ = (pa > 0.65) & (pb3 != 0.5)
    occ_true = (pa > 0.65) & (pb != 0.5)
    assert (pb[occ_true] > 0.65).mean() > (pb3[occ] > 0.65).mean() + 0.3


def test_warp_rejects_bad_matrix() -> None:
    with pytest.raises(ValueError, match="3x3"):
        warp(np.zeros((3, 3)), np.eye(2), (3, 3))


def test_resample_keeps_the_metric_frame_and_walls(shared: Path) -> None:
    g = read_map(shared / "maps/intel/intel.yaml")
    g = Grid(g.logodds, g.resolution, (1.5, -2.0, 0.0))
    coarse = resample(g, 0.1)
    assert coarse.shape == (424, 444) and coarse.origin == g.origin
    # the resampling matrix is the true fine -> coarse pixel relation of the two grids
    np.testing.assert_allclose(
        relative_matrix(coarse, g), scale_matrix(0.05, 0.1, g.shape[0], 424), atol=1e-9
    )
    corner = pixel_to_world(g, [[-0.5, g.shape[0] - 0.5]])
    np.testing.assert_allclose(pixel_to_world(coarse, [[-0.5, 423.5]]), corner, atol=1e-9)
    # every fine wall cell is still a wall in the coarse map (thin walls survive)
    occ = np.argwhere(g.probability() > 0.65)[:, ::-1].astype(float)
    xy = (scale_matrix(0.05, 0.1, g.shape[0], 424) @ np.c_[occ, np.ones(len(occ))].T)[:2]
    cells = np.rint(xy).astype(int)
    assert (coarse.probability()[cells[1], cells[0]] > 0.6).mean() > 0.97
    fine = resample(coarse, 0.05)
    assert fine.shape == g.shape


def test_union_canvas_holds_both_maps() -> None:
    m = rigid_matrix(0.4, -30.0, 50.0)
    shape, off = union_canvas((100, 80), (60, 90), m)
    corners_b = np.array([[0, 0, 1], [89, 0, 1], [0, 59, 1], [89, 59, 1]], float).T
    for pts in ((off @ m @ corners_b)[:2], (off @ [[0, 79], [0, 99], [1, 1]])[:2]):
        assert (pts >= -1e-9).all()
        assert (pts[0] <= shape[1] - 1 + 1e-9).all() and (pts[1] <= shape[0] - 1 + 1e-9).all()
    assert off[0, 2] == np.floor(-(m @ corners_b)[0].min()) or off[0, 2] >= 0
    assert off[:2, 2].tolist() == [float(int(v)) for v in off[:2, 2]]
    # identity: the canvas is A itself
    assert union_canvas((10, 20), (10, 20), np.eye(3))[0] == (10, 20)


angles = st.floats(-3.14159, 3.14159)
offsets = st.floats(-1e4, 1e4)


@given(psi=angles, tx=offsets, ty=offsets)
def test_heading_reads_back_the_psi_of_eq_2(psi, tx, ty) -> None:
    assert heading(rigid_matrix(psi, tx, ty)) == pytest.approx(psi, abs=1e-12)


@given(x=offsets, y=offsets, theta=angles)
def test_se2_pose_reads_back_a_metric_pose(x, y, theta) -> None:
    assert se2_pose(se2(x, y, theta)) == pytest.approx((x, y, theta), abs=1e-9)


def test_heading_turns_counter_clockwise_on_screen_with_rows_down() -> None:
    """A point right of the centre (x = 1, y = 0) goes up on screen (y < 0) for psi > 0."""
    m = rigid_matrix(np.pi / 2, 0.0, 0.0)
    np.testing.assert_allclose(m @ [1.0, 0.0, 1.0], [0.0, -1.0, 1.0], atol=1e-12)
    assert heading(m) == pytest.approx(np.pi / 2)
    # the same matrix read in a y-up frame turns the other way
    assert se2_pose(m)[2] == pytest.approx(-np.pi / 2)
