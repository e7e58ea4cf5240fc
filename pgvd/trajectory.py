"""A robot's route through the free space of a map image, as scan poses.

The route visits goals spread over the reachable free space (farthest-point
sampling, so that the whole building is explored), in nearest-neighbour
order, along least-cost paths that keep away from walls (cost grows as the
clearance shrinks, so the robot drives down the middle of corridors).  The
path is smoothed over :data:`SMOOTHING` metres and sampled every
:data:`SCAN_SPACING` metres of travel; the robot faces its direction of
travel, as a robot exploring with a forward-looking scanner does.
"""

from __future__ import annotations

import itertools

import numpy as np
from scipy import ndimage
from skimage.graph import MCP_Geometric

from pgvd.carmen import LaserScan
from pgvd.grid import Grid
from pgvd.lidar import LMS200, RayCaster, scan_at

#: Robot radius plus margin, metres: the path keeps at least this far from walls and unknown.
CLEARANCE = 0.3
#: One goal per this many square metres of reachable free space.
AREA_PER_GOAL = 25.0
GOALS = (12, 60)
#: Gaussian smoothing of the path (sigma, metres) and the travel between two scans (metres).
SMOOTHING = 0.3
SCAN_SPACING = 0.25
#: Planning grid cell size, metres (coarser than the map to keep the planner quick).
PLAN_RESOLUTION = 0.1


def reachable(caster: RayCaster, clearance: float = CLEARANCE) -> tuple[np.ndarray, int]:
    """The largest connected free region with ``clearance`` on a coarse planning grid.

    Returns the boolean mask of that region and the pooling factor from map cells.
    """
    k = max(1, round(PLAN_RESOLUTION / caster.resolution))
    blocked = caster.wall | caster.unknown
    h, w = (-(-blocked.shape[0] // k)) * k, (-(-blocked.shape[1] // k)) * k
    padded = np.ones((h, w), bool)
    padded[: blocked.shape[0], : blocked.shape[1]] = blocked
    coarse = padded.reshape(h // k, k, w // k, k).any(axis=(1, 3))
    free = ndimage.distance_transform_edt(~coarse) * (k * caster.resolution) >= clearance
    labels, n = ndimage.label(free)
    if n == 0:
        raise ValueError("the map has no free space wide enough for the robot")
    sizes = ndimage.sum_labels(free, labels, np.arange(1, n + 1))
    return labels == 1 + int(np.argmax(sizes)), k


def _goals(free: np.ndarray, n: int, rng: np.random.Generator) -> np.ndarray:
    """``n`` cells of ``free`` by farthest-point sampling from a random first one, (row, col)."""
    cells = np.argwhere(free)
    chosen = [cells[rng.integers(len(cells))]]
    dist = np.full(len(cells), np.inf)
    for _ in range(n - 1):
        dist = np.minimum(dist, np.hypot(*(cells - chosen[-1]).T))
        chosen.append(cells[int(np.argmax(dist))])
    return np.array(chosen)


def _tour_order(goals: np.ndarray) -> list[int]:
    """Nearest-neighbour order through the goals, from the first."""
    left = list(range(1, len(goals)))
    order = [0]
    while left:
        d = [np.hypot(*(goals[i] - goals[order[-1]])) for i in left]
        order.append(left.pop(int(np.argmin(d))))
    return order


def route(free: np.ndarray, cell_m: float, goals: np.ndarray) -> np.ndarray:
    """Least-cost path (row, col) through ``goals`` in order, staying centred in ``free``."""
    clearance = ndimage.distance_transform_edt(free) * cell_m
    cost = np.where(free, 1.0 + (1.0 / np.maximum(clearance, 1e-3)) ** 2, np.inf)
    path = [goals[0][None, :]]
    for a, b in itertools.pairwise(goals):
        mcp = MCP_Geometric(cost)
        mcp.find_costs([tuple(a)], [tuple(b)])
        path.append(np.array(mcp.traceback(tuple(b)))[1:])
    return np.concatenate(path)


def poses_along(path_world: np.ndarray) -> np.ndarray:
    """Smoothed ``x, y, theta`` poses every :data:`SCAN_SPACING` metres along a polyline."""
    seg = np.hypot(*np.diff(path_world, axis=0).T)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    keep = np.concatenate([[True], seg > 0])
    s, path_world = s[keep], path_world[keep]
    fine = np.arange(0.0, s[-1], 0.05)
    xy = np.column_stack([np.interp(fine, s, path_world[:, i]) for i in (0, 1)])
    xy = ndimage.gaussian_filter1d(xy, SMOOTHING / 0.05, axis=0, mode="nearest")
    d = np.gradient(xy, axis=0)
    theta = np.arctan2(d[:, 1], d[:, 0])
    # Resample by travelled distance along the smoothed path (it is shorter than the raw one).
    travel = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(xy, axis=0).T))])
    idx = np.searchsorted(travel, np.arange(0.0, travel[-1], SCAN_SPACING))
    return np.column_stack([xy[idx], theta[idx]])


def tour(caster: RayCaster, rng: np.random.Generator) -> np.ndarray:
    """Scan poses (world ``x, y, theta``) of a robot exploring the map's reachable free space."""
    free, k = reachable(caster)
    cell_m = k * caster.resolution
    area = free.sum() * cell_m**2
    n = int(np.clip(round(area / AREA_PER_GOAL), *GOALS))
    goals = _goals(free, n, rng)
    goals = goals[_tour_order(goals)]
    rc = route(free, cell_m, goals).astype(np.float64)
    # Coarse cell (row, col) -> map pixel (x, y) -> world metres.
    px = np.column_stack([rc[:, 1] * k + (k - 1) / 2.0, rc[:, 0] * k + (k - 1) / 2.0])
    return poses_along(caster.pixel_to_world(px))


#: Fewest scan poses a drive must have: a shorter one leaves no map worth registering.
MIN_DRIVE_POSES = 20


def drive(grid: Grid, seed: int, unknown_blocks: bool = False) -> list[LaserScan]:
    """A simulated robot's run through a map image: a :func:`tour`, scanned by the LMS200.

    Parameters
    ----------
    grid : the map image; its walls are the world the scanner sees (:class:`RayCaster`),
        placed in the image's own metric frame (origin at its lower-left corner, yaw 0).
    seed : seed of the tour's goals and of the range noise: the same seed, the same run.
    unknown_blocks : unknown cells are walls too (see :class:`RayCaster`).

    Returns
    -------
    list of LaserScan
        One scan per pose, :data:`SCAN_SPACING` metres of travel apart, stamped one second
        apart, each with its true pose.

    Raises
    ------
    ValueError
        A map with no free space wide enough for the robot, or too little to drive
        :data:`MIN_DRIVE_POSES` scans through.
    """
    caster = RayCaster(Grid(grid.logodds, grid.resolution), unknown_blocks=unknown_blocks)
    rng = np.random.default_rng(seed)
    poses = tour(caster, rng)
    if len(poses) < MIN_DRIVE_POSES:
        raise ValueError(
            f"the map's free space is too small to drive: {len(poses) * SCAN_SPACING:.1f} m "
            f"of route, at least {MIN_DRIVE_POSES * SCAN_SPACING:.1f} m needed"
        )
    return scan_at(caster, poses, rng, LMS200)
