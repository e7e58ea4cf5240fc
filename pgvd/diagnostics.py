"""What a person looks at after a merge: the PGVDs, the matched edges and Gamma, drawn
at full resolution (:class:`MergeDiagnostics`)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from pgvd.graph import EdgeGraph
from pgvd.pooling import block_scale

if TYPE_CHECKING:
    from pgvd.hypotheses import Hypothesis


@dataclass
class MergeDiagnostics:
    """What a person wants to look at after a merge (all at full resolution).

    Attributes
    ----------
    pgvd_a : A's PGVD (24) in A's pixel frame.
    pgvd_b : B's PGVD in B's own pixel frame (computed on rotated B, mapped back).
    edges_a : bool mask (A frame) of A's edges in the edge pairs supporting the result.
    edges_b : bool mask (B frame) of B's edges in those pairs.
    gamma : Gamma (27) of the chosen heading.
    support : number of distinct edge pairs passing (32) at the chosen translation.
    """

    pgvd_a: np.ndarray
    pgvd_b: np.ndarray
    edges_a: np.ndarray
    edges_b: np.ndarray
    gamma: np.ndarray
    support: int = 0


def _edge_mask(graph: EdgeGraph, idx: np.ndarray) -> np.ndarray:
    """Bool mask of the edges ``idx`` of ``graph`` (each drawn once)."""
    mask = np.zeros(graph.labels.shape, bool)
    for i in np.unique(idx):
        r, c = graph.edges[i].cells()
        mask[r, c] = True
    return mask


def _paint(coarse: np.ndarray, matrix: np.ndarray, k: int, shape: tuple[int, int]) -> np.ndarray:
    """Draw the nonzero coarse cells as ``k x k`` blocks into a full-resolution frame.

    ``matrix`` maps full-resolution pixels of the coarse array's frame to the target frame.
    """
    r, c = np.nonzero(coarse)
    m = matrix @ block_scale(k)
    centres = np.column_stack([c, r]).astype(float) @ m[:2, :2].T + m[:2, 2]
    out = np.zeros(shape, coarse.dtype)
    offsets = np.arange(k) - (k - 1) / 2.0
    for dy in offsets:
        for dx in offsets:
            x = np.rint(centres[:, 0] + dx).astype(np.int64)
            y = np.rint(centres[:, 1] + dy).astype(np.int64)
            ok = (x >= 0) & (x < shape[1]) & (y >= 0) & (y < shape[0])
            out[y[ok], x[ok]] = coarse[r[ok], c[ok]]
    return out


def diagnostics_of(
    best: Hypothesis,
    graph_a: EdgeGraph,
    sp_a: np.ndarray,
    off_a: np.ndarray,
    k: int,
    shapes: tuple[tuple[int, int], tuple[int, int]],
) -> MergeDiagnostics:
    """The diagnostics of the winning hypothesis ``best``, drawn in A's and B's pixels.

    ``graph_a`` and ``sp_a`` are A's edges and PGVD on its coarse crop, ``off_a`` maps
    that crop to A's coarse map, ``k`` is the coarse cell in map cells and ``shapes``
    the two maps' shapes.
    """
    ia, ib = np.nonzero(best.passing)
    to_fine = block_scale(k)
    crop_a = to_fine @ off_a @ np.linalg.inv(to_fine)
    # B's PGVD lives in the rotated coarse frame: draw it back in B's pixels.
    back = np.linalg.inv(to_fine @ best.rotation @ np.linalg.inv(to_fine))
    return MergeDiagnostics(
        pgvd_a=_paint(sp_a, crop_a, k, shapes[0]),
        pgvd_b=_paint(best.sp_b, back, k, shapes[1]),
        edges_a=_paint(_edge_mask(graph_a, ia), crop_a, k, shapes[0]),
        edges_b=_paint(_edge_mask(best.graph_b, ib), back, k, shapes[1]),
        gamma=best.gamma,
        support=best.support,
    )
