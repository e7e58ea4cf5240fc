"""A map's wall cells for the full-resolution stages: nearest walls and their normals.

:class:`WallMap` holds a map's free space and the faces of its walls, with a k-d
tree (:class:`WallTree`) or a nearest-wall table for the lookups of the
overlay counts, the refinement and the covariance.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree

from pgvd.morphology import surface


def transform_points(m: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """The points ``(N, 2)`` ``(x, y)`` moved by the 3x3 homogeneous matrix ``m``."""
    return pts @ m[:2, :2].T + m[:2, 2]


class WallTree(cKDTree):
    """A k-d tree of wall cells ``(x, y)`` that keeps each cell's wall normal once computed.

    The point-to-line stages ask for the normals at the nearest wall cells
    over and over (every Gauss-Newton step, the residual distortion, the
    covariance); a normal depends on its cell alone, so each is computed once.
    """

    def __init__(self, walls: np.ndarray) -> None:
        # the sliding-midpoint tree builds in half the time and answers these
        # nearest-wall queries faster than the median-split default
        super().__init__(walls, balanced_tree=False, compact_nodes=False)
        self._normal = np.full((self.n, 2), np.nan)

    def normals(self, idx: np.ndarray) -> np.ndarray:
        """Unit wall normals at the cells ``idx`` of the tree (see :func:`_normals`)."""
        missing = np.unique(idx[np.isnan(self._normal[idx, 0])])
        if missing.size:
            self._normal[missing] = _normals(self, self.data[missing])
        return self._normal[idx]


class WallMap:
    """A full-resolution map for overlay checks: its probabilities and a k-d tree of its walls.

    With ``lookup``, nearest-wall queries (:meth:`nearest`) read a table of
    every cell's nearest wall cell instead of the tree, built on first use
    from a distance transform: an O(1) lookup a point for a transform of the
    whole map, which pays for the map every hypothesis is scored against
    (A), not for one only counted once per hypothesis (B).
    """

    def __init__(
        self, prob: np.ndarray, occupied: float, free: float, lookup: bool = False
    ) -> None:
        prob = np.asarray(prob)
        self.free = prob < free
        # only the faces of walls: inside a thick wall every cell has a wall cell at
        # distance 0, so the alignment cost is flat there and a refinement stops
        # wherever it enters (intel's map with 5-cell walls, merged onto a crop of
        # itself, came out 2.5 px off); thin walls, as a laser draws them, are all
        # face.  A map that is wall from edge to edge has no face: its wall cells
        # are all it has.
        walls = prob > occupied
        faces = surface(walls)
        # flat indices split by divmod: the same cells in the same (row-major) order as
        # np.nonzero, which is ~8x slower on a full-resolution map
        self._flat = np.flatnonzero(faces if faces.any() else walls)
        r, c = np.divmod(self._flat, prob.shape[1])
        self.walls = np.column_stack([c, r]).astype(float)
        self._x, self._y = c.astype(float), r.astype(float)
        self.tree = WallTree(self.walls)
        self.lookup = lookup
        self._table: np.ndarray | None = None

    def normals(self, idx: np.ndarray) -> np.ndarray:
        """Unit wall normals (:func:`_normals`) at the wall cells ``idx``, computed once each."""
        return self.tree.normals(idx)

    def _nearest_table(self) -> np.ndarray:
        """(H + 1, W + 1) index into :attr:`walls` of each cell's nearest wall cell (built
        once); the last row and column repeat the ones before."""
        if self._table is None:
            h, w = self.free.shape
            open_cells = np.ones((h, w), bool)
            open_cells.flat[self._flat] = False
            # the exact Euclidean transform's nearest wall cell of every cell, as its
            # (row, col) (int32); a (row, col) to its index into self.walls through a
            # map-sized table of wall numbers (row-major: the order of self.walls)
            rows, cols = ndimage.distance_transform_edt(
                open_cells, return_distances=False, return_indices=True
            )
            number = np.zeros(h * w, np.int32)
            number[self._flat] = np.arange(len(self._flat), dtype=np.int32)
            np.multiply(rows, w, out=rows)
            rows += cols
            # one more row and column (copies of the last) so that every point has four
            # cells around it in the table
            table = np.empty((h + 1, w + 1), np.int32)
            np.take(number, rows, out=table[:h, :w])
            table[:h, w] = table[:h, w - 1]
            table[h] = table[h - 1]
            self._table = table
        return self._table

    def nearest(self, points: np.ndarray, reach: float) -> tuple[np.ndarray, np.ndarray]:
        """Distance and index of a nearest wall cell of each point ``(x, y)``, within ``reach``.

        With ``lookup``, the wall is the nearest of those the table names for
        the four cells around the point (a point off the map: the cells on
        it nearest to it), at its exact distance.  Over the map it is the
        nearest wall for 99.8-99.99 % of points (the development maps) and
        otherwise at most 1.42 cells farther (on those maps under 0.4); off
        the map it can be farther by more.  As ``cKDTree.query``: ``inf`` and
        ``len(walls)`` beyond ``reach``.
        """
        if not self.lookup:
            return self.tree.query(points, distance_upper_bound=reach)
        n = len(self.walls)
        if n == 0 or len(points) == 0:
            return np.full(len(points), np.inf), np.full(len(points), n)
        table = self._nearest_table()
        h, w = table.shape
        px, py = points[:, 0], points[:, 1]
        # the cell at the lower corner of the point; the table's extra last row and
        # column make its right and lower neighbours valid cells too.  Clipped to the
        # table first, a coordinate is >= 0, where truncation is the floor
        col = np.clip(px, 0, w - 2).astype(np.intp)
        cell = np.clip(py, 0, h - 2).astype(np.intp)
        cell *= w
        cell += col
        # the four candidates of every point, one corner a row (contiguous), squared
        # distances in place, then a scan of the corners that keeps the first of equals
        # (argmin's choice, without its per-point loop over a short axis)
        corners = np.array([0, 1, w, w + 1])[:, None] + cell
        cand = table.ravel()[corners]
        d2 = self._x[cand]
        d2 -= px
        d2 *= d2
        dy = self._y[cand]
        dy -= py
        dy *= dy
        d2 += dy
        # rows of the scratch arrays d2 and cand, overwritten in place
        best, idx = d2[0], cand[0]
        for k in (1, 2, 3):
            closer = d2[k] < best
            np.copyto(best, d2[k], where=closer)
            np.copyto(idx, cand[k], where=closer)
        idx = idx.astype(np.intp)
        dist = np.sqrt(best, out=best)
        far = dist > reach
        dist[far], idx[far] = np.inf, n
        return dist, idx

    def count(self, points: np.ndarray, tolerance: float) -> tuple[int, int]:
        """(agree, disagree) of another map's wall points ``(N, 2)`` (x, y) in this frame.

        A point agrees within ``tolerance`` of a wall here and disagrees on a
        free cell farther than ``2 tolerance`` from every wall.
        """
        agree, disagree = self.count_each(points, tolerance, np.zeros(len(points), np.intp))
        return int(agree[0]), int(disagree[0])

    def count_each(
        self, points: np.ndarray, tolerance: float, owner: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`count` of the points of each owner: (agree, disagree), int arrays indexed
        by ``owner`` (ints from 0, one a point), as long as its largest value plus one."""
        dist, _ = self.nearest(points, 2 * tolerance + 1e-9)
        ij = np.rint(points).astype(np.int64)
        h, w = self.free.shape
        inside = (ij[:, 0] >= 0) & (ij[:, 0] < w) & (ij[:, 1] >= 0) & (ij[:, 1] < h)
        free = np.zeros(len(points), bool)
        free[inside] = self.free[ij[inside, 1], ij[inside, 0]]
        n = int(owner.max()) + 1 if owner.size else 1
        agree = np.bincount(owner[dist <= tolerance], minlength=n)
        disagree = np.bincount(owner[free & ~np.isfinite(dist)], minlength=n)
        return agree, disagree


