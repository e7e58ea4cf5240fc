"""How registration reads two maps, and the checks that refuse maps it cannot merge."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from pgvd.grid import Grid, check_cell_size
from pgvd.params import MergeParams
from pgvd.speckle import radius_cells, without_speckle
from pgvd.unexplored import restore_unexplored, unknown_share


def registration_probability(
    grid: Grid, params: MergeParams, say: Callable[[str], None] | None = None
) -> np.ndarray:
    """The probabilities (34) of ``grid`` that registration reads.

    With ``params.off.speckle_radius``, lone wall cells (speckle, :mod:`pgvd.speckle`)
    are unknown.  A map with less than ``params.reading.min_unknown`` of its cells unknown
    (an image whose unexplored area was painted free) gets its unexplored space back
    (:func:`pgvd.unexplored.restore_unexplored`).  ``say`` is told of both.
    """
    prob, reading = grid.probability(), params.reading
    # measured as drawn: speckle read as unknown must not hide a map painted free
    painted = unknown_share(prob, reading.free, reading.occupied) < reading.min_unknown
    if params.off.speckle_radius > 0:
        radius = radius_cells(params.off.speckle_radius, grid.resolution)
        prob, lone = without_speckle(prob, reading.occupied, radius, reading.speckle_cells)
        if lone and say is not None:
            say(f"{lone} lone wall cells (speckle) read as unknown")
    if not painted:
        return prob
    if say is not None:
        say("no unknown cells: free space outside the convex hull of its walls read as unknown")
    return restore_unexplored(prob, reading.free, reading.occupied)


def check_extent(name: str, grid: Grid, params: MergeParams) -> None:
    """Refuse a map under three search cells (``params.search.coarse_resolution``) a side,
    or one whose cell size is no occupancy grid's (:func:`pgvd.grid.check_cell_size`).

    The search pools each map to those cells and the decision to about 5 cm
    (:mod:`pgvd.pooling`): a map a few search cells across has no GVD edge to match, and a
    cell size far outside a grid's (a wrong ``resolution``, or a hostile one) would make
    that pooling ask for a canvas of astronomic size instead of failing.

    Parameters
    ----------
    name : str
        How the message names the map ("A", "B").
    grid : Grid
        The map.
    params : MergeParams
        Its ``coarse_resolution``.

    Raises
    ------
    ValueError
        Naming the map, its extent and its cell size.
    """
    try:
        check_cell_size(grid.resolution)
    except ValueError as exc:
        raise ValueError(f"map {name}: {exc}") from None
    least = 3 * params.search.coarse_resolution
    h, w = (n * grid.resolution for n in grid.shape)
    if min(h, w) < least:
        raise ValueError(
            f"map {name} spans {w:.3g} x {h:.3g} m, under {least:.3g} m a side: too small "
            f"to merge at {grid.resolution:g} m/cell (is the cell size right?)"
        )


def check_resolutions(a: Grid, b: Grid) -> None:
    """``ValueError`` unless the two maps have one cell size (to a part in a million)."""
    if not np.isclose(a.resolution, b.resolution, rtol=1e-6, atol=0.0):
        raise ValueError(
            f"maps have different resolutions ({a.resolution} vs {b.resolution} m/cell); "
            "resample B first (pgvd.transform.resample)"
        )


def check_inputs(a: Grid, b: Grid, pa: np.ndarray, pb: np.ndarray, params: MergeParams) -> None:
    """``ValueError`` for maps the merge cannot read: cell sizes that differ, an empty or
    too small map, NaN, or no wall (in ``pa``, ``pb``, the probabilities registration reads).
    """
    check_resolutions(a, b)
    check_map("A", a, pa, params)
    check_map("B", b, pb, params)


def check_map(name: str, grid: Grid, prob: np.ndarray, params: MergeParams) -> None:
    """``ValueError`` naming map ``name`` if the merge cannot read it, whatever the other
    map (:func:`check_inputs`, less the cell sizes' match): empty, too small, NaN, or no
    wall in ``prob``."""
    if grid.logodds.size == 0:
        raise ValueError(f"map {name} is empty")
    check_extent(name, grid, params)
    if not np.isfinite(grid.logodds).all():
        raise ValueError(f"map {name} contains NaN or infinite values")
    if not (prob > params.reading.occupied).any():
        raise ValueError(f"map {name} has no occupied cells")
