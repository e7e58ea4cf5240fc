"""The occupancy grid in log-odds, eq. (9), and the one place where frames meet.

Pixel frame (used everywhere in ``pgvd``): ``x`` is the column, ``y`` is the
row, row 0 is the top row of the image as stored in a PGM/PNG, and cell
centres sit at integer coordinates.  A relative transform is a 3x3
homogeneous matrix ``M`` with ``[xa, ya, 1]^T = M [xb, yb, 1]^T``.

Metric frame (ROS ``map_server``): ``origin`` is the pose of the lower-left
cell's outer corner and metric ``y`` points up.  :func:`pixel_to_world` and
:func:`world_to_pixel` are the only conversions between the two.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: Log-odds are clipped to this magnitude so that p never reaches exactly 0 or 1.
LOGODDS_LIMIT = 20.0
#: Cells converted per pass by logodds_to_probability (fits a CPU cache; speed only).
_CHUNK = 1 << 15
#: Cell sizes (m) a map may have.  Occupancy grids run from about a centimetre to half a
#: metre; outside these bounds a cell size is a unit slip (millimetres written as metres)
#: or hostile, and resampling or pooling such a map asks for filter windows and canvases of
#: absurd size (a 1e9 m cell hung ``pgvd merge``; 1e-320 overflowed its arithmetic).
CELL_SIZE_RANGE = (1e-3, 1.0)


@dataclass(frozen=True)
class Grid:
    """An occupancy grid: log-odds per cell, eq. (9); 0 means unknown.

    Attributes
    ----------
    logodds : numpy.ndarray
        (H, W) float32 log-odds, row 0 at the top of the image.
    resolution : float
        Metres per cell, > 0.
    origin : tuple of float
        ``(x, y, yaw)`` of the lower-left cell corner in metres/radians (ROS).

    Raises
    ------
    ValueError
        If ``logodds`` is not 2-D or ``resolution`` is not a positive number.

    References
    ----------
    .. [1] Saeedi, S., Paull, L., Trentini, M., Seto, M., and Li, H., "Map merging
       using probabilistic generalized Voronoi diagrams", IROS 2012, eq. (9).
    """

    logodds: np.ndarray
    resolution: float = 0.05
    origin: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def __post_init__(self) -> None:
        if self.logodds.ndim != 2:
            raise ValueError(f"a grid must be 2-D, got shape {self.logodds.shape}")
        if not np.isfinite(self.resolution) or self.resolution <= 0:
            raise ValueError(f"resolution must be > 0, got {self.resolution}")

    @property
    def shape(self) -> tuple[int, int]:
        return self.logodds.shape  # type: ignore[return-value]

    def probability(self) -> np.ndarray:
        """Occupancy probability per cell, the inverse of eq. (9)."""
        return logodds_to_probability(self.logodds)

    @classmethod
    def from_probability(
        cls,
        p: np.ndarray,
        resolution: float = 0.05,
        origin: tuple[float, float, float] = (0.0, 0.0, 0.0),
    ) -> Grid:
        """Build a grid from occupancy probabilities (0.5 = unknown), eq. (9)."""
        return cls(probability_to_logodds(p), resolution, origin)


def check_cell_size(resolution: float) -> None:
    """Refuse a cell size outside :data:`CELL_SIZE_RANGE`.

    Parameters
    ----------
    resolution : float
        Metres per cell.

    Raises
    ------
    ValueError
        Naming the cell size and the range.
    """
    lo, hi = CELL_SIZE_RANGE
    if not lo <= resolution <= hi:  # NaN fails too
        raise ValueError(
            f"a cell size of {resolution:g} m is outside {lo:g}-{hi:g} m, the range of "
            "occupancy grids (is it in metres?)"
        )


def probability_to_logodds(p: np.ndarray) -> np.ndarray:
    """Eq. (9): ``l = log(p / (1 - p))``, clipped to +-LOGODDS_LIMIT, as float32.

    Parameters
    ----------
    p : numpy.ndarray
        Occupancy probabilities in [0, 1]; 0.5 (unknown) gives exactly 0.

    Returns
    -------
    numpy.ndarray
        float32 log-odds of the shape of ``p``.

    References
    ----------
    .. [1] Saeedi, S., Paull, L., Trentini, M., Seto, M., and Li, H., "Map merging
       using probabilistic generalized Voronoi diagrams", IROS 2012, eq. (9).
    """
    p = np.asarray(p, dtype=np.float64)
    eps = 1.0 / (1.0 + np.exp(LOGODDS_LIMIT))
    p = np.clip(p, eps, 1.0 - eps)
    return np.log(p / (1.0 - p)).astype(np.float32)


def logodds_to_probability(lo: np.ndarray) -> np.ndarray:
    """Inverse of eq. (9) (the paper's eq. (34)): ``p = 1 - 1 / (1 + exp(l))``.

    Parameters
    ----------
    lo : numpy.ndarray
        Log-odds.

    Returns
    -------
    numpy.ndarray
        float32 occupancy probabilities of the shape of ``lo``.

    References
    ----------
    .. [1] Saeedi, S., Paull, L., Trentini, M., Seto, M., and Li, H., "Map merging
       using probabilistic generalized Voronoi diagrams", IROS 2012, eqs. (9), (34).
    """
    # in float32, in place, a cache-sized piece at a time: float32's SIMD exp is about 4x
    # faster than float64's (0.03 s instead of 0.13 s at 2500^2), no full-size temporaries,
    # and p within 3.5 float32 ulps of exact for float32 log-odds
    # (tests/test_grid_probability.py); float64 log-odds are rounded to float32 first.
    # Below about -88.7 float32's exp overflows to inf and p to 0, less than 3e-39 from
    # the true p; log-odds beyond float32's range become +-inf, p 0 or 1.
    with np.errstate(over="ignore"):
        flat = np.asarray(lo, dtype=np.float32).reshape(-1)
        out = np.empty(flat.size, np.float32)
        for start in range(0, flat.size, _CHUNK):
            p = out[start : start + _CHUNK]
            np.negative(flat[start : start + _CHUNK], out=p)
            np.exp(p, out=p)
            p += 1.0
            np.reciprocal(p, out=p)
    return out.reshape(np.shape(lo))


def pixel_to_world(grid: Grid, xy: np.ndarray) -> np.ndarray:
    """Map pixel coordinates of ``grid`` (x = column, y = row) to metric coordinates.

    Parameters
    ----------
    grid : Grid
        The map whose resolution, height and ROS ``origin`` define the frames.
    xy : numpy.ndarray
        (N, 2) or (2,) pixel coordinates.

    Returns
    -------
    numpy.ndarray
        (N, 2) metric coordinates (ROS map frame, y up).
    """
    xy = np.atleast_2d(np.asarray(xy, dtype=np.float64))
    h = grid.shape[0]
    ox, oy, yaw = grid.origin
    local = np.column_stack(
        [(xy[:, 0] + 0.5) * grid.resolution, (h - 1 - xy[:, 1] + 0.5) * grid.resolution]
    )
    c, s = np.cos(yaw), np.sin(yaw)
    return local @ np.array([[c, s], [-s, c]]) + np.array([ox, oy])


def world_to_pixel(grid: Grid, pts: np.ndarray) -> np.ndarray:
    """Inverse of :func:`pixel_to_world`: metric coordinates to pixel coordinates.

    Parameters
    ----------
    grid : Grid
        The map whose resolution, height and ROS ``origin`` define the frames.
    pts : numpy.ndarray
        (N, 2) or (2,) metric coordinates.

    Returns
    -------
    numpy.ndarray
        (N, 2) pixel coordinates (x = column, y = row).
    """
    pts = np.atleast_2d(np.asarray(pts, dtype=np.float64))
    h = grid.shape[0]
    ox, oy, yaw = grid.origin
    c, s = np.cos(yaw), np.sin(yaw)
    local = (pts - np.array([ox, oy])) @ np.array([[c, -s], [s, c]])
    return np.column_stack(
        [local[:, 0] / grid.resolution - 0.5, h - 1 - (local[:, 1] / grid.resolution - 0.5)]
    )


def world_pose_to_pixel_matrix(grid: Grid) -> np.ndarray:
    """3x3 homogeneous matrix from metric ``[x, y, 1]`` to this grid's pixel ``[x, y, 1]``."""
    h = grid.shape[0]
    ox, oy, yaw = grid.origin
    c, s = np.cos(yaw), np.sin(yaw)
    r = grid.resolution
    world_to_local = np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]]) @ np.array(
        [[1.0, 0.0, -ox], [0.0, 1.0, -oy], [0.0, 0.0, 1.0]]
    )
    local_to_pixel = np.array([[1 / r, 0.0, -0.5], [0.0, -1 / r, h - 0.5], [0.0, 0.0, 1.0]])
    return local_to_pixel @ world_to_local


