"""Binary and grey morphology on small grids, cheaper than scipy.ndimage for square elements."""

from __future__ import annotations

import numpy as np


def grow(mask: np.ndarray, cells: int = 1) -> np.ndarray:
    """Binary dilation of ``mask`` by a ``(2 cells + 1)``-square, cells beyond the edge False.

    The bool case of :func:`grow_max` (the largest of booleans is their OR).
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
    return grow_max(np.asarray(mask, dtype=bool), cells)


def grow_max(values: np.ndarray, cells: int = 1) -> np.ndarray:
    """Grey dilation of ``values`` by a ``(2 cells + 1)``-square: the largest value within it.

    Cells beyond the edge do not count.  For non-negative values inside a
    zero border at least ``cells`` wide, as the edge sub-matrices of
    :func:`pgvd.edge_matching.similarity` are, this equals
    ``scipy.ndimage.grey_dilation(values, size=2 cells + 1)``, at a fraction
    of its per-call cost on arrays of a few hundred cells.

    Parameters
    ----------
    values : (H, W) array.
    cells : half-width of the square, >= 0.

    Returns
    -------
    (H, W) array of ``values``' dtype (a new one).
    """
    if cells < 0:
        raise ValueError(f"cells must be >= 0, got {cells}")
    out = np.array(values)
    if out.ndim != 2:
        raise ValueError(f"morphology needs a 2-D array, got shape {out.shape}")
    for _ in range(cells):
        rows = out.copy()
        np.maximum(rows[1:], out[:-1], out=rows[1:])
        np.maximum(rows[:-1], out[1:], out=rows[:-1])
        out = rows.copy()
        np.maximum(out[:, 1:], rows[:, :-1], out=out[:, 1:])
        np.maximum(out[:, :-1], rows[:, 1:], out=out[:, :-1])
    return out


def surface(mask: np.ndarray) -> np.ndarray:
    """The cells of ``mask`` with a 4-neighbour outside it: the faces of its regions.

    A range sensor sees a wall only where it borders the space in front of it;
    the inside of a thick wall (a map image drawn with 3-10 px walls, an area
    filled in as occupied) is never observed.  Cells beyond the array's edge
    count as inside ``mask``, so a region cut by the edge has no face there.

    Parameters
    ----------
    mask : (H, W) array, read as bool.

    Returns
    -------
    (H, W) bool array (a new one).
    """
    mask = np.asarray(mask, dtype=bool)
    if mask.ndim != 2:
        raise ValueError(f"morphology needs a 2-D array, got shape {mask.shape}")
    inside = mask.copy()
    inside[1:] &= mask[:-1]
    inside[:-1] &= mask[1:]
    inside[:, 1:] &= mask[:, :-1]
    inside[:, :-1] &= mask[:, 1:]
    return mask & ~inside


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
