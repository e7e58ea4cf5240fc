"""A simulated 2-D laser scanner over a map image: the map's walls are the world it sees.

The scanner is modelled on the SICK LMS200 that recorded the intel and
freiburg-079 logs: 181 beams over 180 degrees (1 degree apart), ranges up to
80 m, Gaussian range noise of sigma 0.01 m (the LMS200 technical description
gives a systematic error of +-15 mm and a statistical error of about 5 mm,
1 sigma, in its mm mode; 0.01 m is their order).  A beam that reaches no wall
-- it leaves the image, enters a cell the map marks unknown (glass, an open
door to a room nobody mapped) or runs past the maximum range -- returns the
logs' "no return" value, which :mod:`pgvd.integrate` ignores as it does in the
real logs.

Rays are cast in the image's pixel frame (``x`` = column, ``y`` = row, cell
centres at integers) by sphere tracing on the Euclidean distance to the
nearest wall cell, then bisected to the wall's edge.  Walls are first closed
to 4-connectivity (a diagonal step of a wall gets one of its two corner
cells), which gives every wall a width of at least ``1/sqrt(2)`` cells across
any line: a ray that samples at most :data:`MIN_STEP` cells apart cannot slip
through a diagonal wall.

The simulated log's world frame is the image's own metric frame with the
origin at its lower-left corner and yaw 0 (``Grid.origin = (0, 0, 0)``); a
pair generator puts every map in a random frame of its own anyway.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from pgvd.carmen import LaserScan
from pgvd.grid import Grid

#: Occupancy probability above which a map cell is a wall (map_server's occupied_thresh).
WALL = 0.65
#: Cells within this of 0.5 are unknown.
UNKNOWN_BAND = 0.05
#: Smallest sphere-tracing step (cells): below the 1/sqrt(2) width of a closed wall.
MIN_STEP = 0.3
#: Sphere-tracing steps are shortened by this (cells): a sample may sit up to
#: sqrt(2)/2 from its cell centre, and a wall square reaches sqrt(2)/2 beyond its centre.
STEP_SLACK = np.sqrt(2.0) + 0.01
#: Bisection rounds that place a hit on the wall edge (MIN_STEP / 2**6 < 0.005 cells).
BISECTIONS = 6


@dataclass(frozen=True)
class Scanner:
    """A planar laser scanner.

    Attributes
    ----------
    beams : number of beams, evenly spread over ``fov``.
    fov : field of view, radians.
    max_range : metres; farther walls give no return.
    range_sigma : standard deviation of the Gaussian range noise, metres.
    no_return : the range reported when a beam returns nothing (the logs' marker,
        81.91 m in freiburg-079).
    """

    beams: int = 181
    fov: float = np.pi
    max_range: float = 80.0
    range_sigma: float = 0.01
    no_return: float = 81.91

    def __post_init__(self) -> None:
        if self.beams < 1 or not 0 < self.fov <= 2 * np.pi:
            raise ValueError(f"need beams >= 1 and 0 < fov <= 2 pi, got {self.beams}, {self.fov}")
        if not 0 < self.max_range < self.no_return or self.range_sigma < 0:
            raise ValueError("need 0 < max_range < no_return and range_sigma >= 0")


#: The scanner of the development logs (see the module docstring).
LMS200 = Scanner()


def close_diagonals(wall: np.ndarray) -> np.ndarray:
    """Walls made 4-connected: where two wall cells touch only at a corner, fill one corner cell.

    The filled cell is the one on the row of the upper cell, so a diagonal wall
    becomes a staircase; this thickens diagonal walls by at most one cell.
    """
    out = wall.copy()
    # Down-right diagonal: (r, c) and (r+1, c+1) with both (r, c+1) and (r+1, c) free.
    dr = wall[:-1, :-1] & wall[1:, 1:] & ~wall[:-1, 1:] & ~wall[1:, :-1]
    out[:-1, 1:] |= dr
    # Down-left diagonal: (r, c+1) and (r+1, c) with both (r, c) and (r+1, c+1) free.
    dl = wall[:-1, 1:] & wall[1:, :-1] & ~wall[:-1, :-1] & ~wall[1:, 1:]
    out[:-1, :-1] |= dl
    return out


class RayCaster:
    """Casts beams against the walls of one map image.

    Parameters
    ----------
    grid : the map (any resolution); its walls are cells with probability > :data:`WALL`.
    unknown_blocks : unknown cells are walls too (for an image whose walls are the edge
        of its free space); otherwise a beam entering one returns nothing.
    """

    def __init__(self, grid: Grid, unknown_blocks: bool = False) -> None:
        p = grid.probability()
        self.resolution = float(grid.resolution)
        self.shape = p.shape
        unknown = np.abs(p - 0.5) < UNKNOWN_BAND
        wall = p > WALL
        if unknown_blocks:
            wall, unknown = wall | unknown, np.zeros_like(unknown)
        self.wall = close_diagonals(wall)
        self.unknown = unknown
        # Distance (cells) from every cell centre to the nearest wall cell centre.
        self.clear = ndimage.distance_transform_edt(~self.wall).astype(np.float32)

    def world_to_pixel(self, xy: np.ndarray) -> np.ndarray:
        """World metres (origin at the image's lower-left corner, y up) to pixel (x, y)."""
        xy = np.atleast_2d(xy)
        return np.column_stack(
            [xy[:, 0] / self.resolution - 0.5, self.shape[0] - 0.5 - xy[:, 1] / self.resolution]
        )

    def pixel_to_world(self, px: np.ndarray) -> np.ndarray:
        """Inverse of :meth:`world_to_pixel`."""
        px = np.atleast_2d(px)
        return np.column_stack(
            [(px[:, 0] + 0.5) * self.resolution, (self.shape[0] - 0.5 - px[:, 1]) * self.resolution]
        )

    def _lookup(self, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Flat index of the cell holding each point, and whether it is on the image."""
        col = np.rint(pts[:, 0]).astype(np.int64)
        row = np.rint(pts[:, 1]).astype(np.int64)
        inside = (col >= 0) & (col < self.shape[1]) & (row >= 0) & (row < self.shape[0])
        return np.where(inside, row * self.shape[1] + col, 0), inside

    def cast(self, origins: np.ndarray, angles: np.ndarray, max_range: float) -> np.ndarray:
        """Exact (noise-free) distance in metres to the first wall along every ray; inf if none.

        Parameters
        ----------
        origins : (N, 2) ray origins in world metres (see :meth:`world_to_pixel`).
        angles : (N,) ray directions, radians, counter-clockwise from world x.
        max_range : metres; rays reaching no wall within it, or entering an unknown
            cell or leaving the image first, give inf.
        """
        start = self.world_to_pixel(origins)
        # World y points up, pixel rows down.
        step_dir = np.column_stack([np.cos(angles), -np.sin(angles)])
        limit = max_range / self.resolution
        t = np.zeros(len(angles))
        out = np.full(len(angles), np.inf)
        wall, unknown, clear = self.wall.ravel(), self.unknown.ravel(), self.clear.ravel()
        active = np.arange(len(angles))
        prev = t.copy()
        while active.size:
            pts = start[active] + step_dir[active] * t[active, None]
            idx, inside = self._lookup(pts)
            hit = inside & wall[idx]
            lost = ~inside | (~hit & unknown[idx]) | (t[active] > limit)
            if hit.any():
                out[active[hit]] = self._bisect(start, step_dir, prev, t, active[hit])
            go = ~hit & ~lost
            active = active[go]
            prev[active] = t[active]
            t[active] += np.maximum(MIN_STEP, clear[idx[go]] - STEP_SLACK)
        out[out > limit] = np.inf
        return out * self.resolution

    def _bisect(
        self,
        start: np.ndarray,
        step_dir: np.ndarray,
        lo: np.ndarray,
        hi: np.ndarray,
        rays: np.ndarray,
    ) -> np.ndarray:
        """Distance (cells) at which each ray enters a wall cell, between ``lo`` and ``hi``."""
        a, b = lo[rays].copy(), hi[rays].copy()
        wall = self.wall.ravel()
        for _ in range(BISECTIONS):
            mid = 0.5 * (a + b)
            idx, inside = self._lookup(start[rays] + step_dir[rays] * mid[:, None])
            in_wall = inside & wall[idx]
            b = np.where(in_wall, mid, b)
            a = np.where(in_wall, a, mid)
        return b


def scan_at(
    caster: RayCaster,
    poses: np.ndarray,
    rng: np.random.Generator,
    scanner: Scanner = LMS200,
) -> list[LaserScan]:
    """One scan per pose (world ``x, y, theta``), with range noise and no-return markers.

    Beam ``i`` points at ``theta - fov / 2 + i * fov / (beams - 1)``, the
    convention of :class:`pgvd.carmen.LaserScan`; ``odom`` is the true pose.
    """
    poses = np.atleast_2d(np.asarray(poses, dtype=np.float64))
    rel = (
        np.zeros(1)
        if scanner.beams == 1
        else -scanner.fov / 2 + np.arange(scanner.beams) * (scanner.fov / (scanner.beams - 1))
    )
    angles = (poses[:, 2:3] + rel[None, :]).ravel()
    origins = np.repeat(poses[:, :2], scanner.beams, axis=0)
    ranges = caster.cast(origins, angles, scanner.max_range)
    ranges = ranges + rng.normal(0.0, scanner.range_sigma, ranges.shape)
    ranges = np.where(np.isfinite(ranges), np.maximum(ranges, 0.0), scanner.no_return)
    ranges = ranges.reshape(len(poses), scanner.beams).astype(np.float32)
    return [
        LaserScan(float(i), ranges[i], pose.copy(), pose.copy(), scanner.fov)
        for i, pose in enumerate(poses)
    ]
