"""The links between robots' maps as lines between the maps' centres, one colour per state.

Both pictures of the fleet draw them: RViz through ``--ros-links`` (one ``LINE_LIST`` marker
per state, :mod:`protocol.ros2.markers`) and ``pgvd demo``'s side-by-side picture
(:mod:`agent.sidebyside`), in the same colours. A robot's map sits where its known cells are,
so a link joins the centres of the two maps' known cells, placed as the global map placed
them. Only the links of the current epochs are drawn, as the status lists them by state
(:func:`agent.status.link_states`); rejected links are not drawn.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping

import numpy as np

from agent import trust
from agent.globalmap import Component
from agent.links import LinkRecord
from pgvd.grid import Grid, world_pose_to_pixel_matrix
from protocol.ros2.markers import LineList, Point2

#: The states drawn, each in its own colour (RGB, 0..255); rejected links are not drawn.
COLOURS: dict[str, tuple[int, int, int]] = {
    trust.ACCEPTED: (0, 150, 0),
    trust.CONFIRMED: (150, 60, 200),
    trust.CANDIDATE: (230, 130, 0),
    # dark: a light grey vanishes on the unknown cells of a rendered map
    trust.WITHDRAWN: (70, 70, 70),
}


def known_centre(grid: Grid) -> np.ndarray | None:
    """The mean pixel ``[column, row]`` of ``grid``'s known cells, None if it has none."""
    known = np.argwhere(grid.logodds != 0)
    if not known.size:
        return None
    row, col = known.mean(axis=0)
    return np.array([col, row])


def map_centres(comp: Component, maps: Mapping[str, tuple[int, Grid]]) -> dict[str, Point2]:
    """Each member's :func:`known_centre` in the merged frame (the anchor's map frame), m.

    A member's pixels reach the anchor's through the component's matrix, eqs. (1)-(2), and
    the anchor's pixels its metric frame. As for the TF placements, a robot (or the anchor)
    whose map moved on since the component was built is left out until the next rebuild,
    and so is a map with no known cell.

    Parameters
    ----------
    comp : the component whose global map is published.
    maps : ``{robot: (version, grid)}`` held now.
    """
    anchor = maps.get(comp.anchor)
    if anchor is None or anchor[0] != comp.versions[comp.anchor]:
        return {}
    to_metric = np.linalg.inv(world_pose_to_pixel_matrix(anchor[1]))
    out = {}
    for robot in comp.members:
        held = maps.get(robot)
        if held is None or held[0] != comp.versions[robot]:
            continue
        centre = known_centre(held[1])
        if centre is not None:
            x, y, _ = to_metric @ comp.transforms[robot] @ np.append(centre, 1.0)
            out[robot] = (float(x), float(y))
    return out


def link_line_lists(
    records: Iterable[LinkRecord], versions: Mapping[str, int], centres: Mapping[str, Point2]
) -> list[LineList]:
    """One :class:`LineList` per drawn state (:data:`COLOURS`), namespace the state.

    A list holds a segment per current link of its state whose two robots have a centre;
    a state with no such link has an empty list, so that its lines go (no links, or none
    placed, is every list empty).

    Parameters
    ----------
    records : the links held (:meth:`agent.book.FleetBook.links`).
    versions : the latest version of each robot's map (which links are current).
    centres : where each placed robot's map is, as :func:`map_centres` gives.
    """
    segments: dict[str, list[tuple[Point2, Point2]]] = {state: [] for state in COLOURS}
    for rec in records:
        placed = rec.a in centres and rec.b in centres
        if rec.state in segments and placed and rec.current(versions):
            segments[rec.state].append((centres[rec.a], centres[rec.b]))
    return [
        LineList(state, (*(c / 255 for c in rgb), 1.0), tuple(segments[state]))
        for state, rgb in COLOURS.items()
    ]