def relative_matrix(a: Grid, b: Grid) -> np.ndarray:
    """The true B-pixel -> A-pixel matrix of two grids that share one metric frame.

    This is the ground truth for map pairs rendered in one world frame
    (``*_split_gt``), whose offset is the difference of their YAML origins.

    Parameters
    ----------
    a, b : Grid
        The two maps; their ``origin`` place them in the shared metric frame.

    Returns
    -------
    numpy.ndarray
        3x3 homogeneous matrix, B pixel -> A pixel.
    """
    return world_pose_to_pixel_matrix(a) @ np.linalg.inv(world_pose_to_pixel_matrix(b))


def map_frame_pose(a: Grid, b: Grid, matrix: np.ndarray) -> tuple[float, float, float]:
    """Where a B-pixel -> A-pixel ``matrix`` puts B's map frame in A's: ``(x, y, yaw)``.

    The frames are the grids' ROS map frames (REP 105: the YAML ``origin`` places the
    lower-left cell, y points up): ``(x, y)`` in metres and ``yaw`` in radians are the pose
    of B's map frame in A's, what tf2's ``static_transform_publisher`` takes with A's map as
    the parent frame and B's as the child.  Two maps rendered in one world frame (whose
    :func:`relative_matrix` is the matrix) give ``(0, 0, 0)``.

    Parameters
    ----------
    a, b : Grid
        The two maps, B as ``matrix`` reads its pixels (its resolution may differ from A's
        when ``matrix`` includes the scale between them).
    matrix : numpy.ndarray
        3x3, B pixel -> A pixel (eqs. (1)-(2)).

    Returns
    -------
    tuple of float
        ``(x, y, yaw)``.
    """
    t = np.linalg.inv(world_pose_to_pixel_matrix(a)) @ matrix @ world_pose_to_pixel_matrix(b)
    return float(t[0, 2]), float(t[1, 2]), float(np.arctan2(t[1, 0], t[0, 0]))


