"""Moving maps between pixel frames: warp by a B->A matrix, resample, and the union canvas.

Pixel frame (``pgvd.grid``): ``x`` = column, ``y`` = row, cell centres at
integers; a relative transform ``M`` maps ``[xb, yb, 1]`` to ``[xa, ya, 1]``
(eq. (1)-(2) in homogeneous form).
"""

from __future__ import annotations

import math

import numpy as np
from scipy import ndimage

from pgvd.grid import Grid, finite_3x3


def warp(
    image: np.ndarray,
    matrix: np.ndarray,
    out_shape: tuple[int, int],
    order: int = 1,
    cval: float = 0.0,
) -> np.ndarray:
    """Resample ``image`` (frame B) into frame A through the B->A pixel ``matrix``.

    ``out[ya, xa] = image[M^-1 (xa, ya)]``, eq. (1) applied to every cell.
    ``scipy.ndimage.affine_transform`` pulls values through the *inverse*
    map in ``(row, col)`` order, so the 2x2 part and the offset of ``M^-1``
    are swapped from ``(x, y)`` to ``(y, x)``.

    Parameters
    ----------
    image : numpy.ndarray
        (H, W) array in frame B.
    matrix : numpy.ndarray
        3x3 affine matrix, B pixel -> A pixel.
    out_shape : tuple of int
        (rows, cols) of the output, frame A.
    order : int, optional
        Spline order (0 nearest, 1 bilinear).
    cval : float, optional
        Value of cells that fall outside ``image`` (0 = unknown log-odds).

    Returns
    -------
    numpy.ndarray
        (rows, cols) float array in frame A.

    Raises
    ------
    ValueError
        If ``matrix`` is not a finite 3x3 array.

    References
    ----------
    .. [1] Saeedi, S., Paull, L., Trentini, M., Seto, M., and Li, H., "Map merging
       using probabilistic generalized Voronoi diagrams", IROS 2012, eqs. (1), (12), (30).
    """
    m = finite_3x3(matrix, "matrix")
    inv = np.linalg.inv(m)
    rc = inv[:2, :2][::-1, ::-1]  # (x, y) -> (row, col) = (y, x)
    offset = inv[:2, 2][::-1]
    src = np.asarray(image)
    dtype = src.dtype if src.dtype.kind == "f" else np.float32
    return ndimage.affine_transform(
        src.astype(dtype, copy=False),
        rc,
        offset=offset,
        output_shape=tuple(int(s) for s in out_shape),
        order=order,
        # 'grid-constant': cells are squares around integer centres, so B's border cells
        # blend into cval instead of dropping out on a rounding error ('constant' does that)
        mode="grid-constant",
        cval=cval,
        prefilter=order > 1,
    )


def scale_matrix(
    from_resolution: float, to_resolution: float, from_rows: int, to_rows: int
) -> np.ndarray:
    """Pixel matrix from a grid at ``from_resolution`` to one at ``to_resolution`` that
    shares its metric lower-left corner (origin), as :func:`resample` builds it."""
    s = from_resolution / to_resolution
    # x: (x' + 0.5) r' = (x + 0.5) r;  y counts rows down from the top, the corner is at the bottom:
    # (H' - y' - 0.5) r' = (H - y - 0.5) r
    return np.array(
        [
            [s, 0.0, 0.5 * s - 0.5],
            [0.0, s, to_rows - 0.5 - (from_rows - 0.5) * s],
            [0.0, 0.0, 1.0],
        ]
    )


def resample(grid: Grid, resolution: float) -> Grid:
    """The same map at another resolution, keeping its metric origin.

    Upsampling interpolates log-odds bilinearly.  Downsampling gives each
    target cell the largest log-odds of the source cells around its centre
    (an odd window just wider than its footprint), so that walls one cell
    thick survive -- the GVD depends on them -- at the price of walls up to
    one source cell thicker.

    Parameters
    ----------
    grid : Grid
        The map.
    resolution : float
        Target metres per cell, > 0.

    Returns
    -------
    Grid
        ``round(H * r / resolution)`` rows, same origin.

    Raises
    ------
    ValueError
        If ``resolution`` is not a positive number.
    """
    if not math.isfinite(resolution) or resolution <= 0:
        raise ValueError(f"resolution must be > 0, got {resolution}")
    if resolution == grid.resolution:
        return grid
    h, w = grid.shape
    s = grid.resolution / resolution
    out_shape = (max(1, round(h * s)), max(1, round(w * s)))
    m = scale_matrix(grid.resolution, resolution, h, out_shape[0])
    if s < 1.0:
        size = 2 * math.ceil((1.0 / s + 1.0) / 2.0) - 1
        lo = ndimage.maximum_filter(grid.logodds, size=size)
        out = warp(lo, m, out_shape, order=0, cval=0.0)
    else:
        out = warp(grid.logodds, m, out_shape, order=1, cval=0.0)
    return Grid(out.astype(np.float32), float(resolution), grid.origin)


def footprint(shape: tuple[int, int], matrix: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The whole cells of frame A that a map of ``shape`` covers through ``matrix``.

    Parameters
    ----------
    shape : tuple of int
        (rows, cols) of the map.
    matrix : numpy.ndarray
        3x3, map pixel -> A pixel.

    Returns
    -------
    lo, hi : numpy.ndarray
        Integer ``(x, y)`` of the first and the last A cell of the bounding box of the
        map's cell centres (``hi`` inclusive).
    """
    h, w = shape
    corners = np.array([[0, 0, 1], [w - 1, 0, 1], [0, h - 1, 1], [w - 1, h - 1, 1]], float)
    pts = (np.asarray(matrix, dtype=np.float64) @ corners.T)[:2].T
    return np.floor(pts.min(axis=0)).astype(int), np.ceil(pts.max(axis=0)).astype(int)


def union_canvas(
    shape_a: tuple[int, int], shape_b: tuple[int, int], matrix: np.ndarray
) -> tuple[tuple[int, int], np.ndarray]:
    """The smallest canvas that holds map A and map B (through ``matrix``) whole.

    Parameters
    ----------
    shape_a, shape_b : tuple of int
        (rows, cols) of A and B.
    matrix : numpy.ndarray
        3x3, B pixel -> A pixel.

    Returns
    -------
    out_shape : tuple of int
        (rows, cols) of the canvas.
    offset_matrix : numpy.ndarray
        3x3 integer translation, A pixel -> canvas pixel, so that A lands on
        the canvas without interpolation; B -> canvas is ``offset_matrix @ matrix``.
    """
    lo_b, hi_b = footprint(shape_b, matrix)
    lo = np.minimum(lo_b, 0)
    hi = np.maximum(hi_b, [shape_a[1] - 1, shape_a[0] - 1])
    offset = np.array([[1.0, 0.0, -lo[0]], [0.0, 1.0, -lo[1]], [0.0, 0.0, 1.0]])
    return (int(hi[1] - lo[1] + 1), int(hi[0] - lo[0] + 1)), offset
