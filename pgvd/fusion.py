"""Map fusion: log-odds addition (33)-(34) and the entropy filter (35)-(37), Sec. IV-G.

Two maps: :func:`fuse_maps`.  Many maps into one base, with the warp of each kept apart
from the combine so that a caller can keep the warps: :func:`warp_layer` moves one map
into the base's pixels with its uncertainty, eq. (8), and :func:`fuse_layers` fuses such
layers into the base in a fixed order, eqs. (33)-(37).  :func:`warp_layer` is itself two
steps a caller can keep apart: the blur in the map's own frame, which does not depend on
where the map is placed (:func:`own_frame_covariance`, :func:`blur_in_own_frame`), and
the move (:func:`place_blurred`).
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import numpy as np

from pgvd.grid import (
    LOGODDS_LIMIT,
    Grid,
    finite_3x3,
    pixel_to_world,
    probability_to_logodds,
)
from pgvd.transform import footprint, union_canvas, warp
from pgvd.uncertainty import check_covariance, propagate


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
    cov = covariance if propagation else np.zeros((3, 3))
    fused = fuse(base, _moved_logodds(b, offset @ matrix, cov, shape, center))
    return Grid(fused, a.resolution, _canvas_origin(a, -dx, shape[0] - 1 - dy))


@dataclass(frozen=True)
class Layer:
    """One map moved into a base map's pixel frame with its uncertainty, eq. (8).

    Attributes
    ----------
    logodds : numpy.ndarray
        float32 log-odds of the moved map over the smallest box that holds every cell
        it knows; the cells around the box are unknown (0).
    corner : tuple of int
        ``(x, y)``, the base pixel of ``logodds[0, 0]``.
    bounds : tuple of int
        ``(x0, y0, x1, y1)``, inclusive: the base pixels the moved map covers
        (:func:`pgvd.transform.footprint`), known or not; a canvas that holds the map
        whole holds them.
    resolution : float
        Metres per cell of the moved map.
    """

    logodds: np.ndarray
    corner: tuple[int, int]
    bounds: tuple[int, int, int, int]
    resolution: float


def own_frame_covariance(matrix: np.ndarray, covariance: np.ndarray) -> np.ndarray:
    """The covariance of a transform's ``(tx, ty, psi)`` rotated into the moved map's frame.

    Eqs. (1)-(4): a point ``p`` of B moves by ``dpsi R J p + dT`` (``R`` the transform's
    rotation, ``J = R^-1 dR/dpsi``), that is by ``R (dpsi J p + R^T dT)``.  In B's own
    frame the displacement is ``dpsi J p + R^T dT``: eq. (4) with ``(R^T dT, dpsi)``,
    whose covariance is ``A Sigma_tr A^T``, ``A = diag(R^T, 1)``.  Eq. (8)'s blur is thus
    a blur in B's own frame by that covariance (rotation about B's pixel origin), moved
    rigidly by the transform: it depends on the heading of the transform, not on where it
    puts B.

    Parameters
    ----------
    matrix : numpy.ndarray
        3x3 rigid matrix, B pixel -> base pixel.
    covariance : numpy.ndarray
        3x3 over ``(tx px, ty px, psi rad)`` of ``matrix``, eq. (3).

    Returns
    -------
    numpy.ndarray
        3x3 symmetric covariance over ``(x px, y px, psi rad)`` in B's pixel frame.

    Raises
    ------
    ValueError
        If ``matrix`` is not a finite 3x3 array, or ``covariance`` is not a finite,
        symmetric, positive semi-definite 3x3 array.

    References
    ----------
    .. [1] Saeedi, S., Paull, L., Trentini, M., Seto, M., and Li, H., "Map merging
       using probabilistic generalized Voronoi diagrams", IROS 2012, eqs. (1)-(4).
    """
    a = np.eye(3)
    a[:2, :2] = finite_3x3(matrix, "matrix")[:2, :2].T
    out = a @ check_covariance(covariance) @ a.T
    return (out + out.T) / 2.0


def blur_in_own_frame(
    b: Grid, covariance: np.ndarray, center: tuple[float, float] = (0.0, 0.0)
) -> np.ndarray:
    """Eq. (8)'s blur of map B in B's own pixels: the step of :func:`warp_layer` that does
    not depend on where B is placed.

    :func:`pgvd.uncertainty.propagate` with the identity on B's probabilities, over B's
    own cells: nothing is blurred past B's edges.

    Parameters
    ----------
    b : Grid
        The map to blur.
    covariance : numpy.ndarray
        3x3 over ``(x px, y px, psi rad)`` in B's frame (:func:`own_frame_covariance`).
    center : tuple of float, optional
        B pixel about which the heading error acts, as in :func:`fuse_maps`.

    Returns
    -------
    numpy.ndarray
        float32, B's shape: the blurred probabilities minus 0.5, so that unknown is 0.

    Raises
    ------
    ValueError
        If ``covariance`` is not a finite, symmetric, positive semi-definite 3x3 array.

    References
    ----------
    .. [1] Saeedi, S., Paull, L., Trentini, M., Seto, M., and Li, H., "Map merging
       using probabilistic generalized Voronoi diagrams", IROS 2012, eqs. (4)-(8).
    """
    blurred = propagate(b.probability(), np.eye(3), covariance, b.shape, center=center, cval=0.5)
    blurred -= np.float32(0.5)
    return blurred


def place_blurred(blurred: np.ndarray, resolution: float, matrix: np.ndarray) -> Layer:
    """A map blurred in its own frame (:func:`blur_in_own_frame`) moved into a base map's
    pixels by ``matrix`` (bilinear), eq. (1): the step of :func:`warp_layer` that depends
    on the placement.

    Parameters
    ----------
    blurred : numpy.ndarray
        The map's blurred probabilities minus 0.5, in its own pixels.
    resolution : float
        Metres per cell of the map.
    matrix : numpy.ndarray
        3x3, map pixel -> base pixel.

    Returns
    -------
    Layer
        Cut to the cells the map knows after the blur, as :func:`warp_layer`.

    Raises
    ------
    ValueError
        If ``matrix`` is not a finite 3x3 array.
    """
    matrix = finite_3x3(matrix, "matrix")
    lo, hi = footprint(blurred.shape, matrix)
    to_box = np.array([[1.0, 0.0, -lo[0]], [0.0, 1.0, -lo[1]], [0.0, 0.0, 1.0]])
    shape = (int(hi[1] - lo[1] + 1), int(hi[0] - lo[0] + 1))
    moved = warp(blurred, to_box @ matrix, shape, order=1, cval=0.0).astype(np.float32)
    rows, cols = np.flatnonzero(moved.any(axis=1)), np.flatnonzero(moved.any(axis=0))
    r0, c0 = (int(rows[0]), int(cols[0])) if rows.size else (0, 0)
    r1, c1 = (int(rows[-1]) + 1, int(cols[-1]) + 1) if rows.size else (0, 0)
    probability = moved[r0:r1, c0:c1] + np.float32(0.5)
    return Layer(
        probability_to_logodds(np.clip(probability, 0.0, 1.0)),
        (int(lo[0]) + c0, int(lo[1]) + r0),
        (int(lo[0]), int(lo[1]), int(hi[0]), int(hi[1])),
        float(resolution),
    )


def warp_layer(
    b: Grid,
    matrix: np.ndarray,
    covariance: np.ndarray,
    center: tuple[float, float] = (0.0, 0.0),
    propagation: bool = True,
) -> Layer:
    """Map B moved into a base map's pixels and blurred by the transform's covariance, eq. (8).

    The warp step of :func:`fuse_layers`.  The blur is the same kernel in B's own frame
    whatever B's placement (:func:`own_frame_covariance`), so it is applied there first
    (:func:`blur_in_own_frame`) and the blurred map is then moved (:func:`place_blurred`):
    a caller that keeps the blurred map moves it again without blurring it again.  The
    layer is a function of ``b``, ``matrix`` and ``covariance`` alone, and placing it on a
    canvas that grew is a shift by whole cells, exact.  (:func:`fuse_maps` warps first
    and blurs on the two maps' canvas instead: the two differ by the bilinear read's
    rounding, and in cells within the blur's reach of B's edge, which this blur does not
    cross.)

    Parameters
    ----------
    b : Grid
        The map to move.
    matrix : numpy.ndarray
        3x3, B pixel -> base pixel.
    covariance : numpy.ndarray
        3x3 over ``(tx px, ty px, psi rad)`` of ``matrix``, eq. (3), as in :func:`fuse_maps`.
    center : tuple of float, optional
        B pixel about which the heading error acts, as in :func:`fuse_maps`.
    propagation : bool, optional
        False: B is only warped (bilinear); ``covariance`` is not used.

    Returns
    -------
    Layer
        Cut to the cells B knows after the blur: the combine leaves every other cell of
        the base as it was, eq. (33) adding 0.

    Raises
    ------
    ValueError
        If ``matrix`` is not a finite 3x3 array, or ``covariance`` is not a finite,
        symmetric, positive semi-definite 3x3 array.

    References
    ----------
    .. [1] Saeedi, S., Paull, L., Trentini, M., Seto, M., and Li, H., "Map merging
       using probabilistic generalized Voronoi diagrams", IROS 2012, eqs. (3)-(8).
    """
    cov = own_frame_covariance(matrix, covariance if propagation else np.zeros((3, 3)))
    return place_blurred(blur_in_own_frame(b, cov, center), b.resolution, matrix)


def fuse_layers(base: Grid, layers: Sequence[Layer]) -> Grid:
    """Fuse layers into ``base`` one after another, in the order given, eqs. (33)-(37).

    The combine step after :func:`warp_layer`.  The canvas is the smallest one that holds
    the base and every layer's ``bounds`` whole, so it depends only on the set of maps,
    not on the order they are fused in; each layer is fused where it lies, cells outside
    it staying as they were (eq. (33) adds 0 there).  The entropy filter (37) judges each
    layer against the map so far, so callers pass a fixed order (:func:`fuse_many`).

    Parameters
    ----------
    base : Grid
        The base map; the layers are in its pixel frame.
    layers : sequence of Layer
        At the base's resolution.

    Returns
    -------
    Grid
        In the base's frame, shifted by whole cells to hold every map; ``base`` itself
        when there is no layer.

    Raises
    ------
    ValueError
        If a layer's resolution is not the base's.

    References
    ----------
    .. [1] Saeedi, S., Paull, L., Trentini, M., Seto, M., and Li, H., "Map merging
       using probabilistic generalized Voronoi diagrams", IROS 2012, eqs. (33)-(37).
    """
    if not layers:
        return base
    for layer in layers:
        if not np.isclose(base.resolution, layer.resolution, rtol=1e-6, atol=0.0):
            raise ValueError(
                f"resolutions differ ({base.resolution} vs {layer.resolution}); resample the layer"
            )
    h, w = base.shape
    bounds = np.array([(0, 0, w - 1, h - 1), *(layer.bounds for layer in layers)])
    x0, y0 = bounds[:, :2].min(axis=0)
    x1, y1 = bounds[:, 2:].max(axis=0)
    canvas = np.zeros((y1 - y0 + 1, x1 - x0 + 1), dtype=np.float32)
    canvas[-y0 : h - y0, -x0 : w - x0] = base.logodds
    for layer in layers:
        x, y = layer.corner[0] - x0, layer.corner[1] - y0
        lh, lw = layer.logodds.shape
        view = canvas[y : y + lh, x : x + lw]
        view[...] = fuse(view, layer.logodds)
    return Grid(canvas, base.resolution, _canvas_origin(base, int(x0), int(y1)))


def _moved_logodds(
    b: Grid,
    matrix: np.ndarray,
    covariance: np.ndarray,
    shape: tuple[int, int],
    center: tuple[float, float],
) -> np.ndarray:
    """B's log-odds moved by ``matrix`` onto ``shape`` and blurred by ``covariance``, eq. (8)
    (:func:`pgvd.uncertainty.propagate` on B's probabilities); unknown outside B."""
    moved = propagate(b.probability(), matrix, covariance, shape, center=center, cval=0.5)
    return probability_to_logodds(np.clip(moved, 0.0, 1.0))


def _canvas_origin(a: Grid, x0: int, y1: int) -> tuple[float, float, float]:
    """The origin of a canvas whose first column is A's pixel column ``x0`` and whose last
    row is A's pixel row ``y1``: the metric pose of its lower-left corner, so that A's cells
    keep their metric positions."""
    corner = pixel_to_world(a, [[x0 - 0.5, y1 + 0.5]])[0]
    return (float(corner[0]), float(corner[1]), a.origin[2])
