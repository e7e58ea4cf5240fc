"""Graph representation of the (P)GVD, Sec. IV-D, and the edge sub-matrices of eq. (25).

Vertices are skeleton cells where more than two branches meet.  Counting
raw 8-neighbours would make every staircase step of a thinned line a vertex,
so a cell's branches are the 8-neighbours grouped by the ring crossing number
(the number of 0->1 transitions around the cell), the standard junction test
for thinned skeletons.  The vertices are dilated with a 3x3 mask (Fig. 3-b),
the edges are ``E = S - D`` labelled by 8-connectivity (Fig. 3-c), and edges
shorter than a minimum length are dropped.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage as ndi

from pgvd.morphology import grow

#: The 8 neighbours in ring order (N, NE, E, SE, S, SW, W, NW) as (row, col) offsets.
_RING = ((-1, 0), (-1, 1), (0, 1), (1, 1), (1, 0), (1, -1), (0, -1), (-1, -1))


@dataclass(frozen=True)
class Edge:
    """One labelled GVD edge and its probabilistic sub-matrix, eq. (25).

    Attributes
    ----------
    label : label of the edge in :attr:`EdgeGraph.labels`.
    origin : ``(row, col)`` of the sub-matrix's top-left cell in the map.
    matrix : PGVD values ``Sp`` inside the edge's bounding box, 0 off the edge.
    length : number of cells of the edge, ``l`` of eq. (32).
    confidence : mean PGVD probability of the edge's cells, ``alpha`` of eq. (31).
    """

    label: int
    origin: tuple[int, int]
    matrix: np.ndarray
    length: int
    confidence: float

    def cells(self) -> tuple[np.ndarray, np.ndarray]:
        """Map ``(rows, cols)`` of the edge cells."""
        r, c = np.nonzero(self.matrix > 0)
        return r + self.origin[0], c + self.origin[1]


@dataclass(frozen=True)
class EdgeGraph:
    """Vertices and edges of a PGVD.

    Attributes
    ----------
    vertices : (H, W) bool, the vertex set ``V``.
    labels : (H, W) int, edge labels of ``E = S - D`` (0 = none), dropped edges included.
    edges : the kept edges, longest first.
    """

    vertices: np.ndarray
    labels: np.ndarray
    edges: list[Edge]


def branch_count(skeleton: np.ndarray) -> np.ndarray:
    """Number of skeleton branches leaving each cell (ring crossing number).

    Parameters
    ----------
    skeleton : numpy.ndarray
        (H, W) bool skeleton.

    Returns
    -------
    numpy.ndarray
        (H, W) int8; a vertex of Sec. IV-D has more than 2.
    """
    s = np.pad(np.asarray(skeleton, dtype=bool), 1)
    h, w = s.shape[0] - 2, s.shape[1] - 2
    ring = [s[1 + dr : 1 + dr + h, 1 + dc : 1 + dc + w] for dr, dc in _RING]
    count = np.zeros((h, w), dtype=np.int8)
    for k in range(8):
        count += ~ring[k] & ring[(k + 1) % 8]
    return count


def build_graph(s: np.ndarray, sp: np.ndarray, min_edge_length: int = 8) -> EdgeGraph:
    """Vertices, labelled edges and edge sub-matrices of a PGVD (Sec. IV-D, eq. (25)).

    Parameters
    ----------
    s : numpy.ndarray
        (H, W) bool GVD, eq. (13).
    sp : numpy.ndarray
        (H, W) PGVD probabilities, eq. (24).
    min_edge_length : int, optional
        Edges with fewer cells are dropped (false-positive prone, Sec. IV-E).

    Returns
    -------
    EdgeGraph
        The kept edges sorted by decreasing length.

    Raises
    ------
    ValueError
        If ``s`` and ``sp`` are not 2-D arrays of one shape.

    References
    ----------
    .. [1] Saeedi, S., Paull, L., Trentini, M., Seto, M., and Li, H., "Map merging
       using probabilistic generalized Voronoi diagrams", IROS 2012, Sec. IV-D, eq. (25).
    """
    s = np.asarray(s, dtype=bool)
    sp = np.asarray(sp, dtype=np.float64)
    if s.shape != sp.shape or s.ndim != 2:
        raise ValueError(f"S and Sp must be equal 2-D shapes, got {s.shape} and {sp.shape}")
    vertices = s & (branch_count(s) > 2)
    dilated = grow(vertices)
    labels, n = ndi.label(s & ~dilated, np.ones((3, 3), int))
    edges: list[Edge] = []
    if n:
        lengths = np.bincount(labels.ravel(), minlength=n + 1)
        conf_sum = np.bincount(labels.ravel(), sp.ravel(), minlength=n + 1)
        for lab, box in enumerate(ndi.find_objects(labels), start=1):
            if box is None or lengths[lab] < min_edge_length:
                continue
            mask = labels[box] == lab
            # Cells with p = 0 would vanish from the sub-matrix; keep them visible.
            matrix = np.where(mask, np.maximum(sp[box], 1e-6), 0.0)
            edges.append(
                Edge(
                    label=lab,
                    origin=(box[0].start, box[1].start),
                    matrix=matrix,
                    length=int(lengths[lab]),
                    confidence=float(conf_sum[lab] / lengths[lab]),
                )
            )
    edges.sort(key=lambda e: -e.length)
    return EdgeGraph(vertices=vertices, labels=labels, edges=edges)
