"""Occupancy-grid mapping with known poses: laser scans ray-cast into log-odds, eq. (9).

A robot's local map is the log-odds sum of an inverse sensor model over its
scans (the standard binary Bayes filter, which is what eq. (9) encodes and
what the fusion (33) adds across robots).  Each map lives in its own metric
frame: a :class:`MapFrame` says how the log's world frame sits in it, so two
segments of one log rendered in two frames are two robots' maps with a known
true relative transform.

Rays are sampled with numpy at half-cell steps (no Bresenham loop); every cell
is updated at most once per scan, a hit cell wins over free-space passes of the
same scan, and the log-odds are clamped after every scan.  That makes
:func:`integrate` exactly the fold of :func:`integrate_scan` over the scans.
"""

from __future__ import annotations

import itertools
from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np

from pgvd.carmen import LaserScan
from pgvd.grid import Grid, heading

#: Rays are sampled at this fraction of a cell so that no crossed cell is skipped
#: except at the very corners.
SAMPLE_STEP = 0.5


@dataclass(frozen=True)
class InverseSensorModel:
    """Log-odds increments and clamps of the inverse sensor model.

    Attributes
    ----------
    l_occ : increment of the cell a beam ends in (> 0).
    l_free : increment of every cell a beam passes through (< 0).
    l_min, l_max : clamps of the accumulated log-odds, ``l_min < 0 < l_max``.
    max_range : metres; a range ``>= max_range`` is a free-space-only ray cut
        at ``max_range``, with no hit.
    no_return : metres; a range ``>= no_return`` is the logger's "no return"
        marker (81.83 m in intel, 81.91 m in freiburg-079, from glass, black
        surfaces or open space) and is ignored: casting it as free space would
        spray free cells through the windows.
    """

    l_occ: float = 0.85
    l_free: float = -0.4
    l_min: float = -2.0
    l_max: float = 3.5
    max_range: float = 20.0
    no_return: float = 80.0

    def __post_init__(self) -> None:
        if not (self.l_occ > 0 and self.l_free < 0):
            raise ValueError(f"need l_occ > 0 > l_free, got {self.l_occ}, {self.l_free}")
        if not (self.l_min < 0 < self.l_max):
            raise ValueError(f"need l_min < 0 < l_max, got {self.l_min}, {self.l_max}")
        if not (np.isfinite(self.max_range) and self.max_range > 0):
            raise ValueError(f"max_range must be > 0, got {self.max_range}")
        if not self.no_return > 0:
            raise ValueError(f"no_return must be > 0, got {self.no_return}")


@dataclass(frozen=True)
class MapFrame:
    """Where a map's canvas sits, relative to the log's world frame.

    Attributes
    ----------
    resolution : metres per cell.
    shape : ``(rows, cols)`` of the canvas.
    world_to_map : 3x3 SE(2) matrix from log-world metres to this map's metric frame.
    origin : ``(x, y)`` of the canvas' lower-left corner in the map's metric frame
        (the ROS ``origin``; the grid's yaw is 0 in its own frame).
    """

    resolution: float
    shape: tuple[int, int]
    world_to_map: np.ndarray = field(default_factory=lambda: np.eye(3))
    origin: tuple[float, float] = (0.0, 0.0)

    def __post_init__(self) -> None:
        if not (np.isfinite(self.resolution) and self.resolution > 0):
            raise ValueError(f"resolution must be > 0, got {self.resolution}")
        if len(self.shape) != 2 or min(self.shape) < 1:
            raise ValueError(f"shape must be two positive ints, got {self.shape}")
        m = np.asarray(self.world_to_map, dtype=np.float64)
        if m.shape != (3, 3) or not np.allclose(m[:2, :2] @ m[:2, :2].T, np.eye(2), atol=1e-9):
            raise ValueError("world_to_map must be a 3x3 SE(2) matrix")

    def empty(self) -> np.ndarray:
        """A zero (all unknown) float32 log-odds canvas of this frame's shape."""
        return np.zeros(self.shape, dtype=np.float32)

    def grid(self, logodds: np.ndarray) -> Grid:
        """Wrap a canvas of this frame as a :class:`~pgvd.grid.Grid`."""
        return Grid(logodds, self.resolution, (self.origin[0], self.origin[1], 0.0))


DEFAULT_MODEL = InverseSensorModel()


def se2(x: float, y: float, theta: float) -> np.ndarray:
    """3x3 homogeneous matrix of the planar pose ``(x, y, theta)`` (metric, y up)."""
    c, s = np.cos(theta), np.sin(theta)
    return np.array([[c, -s, x], [s, c, y], [0.0, 0.0, 1.0]])


def se2_pose(m: np.ndarray) -> tuple[float, float, float]:
    """Inverse of :func:`se2`: the planar pose ``(x, y, theta)`` of a metric SE(2) matrix.

    Metric ``y`` points up, so ``theta`` is the negative of the pixel-frame
    :func:`pgvd.grid.heading` of the same matrix.
    """
    return float(m[0, 2]), float(m[1, 2]), -heading(m)


