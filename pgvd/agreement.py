"""Whole-map agreement of two maps at one pose: the paper's future-work check (Sec. VI).

* :func:`map_agreement` overlays the whole maps: walls of one map that fall
  on walls of the other agree, walls that fall on clear free space disagree.
* :func:`local_agreement` counts the same after each few-metre square of the
  overlap is re-aligned by a few cells: a drifted map has no single rigid fit.
"""

from __future__ import annotations

import numpy as np

from pgvd.overlay import Agreement
from pgvd.sampling import subsample
from pgvd.walls import WallMap, transform_points


def map_agreement(
    a: WallMap,
    b: WallMap,
    matrix: np.ndarray,
    tolerance: float = 2.0,
    max_points: int = 0,
    scaled: bool = False,
) -> Agreement:
    """Overlay B on A with the B->A pixel ``matrix`` and count agreement both ways.

    This is the check the paper leaves to future work (Sec. VI): a transform
    counts only if the whole maps agree once overlaid.

    Parameters
    ----------
    a, b : WallMap
        Wall cells and free space of the two maps.
    matrix : numpy.ndarray
        3x3, B pixel -> A pixel.
    tolerance : float, optional
        A wall within this many cells of a wall of the other map agrees.
    max_points : int, optional
        When > 0, an even subsample of each map's walls of about this size
        is evaluated (a quick estimate).
    scaled : bool, optional
        Count each subsampled wall cell for the cells between it and the next,
        so that the counts estimate those of all walls.

    Returns
    -------
    Agreement
        Agreeing walls and walls on clear free space, summed over both directions.
    """
    wb, wa = b.walls, a.walls
    if max_points > 0:
        wb, wa = subsample(wb, max_points), subsample(wa, max_points)
    ag1, dis1 = a.count(transform_points(matrix, wb), tolerance)
    ag2, dis2 = b.count(transform_points(np.linalg.inv(matrix), wa), tolerance)
    if not scaled:
        return Agreement(ag1 + ag2, dis1 + dis2)
    sb, sa = len(b.walls) / max(1, len(wb)), len(a.walls) / max(1, len(wa))
    return Agreement(round(ag1 * sb + ag2 * sa), round(dis1 * sb + dis2 * sa))


def _cells(points: np.ndarray, block: float) -> np.ndarray:
    """One int64 code per point for the ``block`` square it falls in."""
    keys = np.floor(points / block).astype(np.int64)
    return (keys[:, 0] << 32) + keys[:, 1]


def _block_shifts(
    a: WallMap,
    moved: np.ndarray,
    group: np.ndarray,
    pose: np.ndarray,
    max_shift: float,
    iterations: int = 2,
) -> np.ndarray:
    """The translation of each square that re-aligns its points ``moved`` on A's walls.

    Within each square (``group`` indexes the squares of the points) the
    translation ``d`` minimises the point-to-line misfit
    ``sum (n_i . (d - r_i))^2`` of the points within ``max_shift + 2`` of A's
    walls (``n_i`` A's wall normal at the nearest wall cell, ``r_i`` the
    offset to it), refitted once from the shifted points, as in
    :func:`residual_distortion`.  A ridge keeps a square whose walls all run
    one way from sliding along them; ``|d|`` is capped at ``max_shift``.
    ``pose`` gives the pose of each square (:func:`local_agreements` fits several
    at once): a pose none of whose points is near A's walls keeps its shifts from
    then on.

    Returns
    -------
    numpy.ndarray
        ``(n_squares, 2)``; 0 for a square with no point near A's walls.
    """
    n_groups = pose.size
    d = np.zeros((n_groups, 2))
    count = np.bincount(group, minlength=n_groups)
    ridge = 0.1 * np.maximum(count, 1)
    running = np.ones(int(pose.max()) + 1, bool)
    for it in range(iterations):
        pts = moved + d[group]
        # the first pass reaches as far as the shift may go; later ones only refine it
        reach = max_shift + 2.0 if it == 0 else 3.0
        dist, idx = a.nearest(pts, reach)
        ok = np.isfinite(dist) & running[pose[group]]
        running[:] = False
        running[pose[group[ok]]] = True
        if not ok.any():
            break
        g, n = group[ok], a.normals(idx[ok])
        r = np.sum(n * (a.walls[idx[ok]] - pts[ok]), axis=1)
        sxx, sxy, syy, bx, by = (
            np.bincount(g, v, minlength=n_groups)
            for v in (n[:, 0] ** 2, n[:, 0] * n[:, 1], n[:, 1] ** 2, n[:, 0] * r, n[:, 1] * r)
        )
        sxx, syy = sxx + ridge, syy + ridge
        det = sxx * syy - sxy**2
        step = np.column_stack([syy * bx - sxy * by, sxx * by - sxy * bx]) / det[:, None]
        live = running[pose]
        d[live] += step[live]
        norm = np.hypot(d[live, 0], d[live, 1])
        d[live] *= np.minimum(1.0, max_shift / np.maximum(norm, 1e-12))[:, None]
    return d