Walls = cKDTree | WallMap
"""A's walls for the alignment stages: a k-d tree of wall cells, or a :class:`WallMap`."""


def nearest_walls(
    walls_a: Walls, points: np.ndarray, reach: float
) -> tuple[np.ndarray, np.ndarray]:
    """Nearest wall cell of each point within ``reach``: (distance, index), as ``cKDTree.query``."""
    if isinstance(walls_a, WallMap):
        return walls_a.nearest(points, reach)
    return walls_a.query(points, distance_upper_bound=reach)


def wall_cells(walls_a: Walls) -> np.ndarray:
    """(N, 2) wall cells ``(x, y)`` that :func:`nearest_walls` indexes."""
    return walls_a.walls if isinstance(walls_a, WallMap) else walls_a.data


def wall_normals(walls_a: Walls, idx: np.ndarray) -> np.ndarray:
    """Unit wall normals at the cells ``idx`` of ``walls_a``, from its cache when it keeps one."""
    if isinstance(walls_a, WallMap | WallTree):
        return walls_a.normals(idx)
    return _normals(walls_a, walls_a.data[idx])


def _normals(tree: cKDTree, points: np.ndarray, k: int = 8) -> np.ndarray:
    """Unit wall normals at ``points``: the minor axis of the ``k`` nearest cells of the tree."""
    _, idx = tree.query(points, k=k)
    # x and y of the neighbours as two contiguous (N, k) arrays: the same sums, in the
    # same order, as over the (N, k, 2) gather, without its strided passes
    x, y = tree.data[:, 0][idx], tree.data[:, 1][idx]
    x -= x.mean(axis=1, keepdims=True)
    y -= y.mean(axis=1, keepdims=True)
    sxx = np.mean(x * x, axis=1)
    syy = np.mean(y * y, axis=1)
    sxy = np.mean(x * y, axis=1)
    # closed-form eigenvector of the smaller eigenvalue of [[sxx, sxy], [sxy, syy]]
    theta = 0.5 * np.arctan2(2 * sxy, sxx - syy) + np.pi / 2
    return np.column_stack([np.cos(theta), np.sin(theta)])
