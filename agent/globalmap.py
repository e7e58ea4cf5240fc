"""The global map as a pure function of the robots' latest local maps and the chosen links.

Fleet invariant 2: any two agents holding the same ``{robot: (version, grid)}`` and the same
links build the same global maps, bit for bit.  Hence everything here is ordered:

- components are the connected components of *accepted* links;
- each is anchored at its lowest robot id, whose pixel frame is the component's frame;
- the spanning tree keeps links by decreasing score, ties broken by robot ids (Kruskal);
- transforms are composed along the tree from the anchor;
- local maps are fused into the anchor's map in increasing robot id, with
  :func:`pgvd.fusion.fuse_maps` (eqs. (33)-(37), the transform's covariance blurring the
  added map per eqs. (4)-(8)).

Only local maps are ever fused: a fused map is never an input (fleet invariant 1).
"""

from __future__ import annotations

import hashlib
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass

import numpy as np

from agent.links import LinkRecord
from pgvd.grid import Grid, relative_matrix
from pgvd.uncertainty import compose_covariance, inverse_covariance
from protocol.quantize import quantise

FuseFn = Callable[[Grid, Grid, np.ndarray, np.ndarray], Grid]


@dataclass(frozen=True)
class Component:
    """One connected component of the fleet's match graph and its fused map.

    Attributes
    ----------
    anchor : lowest robot id of the component; its map's pixel frame is the global frame.
    members : robot ids, sorted.
    versions : ``{robot: version}`` that went into ``grid``.
    transforms : ``{robot: 3x3}`` from that robot's pixels to the anchor's pixels.
    tree : links used, as ``(a, b)`` pairs, in the order they were chosen.
    grid : the fused map.
    digest : hex SHA-256 of the quantised fused map (see :func:`map_digest`).
    unblurred : robots whose map had to be fused without its uncertainty blur because
        the blur failed on these inputs (reported in the status).
    """

    anchor: str
    members: tuple[str, ...]
    versions: dict[str, int]
    transforms: dict[str, np.ndarray]
    tree: tuple[tuple[str, str], ...]
    grid: Grid
    digest: str
    unblurred: tuple[str, ...] = ()


def spanning_forest(
    robots: Iterable[str], links: Iterable[LinkRecord]
) -> dict[str, list[LinkRecord]]:
    """Kruskal over accepted links, best score first, ties by ``(a, b)``.

    Returns ``{anchor: tree links in the order chosen}`` for every component, singletons
    included (empty list).
    """
    parent = {r: r for r in robots}

    def find(r: str) -> str:
        while parent[r] != r:
            parent[r] = parent[parent[r]]
            r = parent[r]
        return r

    chosen: list[LinkRecord] = []
    usable = [ln for ln in links if ln.accepted and ln.a in parent and ln.b in parent]
    for ln in sorted(usable, key=lambda ln: (-ln.score, ln.a, ln.b)):
        ra, rb = find(ln.a), find(ln.b)
        if ra != rb:
            parent[max(ra, rb)] = min(ra, rb)  # the root is always the lowest id
            chosen.append(ln)
    forest: dict[str, list[LinkRecord]] = {find(r): [] for r in parent}
    for ln in chosen:
        forest[find(ln.a)].append(ln)
    return forest


def compose_transforms(
    anchor: str, tree: list[LinkRecord]
) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
    """Matrices robot px -> anchor px along ``tree``, and their first-order covariances.

    A link's matrix maps ``b`` to ``a``; walking it from ``b`` to ``a`` uses the inverse
    and its covariance.  Covariances compose to first order, eq. (4), with the Jacobian of
    eq. (1): a parent's heading error also moves the child's translation
    (:func:`pgvd.uncertainty.compose_covariance`).
    """
    mats = {anchor: np.eye(3)}
    covs = {anchor: np.zeros((3, 3))}
    adjacency: dict[str, list[tuple[str, np.ndarray, np.ndarray]]] = {}
    for ln in tree:
        adjacency.setdefault(ln.a, []).append((ln.b, ln.matrix, ln.covariance))
        adjacency.setdefault(ln.b, []).append(
            (ln.a, np.linalg.inv(ln.matrix), inverse_covariance(ln.matrix, ln.covariance))
        )
    frontier = [anchor]
    while frontier:
        node = frontier.pop(0)
        for child, m, cov in sorted(adjacency.get(node, []), key=lambda t: t[0]):
            if child in mats:
                continue
            mats[child] = mats[node] @ m
            covs[child] = compose_covariance(mats[node], covs[node], m, cov)
            frontier.append(child)
    return mats, covs


def map_digest(grid: Grid) -> str:
    """SHA-256 of a map as the wire sees it: int8 log-odds, shape, resolution, origin."""
    h = hashlib.sha256()
    q = quantise(grid.logodds)
    h.update(np.asarray(q.shape, dtype=np.int64).tobytes())
    h.update(np.ascontiguousarray(q).tobytes())
    meta = np.round(np.array([grid.resolution, *grid.origin], dtype=np.float64), 6)
    h.update(meta.tobytes())
    return h.hexdigest()


def build_components(
    maps: Mapping[str, tuple[int, Grid]],
    links: Iterable[LinkRecord],
    fuse: FuseFn | None = None,
) -> list[Component]:
    """Every component's global map from the latest local maps and one link per pair.

    Parameters
    ----------
    maps : ``{robot: (version, local grid)}``, the latest local map of each robot.
    links : at most one link per pair (:func:`agent.links.select_links`).
    fuse : ``fuse(base, other, other_px_to_base_px, covariance) -> Grid``; defaults to
        :func:`pgvd.fusion.fuse_maps`.  The result may grow the canvas: its ``origin``
        says where the base went, so matrices are re-expressed through
        :func:`pgvd.grid.relative_matrix`.

    Returns
    -------
    Components sorted by anchor id.
    """
    if fuse is None:
        from pgvd.fusion import fuse_maps as fuse
    forest = spanning_forest(maps, links)
    out = []
    for anchor in sorted(forest):
        tree = forest[anchor]
        mats, covs = compose_transforms(anchor, tree)
        members = tuple(sorted(mats))
        base = maps[anchor][1]
        fused = base
        unblurred: list[str] = []
        for robot in members:
            if robot == anchor:
                continue
            # The canvas of `fused` may have grown: anchor px -> fused px, then compose.
            to_fused = relative_matrix(fused, base) @ mats[robot]
            try:
                fused = fuse(fused, maps[robot][1], to_fused, covs[robot])
            except (ValueError, ArithmeticError):
                # The same inputs fail the same way on every agent, so falling back to
                # fusion without the uncertainty blur keeps them in agreement; a global
                # map that never settles would be worse.
                fused = fuse(fused, maps[robot][1], to_fused, np.zeros((3, 3)))
                unblurred.append(robot)
        out.append(
            Component(
                anchor=anchor,
                members=members,
                versions={r: maps[r][0] for r in members},
                transforms=mats,
                tree=tuple(ln.pair for ln in tree),
                grid=fused,
                digest=map_digest(fused),
                unblurred=tuple(unblurred),
            )
        )
    return out


def component_of(components: Iterable[Component], robot: str) -> Component | None:
    return next((c for c in components if robot in c.members), None)
