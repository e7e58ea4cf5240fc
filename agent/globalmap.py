"""The global map as a pure function of the robots' latest local maps and the chosen links.

Fleet invariant 2: any two agents holding the same ``{robot: (version, grid)}`` and the same
links build the same global maps, bit for bit.  Hence everything here is ordered:

- robots are placed from all *accepted* links at once by the robust pose graph of
  :func:`pgvd.posegraph.solve`, which drops links inconsistent around a cycle (GNC-TLS)
  and sorts its inputs, so the order links arrive in does not matter; of a lone
  inconsistent cycle it leaves out the link of lowest margin
  (:func:`agent.trust.link_strength`), which the link records carry to every agent;
- components are the connected components of the links it kept, each anchored at its
  robot whose first epoch is oldest, ties by robot id (:func:`anchor_rank`), whose pixel
  frame is the component's frame: a robot joining or returning never moves the frame of
  the robots already merged, unless it is older than their anchor, and when two
  components join the older anchor's frame stays;
- local maps are fused into the anchor's map, then the others' in increasing robot id: each
  is blurred in its own frame by its placement's covariance turned into that frame, eqs.
  (4)-(8), then warped into the anchor's pixels (:func:`pgvd.fusion.warp_layer`; both kept
  between rebuilds by :class:`agent.fusecache.LayerCache`), then the layers are fused in
  that order, eqs. (33)-(37) (:func:`pgvd.fusion.fuse_layers`).

The canvas of a global map is the smallest that holds every member's map whole, computed
before anything is fused, and each layer is warped and blurred on its own map's footprint
rather than on that canvas.  Why: on a canvas grown map by map (:func:`pgvd.fusion.fuse_maps`
in turn) each map's blur reaches to the edges of the canvas the maps before it made, so a
robot joining would re-warp every robot after it; a layer that depends on its map and its
placement alone is kept until one of them changes, and a warm rebuild is bit for bit a
cold one.

Only local maps are ever fused: a fused map is never an input (fleet invariant 1).
"""

from __future__ import annotations

import hashlib
import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass

import numpy as np

from agent.fusecache import LayerCache
from agent.links import LinkRecord
from agent.placement import snap_placement
from agent.trust import link_strength
from pgvd.fusion import fuse_layers
from pgvd.grid import Grid
from pgvd.posegraph import PoseGraphParams, Rank, link_problem, solve
from protocol.quantize import quantise

#: ``{id(record): (record, sound)}``: whether a link record is a rigid transform with a
#: covariance (:func:`pgvd.posegraph.link_problem`).  The record is held so that its id
#: cannot be reused while the entry lives.
Soundness = dict[int, tuple[LinkRecord, bool]]


@dataclass(frozen=True)
class Component:
    """One connected component of the fleet's match graph and its fused map.

    Attributes
    ----------
    anchor : the robot of the component whose first epoch is oldest, ties by robot id
        (:func:`anchor_rank`); its map's pixel frame is the global frame.
    members : robot ids, sorted.
    versions : ``{robot: version}`` that went into ``grid``.
    transforms : ``{robot: 3x3}`` from that robot's pixels to the anchor's pixels, as
        fused: the pose graph's, snapped (:func:`agent.placement.snap_placement`).
    covariances : ``{robot: 3x3}`` over ``(x px, y px, psi)`` of that transform, eq. (3),
        snapped likewise.
    used : accepted links the joint solution kept, as sorted ``(a, b)`` pairs.
    rejected : accepted links of its members it dropped as inconsistent around a cycle.
    grid : the fused map.
    digest : hex SHA-256 of the quantised fused map (see :func:`map_digest`).
    unblurred : robots whose map had to be fused without its uncertainty blur because
        the blur failed on these inputs (reported in the status).
    evidence : ``(a, b, decided_by, version_a, version_b)`` of every accepted link of its
        members that went into the solution, used or rejected: the placements are a
        function of these (the soak's steadiness measure compares them).
    """

    anchor: str
    members: tuple[str, ...]
    versions: dict[str, int]
    transforms: dict[str, np.ndarray]
    covariances: dict[str, np.ndarray]
    used: tuple[tuple[str, str], ...]
    rejected: tuple[tuple[str, str], ...]
    grid: Grid
    digest: str
    unblurred: tuple[str, ...] = ()
    evidence: tuple[tuple[str, str, str, int, int], ...] = ()


