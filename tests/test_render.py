"""Pictures: classes get their colours, and merge_figure puts A, B and the edges in place."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from pgvd.grid import Grid, rigid_matrix
from pgvd.io import read_map
from pgvd.render import (
    A_WALL,
    B_WALL,
    BOTH_WALL,
    EDGE,
    SEPARATOR,
    grid_image,
    merge_figure,
    overlay,
    pgvd_image,
)


def test_grid_image_colours() -> None:
    img = grid_image(np.array([[0.0, 0.5, 1.0, np.nan]]))
    assert img.dtype == np.uint8 and img.shape == (1, 4, 3)
    assert img[0, :, 0].tolist() == [255, 128, 0, 128]


def test_overlay_colours_each_class() -> None:
    a = np.array([[0.9, 0.9, 0.1, 0.5, 0.5]])
    b = np.array([[0.9, 0.5, 0.5, 0.9, 0.5]])
    img = overlay(a, b)
    assert [tuple(c) for c in img[0]] == [BOTH_WALL, A_WALL, (255, 255, 255), B_WALL, (200,) * 3]
    with pytest.raises(ValueError, match="equal shapes"):
        overlay(a, b[:, :3])


def test_pgvd_image_ramps_and_highlights_edges() -> None:
    prob = np.full((5, 5), 0.1)
    sp = np.zeros((5, 5))
    sp[1, :] = [0.0, 0.3, 0.6, 1.0, 0.04]
    edges = np.zeros((5, 5), bool)
    edges[4, 4] = True
    img = pgvd_image(prob, sp, edges)
    assert tuple(img[1, 3]) == (90, 10, 110)  # top of the ramp
    assert img[1, 1, 1] > img[1, 2, 1]  # green falls as the probability rises
    assert tuple(img[1, 0]) == tuple(img[1, 4]) == tuple(img[0, 0])  # faded map below 0.05
    assert tuple(img[4, 4]) == EDGE and tuple(img[3, 4]) == EDGE  # dilated by one cell
    assert tuple(img[0, 0]) != EDGE


@dataclass
class _FakeDiagnostics:
    pgvd_a: np.ndarray
    pgvd_b: np.ndarray
    edges_a: np.ndarray
    edges_b: np.ndarray


@dataclass
class _FakeResult:
    accepted: bool
    matrix: np.ndarray
    rotation_deg: float
    translation_px: tuple[float, float]
    score: float
    reason: str
    diagnostics: _FakeDiagnostics | None


def _count(img: np.ndarray, colour: tuple[int, int, int]) -> int:
    return int((img == colour).all(axis=2).sum())


def test_merge_figure_places_both_maps_and_edges(shared: Path) -> None:
    g = read_map(shared / "maps/intel/intel.yaml")
    a = Grid(g.logodds[100:400, 100:450], g.resolution)
    b = Grid(g.logodds[150:420, 160:500], g.resolution)  # B pixel (x, y) = A pixel (x+60, y+50)
    m = rigid_matrix(0.0, 60.0, 50.0)
    edges_a = np.zeros(a.shape, bool)
    edges_a[120, 80:200] = True
    edges_b = np.zeros(b.shape, bool)
    edges_b[70, 20:140] = True  # the same cells as edges_a, seen from B
    diag = _FakeDiagnostics(np.zeros(a.shape), np.zeros(b.shape), edges_a, edges_b)
    res = _FakeResult(True, m, 0.0, (60.0, 50.0), 0.99, "accepted", diag)
    fig = merge_figure(a, b, res, crop=False)
    canvas_h, canvas_w = 320, 400  # union of A (300 x 350) and B at (+60, +50) (270 x 340)
    assert fig.shape == (16 + canvas_h, 3 * canvas_w + 2, 3)
    body = fig[16:]
    assert (body[:, canvas_w] == SEPARATOR).all() and (body[:, 2 * canvas_w + 1] == SEPARATOR).all()
    over = body[:, :canvas_w]
    pa = a.probability()
    walls_a = pa > 0.65
    # B is the same building: where both see walls the overlay is dark, and A's walls
    # outside B's part stay blue
    shared_part = np.zeros_like(walls_a)
    shared_part[50:, 60:] = True
    dark = (over[:300, :350] == BOTH_WALL).all(axis=2)
    assert dark[walls_a & shared_part].mean() > 0.99
    blue = (over[:300, :350] == A_WALL).all(axis=2)
    assert blue[walls_a & ~shared_part].mean() > 0.99
    # the matched edges of A and of the warped B land on the same cells
    green_a = (body[:, canvas_w + 1 : 2 * canvas_w + 1] == EDGE).all(axis=2)
    green_b = (body[:, 2 * canvas_w + 2 :] == EDGE).all(axis=2)
    assert green_a[120, 80:200].all() and green_b[120, 80:200].all()
    np.testing.assert_array_equal(green_a, green_b)
    # cropped to the walls: no larger, and (nearly) every wall still drawn
    cropped = merge_figure(a, b, res)
    assert cropped.shape[0] <= fig.shape[0] and cropped.shape[1] <= fig.shape[1]
    assert _count(cropped, A_WALL) + _count(cropped, BOTH_WALL) >= 0.99 * (
        _count(fig, A_WALL) + _count(fig, BOTH_WALL)
    )


def test_merge_figure_of_a_rejection_without_transform(shared: Path) -> None:
    g = read_map(shared / "maps/intel/intel.yaml")
    a = Grid(g.logodds[:200, :300], g.resolution)
    b = Grid(g.logodds[300:500, 300:500], g.resolution)
    for m in (np.full((3, 3), np.nan), np.eye(3)):
        res = _FakeResult(False, m, 0.0, (0.0, 0.0), 0.0, "no edge pair passes", None)
        fig = merge_figure(a, b, res)
        assert fig.shape == (16 + 200, 300 + 1 + 200, 3)
    np.testing.assert_array_equal(fig[16:, :300], grid_image(a.probability()))
    caption = fig[:16]
    assert (caption < 128).any() and (caption == 255).mean() > 0.5  # black text on white
