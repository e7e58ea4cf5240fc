"""Unknown space that a map image lost: a map with no unknown cells, read for registration.

A SLAM map of part of a building is mostly unknown: over half the cells of
every development map and bench pair.  Some map images have none: an editor
or an export painted the unexplored area white, so that everything outside
the walls reads as free.  Such a map claims to have seen free space where its
robot never looked, and registration counts a wall of the other map on free
space as a contradiction: the walls of the other map beyond this one's
explored part speak against the true pose.

Free space is believed only inside the convex hull of the map's walls
(:func:`wall_hull`), where a robot that drew those walls could have looked;
outside it, free cells are unknown again.  A courtyard, a bay between two
wings, or a room the robot never entered stays free inside the hull: the rule
under-restores, and never adds a wall.  A tighter rule was measured and not
kept: free space that reaches the map's edge through cells over 1 m from
every wall, alone or with the hull, gained painted pairs of the robots' own
partial maps but lost map images or accepted negatives (the project's
``docs/studies.md``, "Map images: tried and not kept").  Registration applies it
only to maps with (almost) no unknown cells
(:func:`pgvd.inputs.registration_probability`), which no SLAM map is: the maps the
bench was tuned on are read exactly as before.
"""

from __future__ import annotations

import numpy as np


def unknown_share(prob: np.ndarray, free: float, occupied: float) -> float:
    """Share of the cells of ``prob`` neither free (< ``free``) nor walls (> ``occupied``)."""
    prob = np.asarray(prob)
    unknown = np.count_nonzero((prob >= free) & (prob <= occupied))
    return unknown / max(1, prob.size)


#: Walls above this share (50 %) of a map's known cells (:func:`wall_share`) are no laser's
#: map: a laser draws thin walls around the free space it saw, 0.5-7 % of the known cells of
#: every development map image.  An image that stores unknown space black reads so: its
#: unexplored space becomes walls (80 % of intel's example map B drawn that way).
MOSTLY_WALLS = 0.5


def wall_share(prob: np.ndarray, free: float, occupied: float) -> float:
    """Share of walls (> ``occupied``) among the known cells of ``prob`` (walls or free,
    < ``free``); 0 for a map with no known cell."""
    prob = np.asarray(prob)
    walls = np.count_nonzero(prob > occupied)
    return walls / max(1, walls + np.count_nonzero(prob < free))


def wall_hull(walls: np.ndarray) -> np.ndarray:
    """Cells whose centres lie in the convex hull of the True cells of ``walls`` (edge
    included), as a boolean mask of its shape; all False without a wall."""
    import cv2

    mask = np.zeros(walls.shape, np.uint8)
    rows, cols = np.nonzero(walls)
    if rows.size:
        points = np.column_stack([cols, rows]).astype(np.int32)
        cv2.fillConvexPoly(mask, cv2.convexHull(points), 1)
    return mask.astype(bool)


def restore_unexplored(prob: np.ndarray, free: float, occupied: float) -> np.ndarray:
    """A copy of ``prob`` whose free cells outside the :func:`wall_hull` are unknown (0.5).

    Parameters
    ----------
    prob : numpy.ndarray
        Occupancy probabilities (eq. (34)) of one map.
    free, occupied : float
        Probability thresholds of free space and walls.

    Returns
    -------
    numpy.ndarray
        The restored probabilities, of ``prob``'s dtype.
    """
    prob = np.asarray(prob)
    outside = (prob < free) & ~wall_hull(prob > occupied)
    return np.where(outside, np.asarray(0.5, prob.dtype), prob)
