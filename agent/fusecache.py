"""Each robot's map blurred and warped into its component anchor's pixels, kept from one
rebuild to the next.

A global map fuses every member's local map into the anchor's (eqs. (33)-(37)), and the
bulk of that is eq. (8): each map blurred by its placement's uncertainty and warped.  The
blur is the same kernel in the map's own frame wherever the map is placed -- the
placement's covariance rotated into that frame (:func:`pgvd.fusion.own_frame_covariance`)
-- so it is done there, before the warp (:func:`pgvd.fusion.warp_layer`), and both steps
are kept:

- a layer (the map blurred and warped) is a function of the map and of its placement
  alone -- the matrix and covariance into the anchor's pixels -- not of the canvas it is
  fused on, so it is computed again only when one of them changed: a robot's new map
  version re-warps that robot only, and a robot that joins or leaves (however the canvas
  grows) re-warps nobody else, as long as the others' placements stay as they were;
- a placement that really moved (a new link re-solves the pose graph) but whose
  covariance in the map's own frame stays the same only re-warps the map blurred before:
  a bilinear read, not the blur.  That covariance is snapped to the placement lattice
  (:func:`agent.placement.snap_covariance`) so that a heading that turned by a step leaves
  it as it was.

A re-solved cycle moves every placement of the component by a rounding error; the
placements are snapped before they get here (:func:`agent.placement.snap_placement`), so
only the robots that moved by a step or more are warped again.

Fleet invariant 2 is untouched: what is held is the very array a cold rebuild would
compute from the same map and placement, so warm and cold rebuilds give the same global
map bit for bit.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Collection
from dataclasses import dataclass

import numpy as np

from agent.placement import snap_covariance
from pgvd.fusion import Layer, blur_in_own_frame, own_frame_covariance, place_blurred
from pgvd.grid import Grid


@dataclass(frozen=True)
class _Held:
    """One robot's layer and what it was computed from."""

    key: tuple[int, bytes, bytes]
    layer: Layer
    unblurred: bool


@dataclass(frozen=True)
class _Blurred:
    """One robot's map blurred in its own frame, and what it was blurred with."""

    key: tuple[int, bytes]
    blurred: np.ndarray
    unblurred: bool


class LayerCache:
    """The layers of the robots a rebuild fused, keyed by robot, map version and placement,
    and their maps blurred in their own frames, keyed by robot, map version and covariance
    in that frame.

    Memory bound: at most one layer and one blurred map per robot, and :meth:`retain` after
    each rebuild drops those of robots it did not fuse (gone, alone, or the anchor).  A
    blurred map is float32 of its map's shape.  A layer is float32 over at most its map's
    footprint in the anchor's pixels: ``H x W`` cells turned by ``psi`` cover
    ``(H |cos| + W |sin| + 2) (W |cos| + H |sin| + 2)`` cells, at most
    ``(H + W)^2 / 2 + O(H + W)``, and usually much less since the unknown border is cut
    off.  At 16 robots with maps of 500 x 500 cells that is under 16 x 3 MB.

    Attributes
    ----------
    warps : layers computed.
    reuses : layers served as held.
    blurs : maps blurred; ``warps - blurs`` layers were warps of a blurred map held.
    blur_causes : why each map was blurred: ``"first"`` (no blurred map of the robot held),
        ``"version"`` (a new map version) or ``"covariance"`` (the same version, its
        covariance in its own frame on another lattice point).
    """

    def __init__(self) -> None:
        self._held: dict[str, _Held] = {}
        self._blurred: dict[str, _Blurred] = {}
        self.warps = 0
        self.reuses = 0
        self.blurs = 0
        self.blur_causes: Counter[str] = Counter()

    def layer(
        self,
        robot: str,
        version: int,
        grid: Grid,
        matrix: np.ndarray,
        covariance: np.ndarray,
        blur: bool = True,
    ) -> tuple[Layer, bool]:
        """``robot``'s map ``grid`` (at ``version``) warped into the anchor's pixels by
        ``matrix`` with ``covariance``, eq. (8); also whether its blur had to be left out.

        ``(robot, version)`` must name one map, as it does in a fleet (invariant 2).  The
        placement's key is the exact bytes of ``matrix`` and ``covariance`` as float64: one
        that moved by a rounding error is a new placement, since another agent holding it
        computes the layer from those bytes.  ``blur`` False: the map warped without the
        blur (a preview), whatever ``covariance``; the blurred map held is kept.
        """
        key = (
            int(version),
            np.asarray(matrix, dtype=np.float64).tobytes(),
            np.asarray(covariance, dtype=np.float64).tobytes() if blur else b"",
        )
        held = self._held.get(robot)
        if held is not None and held.key == key:
            self.reuses += 1
            return held.layer, held.unblurred
        if blur:
            held_blur = self._blur(robot, int(version), grid, matrix, covariance)
            own, unblurred = held_blur.blurred, held_blur.unblurred
        else:  # cheap (a subtraction), so not held
            own, unblurred = _unblurred(grid), False
        layer = place_blurred(own, grid.resolution, matrix)
        layer.logodds.setflags(write=False)  # shared by every rebuild until replaced
        self._held[robot] = _Held(key, layer, unblurred)
        self.warps += 1
        return layer, unblurred

    def _blur(
        self, robot: str, version: int, grid: Grid, matrix: np.ndarray, covariance: np.ndarray
    ) -> _Blurred:
        """``robot``'s map blurred in its own frame by ``covariance`` turned into it,
        snapped; the one held if it was blurred with the same."""
        try:
            own = snap_covariance(own_frame_covariance(matrix, covariance))
            key = (version, own.tobytes())
            held = self._blurred.get(robot)
            if held is not None and held.key == key:
                return held
            self.blur_causes[_cause(held, version)] += 1
            blurred = _Blurred(key, blur_in_own_frame(grid, own), False)
        except (ValueError, ArithmeticError):
            # The same inputs fail the same way on every agent, so warping without the
            # uncertainty blur keeps them in agreement; a global map that never settles
            # would be worse.
            blurred = _Blurred((version, b""), _unblurred(grid), True)
        blurred.blurred.setflags(write=False)
        self._blurred[robot] = blurred
        self.blurs += 1
        return blurred

    def retain(self, robots: Collection[str]) -> None:
        """Forget the layers and blurred maps of every robot not in ``robots``."""
        self._held = {r: h for r, h in self._held.items() if r in robots}
        self._blurred = {r: b for r, b in self._blurred.items() if r in robots}

    @property
    def robots(self) -> frozenset[str]:
        """The robots whose layer is held."""
        return frozenset(self._held)

    def held_bytes(self) -> int:
        """Bytes of the layers and blurred maps held."""
        return sum(h.layer.logodds.nbytes for h in self._held.values()) + sum(
            b.blurred.nbytes for b in self._blurred.values()
        )


def _cause(held: _Blurred | None, version: int) -> str:
    """Why a map is blurred again, given what was held for its robot (:class:`LayerCache`)."""
    if held is None:
        return "first"
    return "version" if held.key[0] != version else "covariance"


def _unblurred(grid: Grid) -> np.ndarray:
    """``grid`` in its own frame without eq. (8)'s blur, as :func:`blur_in_own_frame` gives
    it for a zero covariance."""
    return blur_in_own_frame(grid, np.zeros((3, 3)))
