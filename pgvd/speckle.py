"""Speckle: lone wall cells of a raw map, read as unknown for registration.

A raw occupancy grid (one saved straight from a SLAM, never cleaned) carries
isolated occupied cells in its free space: spurious returns, a person seen
once, a reflection.  Two maps of one building carry different speckle, and
registration reads every speckle cell as a wall: coarsened to the search's
0.2 m cells it becomes a wall block, its PGVD grows edges around it, and on
the other map it lands on free space as a contradiction.  Cut from the
development map images with 0.5 % of their free cells turned into lone
walls, independently in each part, 14 of 18 pairs merged right instead of 18
of 18; with 2 %, 2 of 18 (``python3 -m bench.mapimages --speckle``).

A wall cell is speckle when the square of ``2 radius + 1`` cells around it
holds at most ``most`` wall cells, itself included.  A wall, even one a
laser draws as a dotted line at a grazing angle, has wall cells every cell or
two along it, so its cells have several neighbours in that square; a lone
cell or a pair has none.  With ``MergeParams.speckle_radius`` (``pgvd merge
--despeckle``), registration reads speckle as unknown
(:func:`pgvd.merge.registration_probability`); fusion keeps the map as drawn.  It is
off by default: a laser's own map holds lone cells that are real (far walls drawn as
sparse dots, chair legs), and reading them as unknown loses pairs of the development
bench (:class:`pgvd.merge.MergeParams`).
"""

from __future__ import annotations

import numpy as np

#: ``pgvd merge --despeckle``'s ``MergeParams.speckle_radius`` (m): 3 cells at 0.05 m, where
#: a laser's dotted wall still has a dot every cell or two, and speckle at 0.5 % of the free
#: cells has another within it about once in five.
DESPECKLE_RADIUS = 0.15


def lone_walls(walls: np.ndarray, radius: int, most: int) -> np.ndarray:
    """Wall cells with at most ``most`` wall cells (themselves included) in the square of
    side ``2 radius + 1`` centred on them; the map's border counts as no wall.

    Parameters
    ----------
    walls : numpy.ndarray
        (H, W) bool, the wall cells.
    radius : int
        Half the side of the square, in cells (>= 1).
    most : int
        Largest number of wall cells in the square of a lone wall cell (>= 1).

    Returns
    -------
    numpy.ndarray
        (H, W) bool, True at the lone wall cells.

    Raises
    ------
    ValueError
        If ``radius`` or ``most`` is below 1.
    """
    import cv2

    if radius < 1 or most < 1:
        raise ValueError(f"radius and most must be >= 1, got {radius} and {most}")
    walls = np.asarray(walls, dtype=bool)
    side = 2 * radius + 1
    # counts are small whole numbers, exact in float32
    count = cv2.boxFilter(
        walls.astype(np.float32), -1, (side, side), normalize=False,
        borderType=cv2.BORDER_CONSTANT,
    )  # fmt: skip
    return walls & (count < most + 0.5)


def without_speckle(
    prob: np.ndarray, occupied: float, radius: int, most: int
) -> tuple[np.ndarray, int]:
    """``prob`` with its :func:`lone_walls` (cells above ``occupied``) unknown (0.5), and
    how many there were.

    Parameters
    ----------
    prob : numpy.ndarray
        Occupancy probabilities (eq. (34)) of one map.
    occupied : float
        Probability above which a cell is a wall.
    radius, most : int
        As in :func:`lone_walls`.

    Returns
    -------
    tuple of (numpy.ndarray, int)
        The probabilities (a copy of ``prob``'s dtype when a cell changed, else ``prob``)
        and the number of wall cells read as unknown.
    """
    prob = np.asarray(prob)
    lone = lone_walls(prob > occupied, radius, most)
    n = int(np.count_nonzero(lone))
    if n == 0:
        return prob, 0
    return np.where(lone, np.asarray(0.5, prob.dtype), prob), n
