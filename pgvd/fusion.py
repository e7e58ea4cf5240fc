"""Map fusion: log-odds addition (33)-(34) and the entropy filter (35)-(37), Sec. IV-G."""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np

from pgvd.grid import (
    LOGODDS_LIMIT,
    Grid,
    finite_3x3,
    pixel_to_world,
    probability_to_logodds,
)
from pgvd.transform import union_canvas
from pgvd.uncertainty import propagate


def entropy(p: np.ndarray) -> np.ndarray:
    """Eq. (35): ``H = -p log p - (1 - p) log(1 - p)`` in nats, with ``0 log 0 = 0``.

    Parameters
    ----------
    p : numpy.ndarray
        Occupancy probabilities in [0, 1].

    Returns
    -------
    numpy.ndarray
        float64 entropy per cell.

    References
    ----------
    .. [1] Saeedi, S., Paull, L., Trentini, M., Seto, M., and Li, H., "Map merging
       using probabilistic generalized Voronoi diagrams", IROS 2012, eq. (35).
    """
    p = np.asarray(p, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        h = -(np.where(p > 0, p * np.log(p), 0.0) + np.where(p < 1, (1 - p) * np.log1p(-p), 0.0))
    return h


def fuse(base_logodds: np.ndarray, other_logodds: np.ndarray) -> np.ndarray:
    """Fuse ``other`` into ``base``: eq. (33), then the entropy filter (35)-(37).

    ``l_fused = l_base + l_other`` (33); a cell keeps ``l_fused`` where the
    information ``I = H(base) - H(fused)`` (36) is >= 0, else ``l_base`` (37).
    The entropy of a binary cell falls strictly with ``|l|``, so ``I >= 0``
    is evaluated as ``|l_fused| >= |l_base|``: the same test without the
    rounding of (35) near p = 0 or 1.  An unknown ``other`` cell (0) leaves
    ``base`` as it was.

    Parameters
    ----------
    base_logodds, other_logodds : numpy.ndarray
        Same-shape log-odds arrays, both in base's frame.

    Returns
    -------
    numpy.ndarray
        float32 log-odds, the final map of eq. (37).

    Raises
    ------
    ValueError
        If the shapes differ.

    References
    ----------
    .. [1] Saeedi, S., Paull, L., Trentini, M., Seto, M., and Li, H., "Map merging
       using probabilistic generalized Voronoi diagrams", IROS 2012, eqs. (33)-(37).
    """
    base = np.asarray(base_logodds, dtype=np.float32)
    other = np.asarray(other_logodds, dtype=np.float32)
    if base.shape != other.shape:
        raise ValueError(f"maps must have the same shape, got {base.shape} and {other.shape}")
    fused = np.clip(base + other, -LOGODDS_LIMIT, LOGODDS_LIMIT)  # as eq. (9) clips
    return np.where(np.abs(fused) >= np.abs(base), fused, base).astype(np.float32)


def fuse_many(base: np.ndarray, others: Iterable[np.ndarray]) -> np.ndarray:
    """Fuse several maps into ``base`` one after another, in the order given.

    The entropy filter (37) judges each update against the map so far, so
    the result depends on the order; callers pass a fixed order (e.g. by
    robot id) so that every agent computes the same map.

    Parameters
    ----------
    base : numpy.ndarray
        Log-odds of the base map.
    others : iterable of numpy.ndarray
        Log-odds of the other maps, each already in base's frame and shape.

    Returns
    -------
    numpy.ndarray
        float32 log-odds.

    References
    ----------
    .. [1] Saeedi, S., Paull, L., Trentini, M., Seto, M., and Li, H., "Map merging
       using probabilistic generalized Voronoi diagrams", IROS 2012, eqs. (33)-(37).
    """
    out = np.asarray(base, dtype=np.float32)
    for other in others:
        out = fuse(out, other)
    return out


def fuse_maps(
    a: Grid,
    b: Grid,
    matrix: np.ndarray,
    covariance: np.ndarray,
    center: tuple[float, float] = (0.0, 0.0),
    propagation: bool = True,
) -> Grid:
    """Fuse map B into map A on a canvas that holds both whole (Fig. 1, last blocks).

    B is moved by ``matrix`` with its uncertainty propagated, eq. (8)
    (:func:`pgvd.uncertainty.propagate` on B's probabilities, unknown
    outside B), then fused into A by (33)-(37).  The result keeps A's world
    frame: its origin is the metric pose of the canvas's lower-left corner,
    so that A's cells sit at the same metric positions as before.

    Parameters
    ----------
    a, b : Grid
        The maps, with equal resolutions.
    matrix : numpy.ndarray
        3x3, B pixel -> A pixel.
    covariance : numpy.ndarray
        3x3 over ``(tx px, ty px, psi rad)`` of ``matrix`` read as eq. (1)
        (``rigid_matrix(psi, tx, ty)``), eq. (3), as :class:`pgvd.result.MergeResult`
        reports it.
    center : tuple of float, optional
        B pixel about which that heading error acts: eq. (1) rotates about
        B's pixel origin, the default.
    propagation : bool, optional
        False is the ablation "without propagation": B is only warped
        (bilinear), as if the transform were exact; ``covariance`` is not used.

    Returns
    -------
    Grid
        In A's frame, shifted by whole cells to hold both maps.

    Raises
    ------
    ValueError
        If the resolutions differ, ``matrix`` is not a finite 3x3 array, or
        ``covariance`` is not a finite, symmetric, positive semi-definite 3x3 array.

    References
    ----------
    .. [1] Saeedi, S., Paull, L., Trentini, M., Seto, M., and Li, H., "Map merging
       using probabilistic generalized Voronoi diagrams", IROS 2012, eqs. (3)-(8), (33)-(37).
    """
    if not np.isclose(a.resolution, b.resolution, rtol=1e-6, atol=0.0):
        raise ValueError(f"resolutions differ ({a.resolution} vs {b.resolution}); resample B")
    matrix = finite_3x3(matrix, "matrix")
    shape, offset = union_canvas(a.shape, b.shape, matrix)
    dx, dy = int(offset[0, 2]), int(offset[1, 2])
    base = np.zeros(shape, dtype=np.float32)
    base[dy : dy + a.shape[0], dx : dx + a.shape[1]] = a.logodds
    moved = propagate(
        b.probability(),
        offset @ matrix,
        covariance if propagation else np.zeros((3, 3)),
        shape,
        center=center,
        cval=0.5,
    )
    fused = fuse(base, probability_to_logodds(np.clip(moved, 0.0, 1.0)))
    # canvas pixel (0, H-1) is A pixel (-dx, H-1-dy); its lower-left corner is the new origin
    corner = pixel_to_world(a, [[-dx - 0.5, shape[0] - 1 - dy + 0.5]])[0]
    return Grid(fused, a.resolution, (float(corner[0]), float(corner[1]), a.origin[2]))
