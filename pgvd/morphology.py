"""Binary morphology on small grids, cheaper than :mod:`scipy.ndimage` for square elements."""

from __future__ import annotations

import numpy as np


def grow(mask: np.ndarray, cells: int = 1) -> np.ndarray:
    """Binary dilation of ``mask`` by a ``(2 cells + 1)``-square, cells beyond the edge False.

    The square is separable, so each step is an OR of shifted slices along the
    rows, then along the columns: the result equals
    ``scipy.ndimage.binary_dilation(mask, np.ones((3, 3)), iterations=cells)``
    without its per-call overhead, which dominates on the coarse maps of the
    merge (a few hundred cells a side).

    Parameters
    ----------
    mask : (H, W) array, read as bool.
    cells : half-width of the square, >= 0.

    Returns
    -------
    (H, W) bool array (a new one).
    """
    if cells < 0:
        raise ValueError(f"cells must be >= 0, got {cells}")
    out = np.array(mask, dtype=bool)
    if out.ndim != 2:
        raise ValueError(f"grow needs a 2-D mask, got shape {out.shape}")
    for _ in range(cells):
        rows = out.copy()
        rows[1:] |= out[:-1]
        rows[:-1] |= out[1:]
        out = rows.copy()
        out[:, 1:] |= rows[:, :-1]
        out[:, :-1] |= rows[:, 1:]
    return out


def drop_small(mask: np.ndarray, max_size: int) -> np.ndarray:
    """``mask`` without its 4-connected components of at most ``max_size`` cells.

    The same cells as scikit-image's ``remove_small_objects(mask, max_size=max_size)`` (whose
    ``max_size`` exists only from 0.26, while Python 3.10, ROS 2 Humble's, has at most 0.25),
    from :func:`scipy.ndimage.label` and a count per label.

    Parameters
    ----------
    mask : (H, W) array, read as bool.
    max_size : components of this many cells or fewer are removed; >= 0.

    Returns
    -------
    (H, W) bool array (a new one).
    """
    from scipy import ndimage

    if max_size < 0:
        raise ValueError(f"max_size must be >= 0, got {max_size}")
    out = np.array(mask, dtype=bool)
    labels, _ = ndimage.label(out)
    sizes = np.bincount(labels.ravel())
    small = sizes <= max_size
    small[0] = False  # the background is not a component
    out[small[labels]] = False
    return out
