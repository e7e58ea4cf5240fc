"""Even, deterministic subsampling of point sets, shared by every stage that caps its work."""

from __future__ import annotations

import numpy as np


def subsample(points: np.ndarray, max_points: int) -> np.ndarray:
    """Every ``k``-th row of ``points``, ``k = ceil(len / max_points)``, so at most ``max_points``.

    Taking a fixed stride rather than a random draw keeps merges reproducible
    and spreads the kept cells along every wall.

    Parameters
    ----------
    points : numpy.ndarray
        Array whose first axis indexes the points (any number of them, 0 included).
    max_points : int
        The most rows to keep, >= 1.

    Returns
    -------
    numpy.ndarray
        A view of ``points``: all of it when it holds at most ``max_points`` rows.

    Raises
    ------
    ValueError
        If ``max_points < 1``.
    """
    if max_points < 1:
        raise ValueError(f"max_points must be >= 1, got {max_points}")
    # at least 1: an empty set would give a stride of 0, which numpy refuses
    return points[:: max(1, -(-len(points) // max_points))]
