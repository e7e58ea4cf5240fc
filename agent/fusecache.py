"""Each robot's map warped into its component anchor's pixels, kept from one rebuild to the next.

A global map fuses every member's local map into the anchor's (eqs. (33)-(37)), and the
bulk of that is the warp of each map with its placement's uncertainty, eq. (8)
(:func:`pgvd.fusion.warp_layer`).  A layer is a function of the map and of its placement
alone -- the matrix and covariance into the anchor's pixels -- not of the canvas it is
fused on, so it is computed again only when one of them changed: a robot's new map
version re-warps that robot only, and a robot that joins or leaves (however the canvas
grows) re-warps nobody else, as long as the others' placements stay as they were.  A
re-solved cycle moves every placement of the component by a rounding error; the
placements are snapped before they get here (:func:`agent.placement.snap_placement`), so
only the robots that moved by a step or more are warped again.

Fleet invariant 2 is untouched: a layer held is the very array a cold rebuild would
compute, so warm and cold rebuilds give the same global map bit for bit.
"""

from __future__ import annotations

from collections.abc import Collection
from dataclasses import dataclass

import numpy as np

from pgvd.fusion import Layer, warp_layer
from pgvd.grid import Grid


@dataclass(frozen=True)
class _Held:
    """One robot's layer and what it was computed from."""

    key: tuple[int, bytes, bytes]
    layer: Layer
    unblurred: bool


class LayerCache:
    """The layers of the robots a rebuild fused, keyed by robot, map version and placement.

    Memory bound: at most one layer per robot, and :meth:`retain` after each rebuild
    drops those of robots it did not fuse (gone, alone, or the anchor).  A layer is float32
    over at most its map's footprint in the anchor's pixels: ``H x W`` cells turned by
    ``psi`` cover ``(H |cos| + W |sin| + 2) (W |cos| + H |sin| + 2)`` cells, at most
    ``(H + W)^2 / 2 + O(H + W)``, and usually much less since the unknown border is cut
    off.  At 16 robots with maps of 500 x 500 cells that is under 16 x 2 MB.

    Attributes
    ----------
    warps : layers computed.
    reuses : layers served as held.
    """

    def __init__(self) -> None:
        self._held: dict[str, _Held] = {}
        self.warps = 0
        self.reuses = 0

    def layer(
        self, robot: str, version: int, grid: Grid, matrix: np.ndarray, covariance: np.ndarray
    ) -> tuple[Layer, bool]:
        """``robot``'s map ``grid`` (at ``version``) warped into the anchor's pixels by
        ``matrix`` with ``covariance``, eq. (8); also whether its blur had to be left out.

        ``(robot, version)`` must name one map, as it does in a fleet (invariant 2).  The
        placement's key is the exact bytes of ``matrix`` and ``covariance`` as float64: one
        that moved by a rounding error is a new placement, since another agent holding it
        computes the layer from those bytes.
        """
        key = (
            int(version),
            np.asarray(matrix, dtype=np.float64).tobytes(),
            np.asarray(covariance, dtype=np.float64).tobytes(),
        )
        held = self._held.get(robot)
        if held is not None and held.key == key:
            self.reuses += 1
            return held.layer, held.unblurred
        layer, unblurred = _warp(grid, matrix, covariance)
        layer.logodds.setflags(write=False)  # shared by every rebuild until replaced
        self._held[robot] = _Held(key, layer, unblurred)
        self.warps += 1
        return layer, unblurred

    def retain(self, robots: Collection[str]) -> None:
        """Forget the layers of every robot not in ``robots``."""
        self._held = {r: h for r, h in self._held.items() if r in robots}

    @property
    def robots(self) -> frozenset[str]:
        """The robots whose layer is held."""
        return frozenset(self._held)

    def held_bytes(self) -> int:
        """Bytes of the layers held."""
        return sum(h.layer.logodds.nbytes for h in self._held.values())


def _warp(grid: Grid, matrix: np.ndarray, covariance: np.ndarray) -> tuple[Layer, bool]:
    """:func:`pgvd.fusion.warp_layer`, or without the blur where the blur fails (then True)."""
    try:
        return warp_layer(grid, matrix, covariance), False
    except (ValueError, ArithmeticError):
        # The same inputs fail the same way on every agent, so warping without the
        # uncertainty blur keeps them in agreement; a global map that never settles
        # would be worse.
        return warp_layer(grid, matrix, np.zeros((3, 3))), True
