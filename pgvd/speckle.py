"""Speckle: lone wall cells of a raw map, read as unknown for registration.

A raw occupancy grid (one saved straight from a SLAM, never cleaned) carries
isolated occupied cells in its free space: spurious returns, a person seen
once, a reflection.  Two maps of one building carry different speckle, and
registration reads every speckle cell as a wall: coarsened to the search's
0.2 m cells it becomes a wall block, its PGVD grows edges around it, and on
the other map it lands on free space as a contradiction.  Cut from the
development map images with 0.5 % of their free cells turned into lone
walls, independently in each part, 15 of 18 pairs merged right instead of 18
of 18 (walls as drawn); with 2 %, 1 of 18 (``python3 -m bench.mapimages
--speckle 0.005``, ``bench/results/mapimages-speckle-*.md``).

A wall cell is speckle when the square of ``2 radius + 1`` cells around it
holds at most ``most`` wall cells, itself included.  A wall, even one a
laser draws as a dotted line at a grazing angle, has wall cells every cell or
two along it, so with a radius of 2 cells or more its cells have several
neighbours in that square (the two end dots of a dotted wall may not); a lone
cell or a pair has none.  With ``OffParams.speckle_radius`` (``pgvd merge
--despeckle``), registration reads speckle as unknown
(:func:`pgvd.inputs.registration_probability`); fusion keeps the map as drawn.  It is
off by default: a laser's own map holds lone cells that are real (far walls drawn as
sparse dots, chair legs), and reading them as unknown loses pairs of the development
bench (:class:`pgvd.params.MergeParams`).  A merge that is rejected is tried once more
with speckle read as unknown when a map's lone wall cells are 0.4 % of its free cells or
more (:func:`speckle_share`, ``ReadingParams.speckle_retry``): more than most laser maps
have, as raw images with half a per cent of speckle do.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

#: ``pgvd merge --despeckle``'s ``OffParams.speckle_radius`` (m): 3 cells at 0.05 m, where
#: a laser's dotted wall still has a dot every cell or two, and speckle at 0.5 % of the free
#: cells has another within it about once in five.
DESPECKLE_RADIUS = 0.15


def radius_cells(radius: float, resolution: float) -> int:
    """The half-side in cells of the speckle square of ``radius`` metres: at least 2, since
    in a 3x3 square a wall drawn every other cell is all speckle."""
    return max(2, round(radius / resolution))


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
    if not 1 <= radius <= 127 or most < 1:
        raise ValueError(f"radius must be in 1..127 and most >= 1, got {radius} and {most}")
    walls = np.asarray(walls, dtype=bool)
    # the square's count as two 1-D sums, 16-bit (a square of up to 255x255 cells): a
    # quarter of the memory of float32 counts on a map at --max-cells
    ones = np.ones(2 * radius + 1)
    count = ndimage.correlate1d(walls.view(np.uint8), ones, 0, np.uint16, mode="constant")
    count = ndimage.correlate1d(count, ones, 1, np.uint16, mode="constant")
    return walls & (count <= most)


def speckle_share(prob: np.ndarray, occupied: float, free: float, radius: int, most: int) -> float:
    """How raw a map is: its :func:`lone_walls` (cells above ``occupied``) per free cell
    (below ``free``).

    A share of free cells, as speckle is drawn: spurious returns land in the space the
    laser swept.  On the development bench (``python3 -m bench.merge``) at 5 cm cells, with
    the despeckle reading (radius 3 cells, at most 2 walls), the laser's and the simulated
    laser's maps have at most 0.82 % (median 0.07-0.30 % per source), the map images as
    saved 0.01-0.33 %, and those images with 2 % of their free cells turned into walls
    1.25-2.2 %.

    Parameters
    ----------
    prob : numpy.ndarray
        Occupancy probabilities (eq. (34)) of one map.
    occupied, free : float
        Probabilities above which a cell is a wall, below which it is free.
    radius, most : int
        As in :func:`lone_walls`.

    Returns
    -------
    float
        0 for a map without free cells.
    """
    prob = np.asarray(prob)
    n_free = int(np.count_nonzero(prob < free))
    if n_free == 0:
        return 0.0
    return int(np.count_nonzero(lone_walls(prob > occupied, radius, most))) / n_free


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