def map_digest(grid: Grid) -> str:
    """SHA-256 of a map as the wire sees it: int8 log-odds, shape, resolution, origin."""
    h = hashlib.sha256()
    q = quantise(grid.logodds)
    h.update(np.asarray(q.shape, dtype=np.int64).tobytes())
    h.update(np.ascontiguousarray(q).tobytes())
    meta = np.round(np.array([grid.resolution, *grid.origin], dtype=np.float64), 6)
    h.update(meta.tobytes())
    return h.hexdigest()


def anchor_rank(firsts: Mapping[str, int]) -> Rank:
    """The rank that anchors each component at its oldest robot: least first epoch, then
    least robot id (:func:`pgvd.posegraph.solve`).

    A robot's first epoch is the epoch of its first map version, carried by every manifest
    of the robot and kept in its state directory, so it never changes while the robot
    lives: a robot that joins or returns ranks after the robots that were there before it
    and leaves their frame where it was.  A robot whose first epoch is not known (a map
    whose manifest did not say) ranks after every robot whose first epoch is.
    """
    return lambda robot: firsts.get(robot, math.inf)


def accepted_links(
    maps: Mapping[str, tuple[int, Grid]], links: Iterable[LinkRecord]
) -> list[LinkRecord]:
    """The accepted links between robots of ``maps``, sorted by pair."""
    held = (ln for ln in links if ln.accepted and ln.a in maps and ln.b in maps)
    return sorted(held, key=lambda ln: ln.pair)


def usable_links(
    maps: Mapping[str, tuple[int, Grid]],
    links: Iterable[LinkRecord],
    sound: Soundness | None = None,
) -> list[LinkRecord]:
    """The accepted links the pose graph can take (:func:`accepted_links`), sorted by pair.

    A peer's link that is not a rigid transform with a covariance
    (:func:`pgvd.posegraph.link_problem`) is left out like an inconsistent one: refusing the
    whole global map for it would let one bad record stall it.  ``sound`` remembers each
    record's verdict across calls (records never change): a fleet of 16 holds 120 links,
    and judging them all at every link and every rebuild cost as much as a registration's
    check.
    """
    memo: Soundness = {} if sound is None else sound
    out = []
    for ln in accepted_links(maps, links):
        held = memo.get(id(ln))
        if held is None or held[0] is not ln:
            held = memo[id(ln)] = (ln, link_problem(ln, (ln.a, ln.b)) is None)
        if held[1]:
            out.append(ln)
    return out


