"""Refinement of the decision's poses on the wall cells at full resolution."""

from __future__ import annotations

import numpy as np

from pgvd.alignment import refine, refine_point_to_line
from pgvd.params import MergeParams
from pgvd.sampling import subsample
from pgvd.walls import WallMap

#: ICP iterations per correspondence radius when the finalists are refined (each stops
#: early once it no longer moves).  ``DecisionParams.min_margin`` was set on finalists
#: refined with 3: better-refined rivals move every margin, so the two go together
#: (``docs/studies-merge-history.md`` has what 8 did).
FINALIST_ICP_ITERATIONS = 3


def final_refinement(
    matrix: np.ndarray, fine_a: WallMap, fine_b: WallMap, params: MergeParams
) -> np.ndarray:
    """The winner refined on all its wall cells: the pose a merge returns.

    Point-to-point ICP at 3 and 2 cells on ``params.refinement.fine_points`` of B's walls,
    then the robust point-to-line fit (:func:`pgvd.alignment.refine_point_to_line`,
    eqs. (1)-(2)) on all of them.

    Parameters
    ----------
    matrix : numpy.ndarray
        3x3 B pixel -> A pixel, the decision's winner.
    fine_a, fine_b : WallMap
        The two maps at full resolution.
    params : MergeParams
        The merge's parameters.

    Returns
    -------
    numpy.ndarray
        The refined 3x3 B pixel -> A pixel matrix.
    """
    points = subsample(fine_b.walls, params.refinement.fine_points)
    start = refine(fine_a, points, matrix, radii=(3.0, 2.0))
    # the pose returned is fitted on A's exact nearest walls (the tree): the table's
    # lookups at the four cells around a point miss the nearest wall for ~0.5 % of points
    return refine_point_to_line(fine_a.tree, fine_b.walls, start)


def refine_finalists(
    starts: list[np.ndarray], fine_a: WallMap, fine_b: WallMap, params: MergeParams
) -> list[np.ndarray]:
    """The finalists' poses (3x3, B pixel -> A pixel) refined by trimmed ICP at 12, 6 and
    3 cells on ``params.refinement.refine_points`` of B's walls: a coarse pose is a few
    cells off at full resolution."""
    sub_b = subsample(fine_b.walls, params.refinement.refine_points)
    return [
        refine(fine_a, sub_b, m, radii=(12.0, 6.0, 3.0), iterations=FINALIST_ICP_ITERATIONS)
        for m in starts
    ]
