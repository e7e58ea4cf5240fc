"""Ground truth for fleets that replay runs: true transforms, link and placement errors, overlaps.

A ``carmen:`` or ``sim:`` source reports ``world_to_pixel``, the 3x3 map from the log's world metres
to its map's pixels.  The true B-pixel -> A-pixel matrix is then
``W_a @ inv(W_b)``, the same convention as a link's matrix and ``pgvd merge --json``.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from pgvd.grid import Grid, heading


def true_matrix(world_to_pixel_a: np.ndarray, world_to_pixel_b: np.ndarray) -> np.ndarray:
    """The true matrix from B's pixels to A's pixels."""
    return np.asarray(world_to_pixel_a, float) @ np.linalg.inv(np.asarray(world_to_pixel_b, float))


def link_error(
    matrix: np.ndarray, truth: np.ndarray, shape_b: tuple[int, int]
) -> tuple[float, float]:
    """``(rotation error deg, translation error cells)`` of an estimated B->A matrix.

    The translation error is the largest displacement between estimate and truth over the
    four corners of B's canvas, so a small rotation error far from the centre counts too.
    """
    m, t = np.asarray(matrix, float), np.asarray(truth, float)
    rot = np.degrees(heading(m) - heading(t))
    rot = (rot + 180.0) % 360.0 - 180.0
    h, w = shape_b
    corners = np.array([[0, 0, 1], [w - 1, 0, 1], [0, h - 1, 1], [w - 1, h - 1, 1]], float).T
    cells = np.linalg.norm((m @ corners - t @ corners)[:2], axis=0).max()
    return float(abs(rot)), float(cells)


def true_overlap(a: Grid, b: Grid, truth: np.ndarray) -> float:
    """Fraction of the smaller map's known cells that the other map also knows, under ``truth``."""
    known_a = a.logodds != 0
    known_b = b.logodds != 0
    ys, xs = np.nonzero(known_b)
    if not len(xs) or not known_a.any():
        return 0.0
    pts = np.asarray(truth, float) @ np.vstack([xs, ys, np.ones_like(xs)])
    ca, ra = np.rint(pts[0]).astype(int), np.rint(pts[1]).astype(int)
    inside = (ra >= 0) & (ra < a.shape[0]) & (ca >= 0) & (ca < a.shape[1])
    shared = np.count_nonzero(known_a[ra[inside], ca[inside]])
    return float(shared / min(known_a.sum(), known_b.sum()))


def placement_errors(
    anchor: str,
    transforms: Mapping[str, np.ndarray],
    world_to_pixel: Mapping[str, np.ndarray],
    shapes: Mapping[str, tuple[int, int]],
) -> dict[str, tuple[float, float]]:
    """How far a global map placed each of its robots from the truth, as :func:`link_error`.

    Parameters
    ----------
    anchor : the robot whose pixels the global map's placements map to.
    transforms : per member, its pixels -> the anchor's pixels (a component's placements).
    world_to_pixel : per robot, the log world -> its map's pixels (the truth).
    shapes : per robot, its map's shape (the corners the translation error is taken at).

    Returns
    -------
    dict
        ``{robot: (rotation error deg, translation error cells)}`` for every member whose
        truth and shape are known; the anchor's error is 0 by construction.
    """
    if anchor not in world_to_pixel:
        return {}
    return {
        r: link_error(m, true_matrix(world_to_pixel[anchor], world_to_pixel[r]), shapes[r])
        for r, m in transforms.items()
        if r in world_to_pixel and r in shapes
    }