def map_frame_covariance(
    a: Grid, b: Grid, matrix: np.ndarray, covariance: np.ndarray
) -> np.ndarray:
    """The covariance of :func:`map_frame_pose`: ``(x m, y m, yaw rad)``, from the merge's.

    The merge's covariance (eq. (3)) is over ``(tx px, ty px, psi rad)`` of ``matrix``
    (:func:`matrix_to_pose`); it is carried to the map frames by the Jacobian of
    :func:`map_frame_pose` in those three, ``J Sigma J^T``.  The pose is linear in the
    translation, so central differences give J to rounding, and in the heading to
    ``O(h^2)`` with ``h`` 1 microradian.  The 3x3 is what a ROS ``PoseWithCovariance`` holds
    at rows and columns x, y and yaw (0, 1 and 5 of its 6x6).

    Parameters
    ----------
    a, b : Grid
        The two maps, B in the pixels ``matrix`` and ``covariance`` refer to.
    matrix : numpy.ndarray
        3x3 rigid, B pixel -> A pixel.
    covariance : numpy.ndarray
        3x3 over ``(tx px, ty px, psi rad)`` of ``matrix``.

    Returns
    -------
    numpy.ndarray
        3x3 over ``(x m, y m, yaw rad)``.

    Raises
    ------
    ValueError
        If ``matrix`` is not rigid (a scale between the maps' cells: give B at A's cells,
        as the merge does, where the covariance is defined).
    """
    r = np.asarray(matrix, dtype=np.float64)[:2, :2]
    if not np.allclose(r @ r.T, np.eye(2), atol=1e-6):
        raise ValueError("map_frame_covariance needs a rigid B pixel -> A pixel matrix")
    psi, tx, ty = matrix_to_pose(matrix)
    params = np.array([tx, ty, psi])
    jac = np.empty((3, 3))
    for k, h in enumerate((1.0, 1.0, 1e-6)):
        step = np.zeros(3)
        step[k] = h
        up, down = (
            np.array(map_frame_pose(a, b, rigid_matrix(q[2], q[0], q[1])))
            for q in (params + step, params - step)
        )
        diff = up - down
        diff[2] = np.angle(np.exp(1j * diff[2]))
        jac[:, k] = diff / (2 * h)
    cov = jac @ np.asarray(covariance, dtype=np.float64) @ jac.T
    return 0.5 * (cov + cov.T)