def build_components(
    maps: Mapping[str, tuple[int, Grid]],
    links: Iterable[LinkRecord],
    params: PoseGraphParams | None = None,
    sound: Soundness | None = None,
    layers: LayerCache | None = None,
    firsts: Mapping[str, int] | None = None,
    fuse: bool = True,
    blur: bool = True,
) -> list[Component]:
    """Every component's global map from the latest local maps and one link per pair.

    Parameters
    ----------
    maps : ``{robot: (version, local grid)}``, the latest local map of each robot.
    links : at most one link per pair (:func:`agent.links.select_links`); rejected
        ones and those of robots without a map are ignored.
    params : the pose graph's floors and threshold (:class:`pgvd.posegraph.PoseGraphParams`).
    sound : the links' soundness judged before (:func:`usable_links`); filled in.
    layers : the layers of the last rebuild (:class:`agent.fusecache.LayerCache`), reused
        where a robot's version and placement are unchanged; left holding this build's.
        None: a cold build.
    firsts : ``{robot: first epoch}`` that came with those maps; each component is
        anchored at its oldest robot (:func:`anchor_rank`), and without ``firsts`` at its
        lowest robot id.
    fuse : False: the placements alone, each component's ``grid`` its anchor's map (for a
        simulation that charges the fusion's cost rather than spending it); ``layers`` is
        then not used.
    blur : False: each map placed without eq. (8)'s blur (a preview of a round still in
        progress, :meth:`agent.worker.FusionWorker._rebuild`); the entropy filter as ever.

    Returns
    -------
    Components sorted by their anchor's rank.
    """
    layers = LayerCache() if layers is None else layers
    accepted = accepted_links(maps, links)
    usable = usable_links(maps, accepted, sound)
    sol = solve(maps, usable, params, anchor_rank(firsts or {}), link_strength)
    # The one place the solve's placements become the fusion's (and the status's and TF's):
    # snapped, so a re-solve that moved a robot by a rounding error keeps its layer.
    snapped = {
        r: snap_placement(m, sol.covariances[r], maps[r][1].shape)
        for r, m in sol.transforms.items()
    }
    mats = {r: m for r, (m, _) in snapped.items()}
    covs = {r: c for r, (_, c) in snapped.items()}
    dropped = {ln.pair for ln in accepted} - {
        ln.pair for ln, u in zip(usable, sol.used, strict=True) if u
    }
    out = []
    for placed in sol.components:  # the anchor first, then the others by id: the fusion order
        members = tuple(sorted(placed))
        anchor, order = placed[0], placed[1:]
        inside = [(ln.pair, u) for ln, u in zip(usable, sol.used, strict=True) if ln.a in members]
        if fuse:
            grid, unblurred = _fuse_component(maps, anchor, order, mats, covs, layers, blur)
        else:
            grid, unblurred = maps[anchor][1], ()
        out.append(
            Component(
                anchor=anchor,
                members=members,
                versions={r: maps[r][0] for r in members},
                transforms={r: mats[r] for r in members},
                covariances={r: covs[r] for r in members},
                used=tuple(p for p, u in inside if u),
                rejected=tuple(p for p in sorted(dropped) if p[0] in members or p[1] in members),
                grid=grid,
                digest=map_digest(grid),
                unblurred=unblurred,
                evidence=tuple(
                    (ln.a, ln.b, ln.decided_by, ln.version_a, ln.version_b)
                    for ln in usable
                    if ln.a in members
                ),
            )
        )
    if fuse:
        layers.retain({r for c in out for r in c.members if r != c.anchor})
    return out


def _fuse_component(
    maps: Mapping[str, tuple[int, Grid]],
    anchor: str,
    order: tuple[str, ...],
    mats: Mapping[str, np.ndarray],
    covs: Mapping[str, np.ndarray],
    layers: LayerCache,
    blur: bool = True,
) -> tuple[Grid, tuple[str, ...]]:
    """Local maps fused into ``anchor``'s in ``order``, eqs. (33)-(37); also the robots
    fused without their blur.

    ``mats`` and ``covs`` place each robot of ``order`` in ``anchor``'s pixels.  Each map is
    warped into them on its own (:meth:`agent.fusecache.LayerCache.layer`, eq. (8)), then
    the layers are fused into the anchor's map in ``order`` on one canvas that holds them
    all (:func:`pgvd.fusion.fuse_layers`).
    """
    got = [(r, *layers.layer(r, maps[r][0], maps[r][1], mats[r], covs[r], blur)) for r in order]
    grid = fuse_layers(maps[anchor][1], [layer for _, layer, _ in got])
    return grid, tuple(r for r, _, unblurred in got if unblurred)


def component_of(components: Iterable[Component], robot: str) -> Component | None:
    return next((c for c in components if robot in c.members), None)