def _rays(
    scan: LaserScan, world_to_map: np.ndarray, model: InverseSensorModel
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Sensor position, unit directions, usable lengths and hit flags in the map frame."""
    m = np.asarray(world_to_map, dtype=np.float64)
    sensor = m[:2, :2] @ scan.pose[:2] + m[:2, 2]
    ranges = scan.ranges.astype(np.float64)
    valid = ranges < model.no_return
    ranges = ranges[valid]
    angles = scan.beam_angles()[valid] + se2_pose(m)[2]
    hit = ranges < model.max_range
    length = np.where(hit, ranges, model.max_range)
    return sensor, np.column_stack([np.cos(angles), np.sin(angles)]), length, hit


def frame_for(
    scans: list[LaserScan],
    resolution: float = 0.05,
    transform: np.ndarray | None = None,
    margin: float = 1.0,
    model: InverseSensorModel = DEFAULT_MODEL,
) -> MapFrame:
    """The smallest canvas (plus ``margin`` metres) holding every ray of ``scans``.

    Parameters
    ----------
    scans : list of LaserScan
        The scans the map will be built from.
    resolution : float, optional
        Metres per cell.
    transform : numpy.ndarray, optional
        3x3 SE(2) from log-world metres to the map's metric frame (identity if None).
    margin : float, optional
        Unknown border in metres around the outermost ray end.
    model : InverseSensorModel, optional
        Its ``max_range`` caps the no-return rays.

    Returns
    -------
    MapFrame
        The canvas shape, resolution and placement.

    Raises
    ------
    ValueError
        If ``scans`` is empty.
    """
    if not scans:
        raise ValueError("frame_for needs at least one scan")
    transform = np.eye(3) if transform is None else np.asarray(transform, dtype=np.float64)
    points = []
    for scan in scans:
        sensor, direction, length, _ = _rays(scan, transform, model)
        points.append(sensor + direction * length[:, None])
        points.append(sensor[None, :])
    pts = np.concatenate(points)
    lo = pts.min(axis=0) - margin
    hi = pts.max(axis=0) + margin
    cols, rows = (np.ceil((hi - lo) / resolution).astype(int) + 1).tolist()
    return MapFrame(resolution, (rows, cols), transform, (float(lo[0]), float(lo[1])))


def _cells(frame: MapFrame, pts: np.ndarray) -> np.ndarray:
    """Flat indices of the cells holding points given in cells from the origin; -1 if off canvas."""
    rows, cols = frame.shape
    ij = np.floor(pts).astype(np.int64)
    col, row = ij[:, 0], rows - 1 - ij[:, 1]
    inside = (col >= 0) & (col < cols) & (row >= 0) & (row < rows)
    return np.where(inside, row * cols + col, -1)


def integrate_scan(
    logodds: np.ndarray,
    scan: LaserScan,
    frame: MapFrame,
    model: InverseSensorModel = DEFAULT_MODEL,
) -> tuple[slice, slice]:
    """Add one scan to a log-odds canvas in place (inverse sensor model, eq. (9)).

    Parameters
    ----------
    logodds : float32 C-contiguous canvas of ``frame.shape``, modified in place.
    scan : the scan, with its pose in the log's world frame.
    frame : the canvas' frame.
    model : increments and clamps.

    Returns
    -------
    ``(rows, cols)`` slices of the bounding box of the cells touched (empty
    slices if the scan misses the canvas), e.g. to send one scan's delta.
    """
    if logodds.shape != frame.shape or not logodds.flags.c_contiguous:
        raise ValueError(f"canvas must be C-contiguous of shape {frame.shape}, got {logodds.shape}")
    sensor, direction, length, hit = _rays(scan, frame.world_to_map, model)
    # Work in cell units from the canvas corner, in float32: ~10^5 samples per scan.
    sensor = ((sensor - np.asarray(frame.origin)) / frame.resolution).astype(np.float32)
    direction = direction.astype(np.float32)
    length = (length / frame.resolution).astype(np.float32)
    # Free samples at k * SAMPLE_STEP cells, k = 0 .. ceil(length / step) - 1, all beams at once.
    counts = np.ceil(length / SAMPLE_STEP).astype(np.int64)
    beam = np.repeat(np.arange(length.size), counts)
    k = np.arange(beam.size) - np.repeat(np.cumsum(counts) - counts, counts)
    dist = k.astype(np.float32) * np.float32(SAMPLE_STEP)
    free = _cells(frame, sensor + direction[beam] * dist[:, None])
    occ = _cells(frame, sensor + direction[hit] * length[hit, None])
    free = free[free >= 0]
    occ = occ[occ >= 0]
    touched = np.concatenate([free, occ])
    if touched.size == 0:
        return slice(0, 0), slice(0, 0)
    # Fancy-index assignment writes each repeated index once, which is exactly
    # "one update per cell per scan" without sorting; hits are written last so a
    # cell that is both passed through and hit gets only the hit increment.
    flat = logodds.reshape(-1)
    occ_before = flat[occ]
    flat[free] = np.clip(flat[free] + np.float32(model.l_free), model.l_min, model.l_max)
    flat[occ] = np.clip(occ_before + np.float32(model.l_occ), model.l_min, model.l_max)
    r, c = np.divmod(touched, frame.shape[1])
    return slice(int(r.min()), int(r.max()) + 1), slice(int(c.min()), int(c.max()) + 1)


StepNoise = Callable[[float, float, np.random.Generator], tuple[float, float, float]]
"""``(metres moved, radians turned, rng) -> (dx, dy, dtheta)``: the error of one odometry step."""


def rechain_poses(scans: list[LaserScan], step_noise: StepNoise, seed: int) -> list[LaserScan]:
    """The scans with their poses re-chained through noisy odometry steps.

    Each step between consecutive poses (in the robot frame) is composed with
    the error ``step_noise`` draws for it, so the drift grows along the
    segment as on a robot without loop closure; the first pose is kept.
    """
    if not scans:
        return []
    rng = np.random.default_rng(seed)
    current = se2(*scans[0].pose)
    out = [scans[0]]
    for prev, scan in itertools.pairwise(scans):
        step = np.linalg.inv(se2(*prev.pose)) @ se2(*scan.pose)
        dist = float(np.hypot(step[0, 2], step[1, 2]))
        turn = abs(se2_pose(step)[2])
        current = current @ step @ se2(*step_noise(dist, turn, rng))
        out.append(replace(scan, pose=np.array(se2_pose(current))))
    return out


def perturb_odometry(
    scans: list[LaserScan], odom_noise: tuple[float, float], seed: int = 0
) -> list[LaserScan]:
    """Re-chain the poses with extra odometry noise, as a robot without loop closure sees them.

    Each step gets zero-mean Gaussian noise (:func:`rechain_poses`):
    translation sigma ``odom_noise[0]`` metres per metre moved, heading sigma
    ``odom_noise[1]`` radians per radian turned plus per metre moved.
    """
    sigma_t, sigma_r = odom_noise
    if sigma_t < 0 or sigma_r < 0:
        raise ValueError(f"odometry noise must be >= 0, got {odom_noise}")

    def noise(dist: float, turn: float, rng: np.random.Generator) -> tuple[float, float, float]:
        dx, dy = rng.normal(0.0, sigma_t * dist, 2)
        return dx, dy, rng.normal(0.0, sigma_r * (turn + dist))

    return rechain_poses(scans, noise, seed)


def integrate(
    scans: list[LaserScan],
    frame: MapFrame,
    model: InverseSensorModel = DEFAULT_MODEL,
    odom_noise: tuple[float, float] | None = None,
    seed: int = 0,
) -> Grid:
    """Ray-cast all scans into a fresh log-odds grid in ``frame`` (eq. (9)).

    Parameters
    ----------
    scans : list of LaserScan
        The scans, in time order.
    frame : MapFrame
        Canvas and world-to-map transform (see :func:`frame_for`).
    model : InverseSensorModel, optional
        Inverse sensor model.
    odom_noise : tuple of float, optional
        Extra odometry noise, see :func:`perturb_odometry`.
    seed : int, optional
        Seed of that noise.

    Returns
    -------
    Grid
        Its ``origin`` makes :func:`pgvd.grid.pixel_to_world` return coordinates
        in the frame's metric frame.

    Raises
    ------
    ValueError
        If the odometry noise is negative.

    References
    ----------
    .. [1] Saeedi, S., Paull, L., Trentini, M., Seto, M., and Li, H., "Map merging
       using probabilistic generalized Voronoi diagrams", IROS 2012, eq. (9).
    """
    if odom_noise is not None:
        scans = perturb_odometry(scans, odom_noise, seed)
    logodds = frame.empty()
    for scan in scans:
        integrate_scan(logodds, scan, frame, model)
    return frame.grid(logodds)


def select_segment(scans: list[LaserScan], segment: tuple[float, float] | slice) -> list[LaserScan]:
    """The scans of a segment: a fraction range ``(start, stop)`` in [0, 1] or an index slice.

    Fractions are floored to indices, so ``(0.0, 0.55)`` of intel's 910 scans is
    its first 500 (the convention of the ``*_split_gt`` renders).
    """
    if isinstance(segment, slice):
        return scans[segment]
    start, stop = segment
    if not 0.0 <= start < stop <= 1.0:
        raise ValueError(f"segment fractions must satisfy 0 <= start < stop <= 1, got {segment}")
    n = len(scans)
    return scans[int(start * n) : int(stop * n)]
