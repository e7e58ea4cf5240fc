"""Where a map has known cells, coarsely: which pairs the accepted links place near each other.

Two robots of one component have a predicted relative pose (:func:`agent.worker.predict`).
The check of that prediction (:func:`agent.worker.verify_check`) rejects the pair when the
walls of one map cover fewer than ``min_overlap`` metres of the other's known space at the
predicted pose; where the two maps' known cells do not even come near each other, that is
certain without reading the maps: there is no evidence to check.  A fleet of N robots
holds about N(N-1)/2 pairs within one component, but each map overlaps only its
neighbours in the building, so testing footprints first leaves checks growing with the
robots rather than with the pairs.

A footprint is the map's known cells pooled to :data:`CELL_M` blocks, made once per
(robot, version) (:class:`FootprintCache`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.ndimage import binary_dilation

from pgvd.grid import Grid

#: Side of a footprint's block (m): coarse enough that a footprint is a few hundred blocks.
CELL_M = 1.0
#: How near two footprints must come for the pair to be checked (m): the check's basin
#: (:data:`pgvd.verify.BASIN_M`, 1 m), within which its refinement may move the pose, and
#: 1 m more for the error of a prediction composed over several links.
MARGIN_M = 2.0


@dataclass(frozen=True)
class Footprint:
    """The known cells of one map, pooled to blocks of ``block`` pixels.

    ``mask`` marks the blocks holding a known cell; ``near`` is ``mask`` grown by the
    margin (and half a block's diagonal for the other map's block centres) and padded by as
    much on every side, ``pad`` blocks; ``centres`` are the known blocks' centres (x, y) in
    the map's pixels.
    """

    block: int
    mask: np.ndarray
    near: np.ndarray
    pad: int
    centres: np.ndarray

    @classmethod
    def of(cls, grid: Grid, margin_m: float = MARGIN_M) -> Footprint:
        """The footprint of ``grid``'s known cells (log-odds not 0)."""
        block = max(1, round(CELL_M / grid.resolution))
        known = np.asarray(grid.logodds) != 0
        rows = -(-known.shape[0] // block)
        cols = -(-known.shape[1] // block)
        padded = np.zeros((rows * block, cols * block), dtype=bool)
        padded[: known.shape[0], : known.shape[1]] = known
        mask = padded.reshape(rows, block, cols, block).any(axis=(1, 3))
        # a block centre of the other map lies within half a block diagonal of its cells
        reach = margin_m / grid.resolution + block * math.sqrt(0.5)
        pad = math.ceil(reach / block)
        near = np.pad(mask, pad)
        if pad:
            near = binary_dilation(near, np.ones((2 * pad + 1, 2 * pad + 1), dtype=bool))
        r, c = np.nonzero(mask)
        centres = np.column_stack([(c + 0.5) * block - 0.5, (r + 0.5) * block - 0.5])
        return cls(block, mask, near, pad, centres)

    def comes_near(self, other: Footprint, matrix: np.ndarray) -> bool:
        """Whether ``other``'s known blocks, placed by ``matrix`` (other's pixels -> this
        map's pixels), come within the margin of this map's known blocks."""
        if not len(self.centres) or not len(other.centres):
            return False
        m = np.asarray(matrix, dtype=np.float64)
        placed = other.centres @ m[:2, :2].T + m[:2, 2]
        idx = np.floor((placed + 0.5) / self.block).astype(np.int64) + self.pad
        col, row = idx[:, 0], idx[:, 1]
        inside = (row >= 0) & (row < self.near.shape[0]) & (col >= 0) & (col < self.near.shape[1])
        return bool(self.near[row[inside], col[inside]].any())


class FootprintCache:
    """:class:`Footprint` per (robot, version): a map's is made once, and dropped when a newer
    version of its robot is asked for."""

    def __init__(self, margin_m: float = MARGIN_M) -> None:
        self.margin_m = margin_m
        self._held: dict[str, tuple[int, Footprint]] = {}

    def get(self, robot: str, version: int, grid: Grid) -> Footprint:
        """The footprint of ``robot``'s map ``version`` (``grid``)."""
        held = self._held.get(robot)
        if held is None or held[0] != version:
            held = self._held[robot] = (version, Footprint.of(grid, self.margin_m))
        return held[1]

    def forget_except(self, robots: set[str]) -> None:
        """Drop the footprints of robots not in ``robots`` (they left the fleet)."""
        self._held = {r: f for r, f in self._held.items() if r in robots}