def finite_3x3(value: object, what: str) -> np.ndarray:
    """``value`` as a float64 3x3 array (a transform of eq. (1), a covariance of eq. (3)).

    Raises
    ------
    ValueError
        Naming ``what``, if it is not 3x3 or holds NaN or infinite values.
    """
    m = np.asarray(value, dtype=np.float64)
    if m.shape != (3, 3):
        raise ValueError(f"{what} must be a finite 3x3 array, got shape {m.shape}")
    if not np.isfinite(m).all():
        raise ValueError(f"{what} must be a finite 3x3 array, got NaN or infinite values")
    return m


def rigid_matrix(psi: float, tx: float, ty: float) -> np.ndarray:
    """Eqs. (1)-(2) as a 3x3 homogeneous matrix in the pixel frame.

    ``R_psi = [[cos, sin], [-sin, cos]]`` as in eq. (2); with rows pointing
    down, a positive ``psi`` turns the image counter-clockwise on screen.

    Parameters
    ----------
    psi : float
        Heading, radians.
    tx, ty : float
        Translation ``T`` of eq. (1), pixels.

    Returns
    -------
    numpy.ndarray
        3x3 homogeneous matrix ``[[R_psi, T], [0, 0, 1]]``.

    References
    ----------
    .. [1] Saeedi, S., Paull, L., Trentini, M., Seto, M., and Li, H., "Map merging
       using probabilistic generalized Voronoi diagrams", IROS 2012, eqs. (1)-(2).
    """
    c, s = np.cos(psi), np.sin(psi)
    return np.array([[c, s, tx], [-s, c, ty], [0.0, 0.0, 1.0]])


def heading(m: np.ndarray) -> float:
    """The rotation ``psi`` of a rigid pixel-frame matrix: the one place it is read.

    Read as :func:`rigid_matrix` writes it, ``R_psi = [[cos, sin], [-sin, cos]]``
    of eq. (2): ``psi = atan2(m[0, 1], m[0, 0])``.  Rows point down in the
    pixel frame, so a positive ``psi`` turns counter-clockwise on screen, and
    the angle ``atan2(m[1, 0], m[0, 0])`` a y-up (metric) frame reads from the
    same matrix is ``-psi``.

    Parameters
    ----------
    m : numpy.ndarray
        3x3 rigid homogeneous matrix in the convention of eqs. (1)-(2).

    Returns
    -------
    float
        ``psi`` in radians, in ``[-pi, pi]``.

    References
    ----------
    .. [1] Saeedi, S., Paull, L., Trentini, M., Seto, M., and Li, H., "Map merging
       using probabilistic generalized Voronoi diagrams", IROS 2012, eq. (2).
    """
    return float(np.arctan2(m[0, 1], m[0, 0]))


def matrix_to_pose(m: np.ndarray) -> tuple[float, float, float]:
    """Inverse of :func:`rigid_matrix`: ``(psi, tx, ty)`` of a rigid 3x3 matrix.

    Parameters
    ----------
    m : numpy.ndarray
        3x3 rigid homogeneous matrix in the convention of eqs. (1)-(2).

    Returns
    -------
    tuple of float
        ``(psi, tx, ty)``: heading in radians and translation in pixels.
    """
    return heading(m), float(m[0, 2]), float(m[1, 2])