def local_agreement(
    a: WallMap,
    b: WallMap,
    matrix: np.ndarray,
    block: float,
    max_shift: float,
    tolerance: float = 2.0,
    max_points: int = 0,
) -> Agreement:
    """:func:`map_agreement` after a small re-alignment of every ``block`` square of the overlap.

    A drifted map has no single rigid fit: after the best rigid ``matrix``
    its walls still run a few cells beside A's away from the overlap's
    centre, and a plain count calls them walls on free space.  Here B's
    walls, moved into A, are cut into squares of A's frame and each square
    is shifted by its own translation (at most ``max_shift``, fitted
    point-to-line, :func:`_block_shifts`) before counting; A's walls in a
    square are moved back by the same shift before being mapped into B.  A
    wall on clear free space farther than ``max_shift`` from every wall still
    disagrees.

    Parameters
    ----------
    a, b : WallMap
        Wall cells and free space of the two maps.
    matrix : numpy.ndarray
        3x3 rigid transform (eqs. (1)-(2)), B pixel -> A pixel.
    block : float
        Side of the squares, pixels.
    max_shift : float
        Largest local shift, pixels.
    tolerance : float, optional
        As in :func:`map_agreement`.
    max_points : int, optional
        As in :func:`map_agreement`.

    Returns
    -------
    Agreement
        Counts summed over both directions.

    Raises
    ------
    ValueError
        If ``block`` is not positive or ``max_shift`` is negative.
    """
    return local_agreements(a, b, [matrix], block, max_shift, tolerance, max_points)[0]


def local_agreements(
    a: WallMap,
    b: WallMap,
    matrices: list[np.ndarray],
    block: float,
    max_shift: float,
    tolerance: float = 2.0,
    max_points: int = 0,
) -> list[Agreement]:
    """:func:`local_agreement` at each pose of ``matrices``, all in one pass.

    The poses' points go through each lookup, fit and count together, each pose's
    squares and sums kept apart: the counts are those of one call per pose, at the
    cost of one call's array passes rather than one per pose (a decision scores
    eight finalists, then eight probes, :mod:`pgvd.scoring`).

    Raises
    ------
    ValueError
        If ``block`` is not positive or ``max_shift`` is negative.
    """
    if not block > 0 or not max_shift >= 0:
        raise ValueError(f"block must be > 0 and max_shift >= 0, got {block} and {max_shift}")
    wb, wa = b.walls, a.walls
    if max_points > 0:
        wb, wa = subsample(wb, max_points), subsample(wa, max_points)
    if len(wb) == 0 or len(wa) == 0 or not matrices:
        return [map_agreement(a, b, m, tolerance, max_points) for m in matrices]
    each = [transform_points(m, wb) for m in matrices]
    moved = np.concatenate(each)
    # each pose's squares numbered after the previous pose's, in the order of their codes
    found = [np.unique(_cells(pts, block), return_inverse=True) for pts in each]
    squares = [sq for sq, _ in found]
    first = np.cumsum([0, *(sq.size for sq in squares)])
    group = np.concatenate([g.ravel() + f for (_, g), f in zip(found, first, strict=False)])
    pose = np.repeat(np.arange(len(matrices)), [sq.size for sq in squares])
    shift = _block_shifts(a, moved, group, pose, max_shift)
    owner_b = np.repeat(np.arange(len(matrices)), len(wb))
    ag1, dis1 = a.count_each(moved + shift[group], tolerance, owner_b)
    # A's walls take the shift of the square they fall in (fitted on B's walls there).
    codes = _cells(wa, block)
    back = []
    for m, sq, f in zip(matrices, squares, first, strict=False):
        at = np.minimum(np.searchsorted(sq, codes), len(sq) - 1)
        moved_back = np.where((sq[at] == codes)[:, None], shift[f + at], 0.0)
        back.append(transform_points(np.linalg.inv(m), wa - moved_back))
    owner_a = np.repeat(np.arange(len(matrices)), len(wa))
    ag2, dis2 = b.count_each(np.concatenate(back), tolerance, owner_a)
    counts = zip(ag1, ag2, dis1, dis2, strict=True)
    return [Agreement(int(g1 + g2), int(d1 + d2)) for g1, g2, d1, d2 in counts]
