"""Pooling a probability grid into blocks, and the pixel frames of pooled maps.

The coarse search runs on maps pooled to ``SearchParams.coarse_resolution``
(:func:`coarsen`, :func:`block_scale`).  The decision (finalists refined and
scored, the acceptance margin, the covariance) runs on maps pooled to about
:data:`REFERENCE_RESOLUTION`, the cell size every one of its distances in
cells was set on (:func:`decision_pool`): a wall within 2 cells of the other
map's agrees, and at 1.75 cm cells 2 cells are 3.5 cm, a stricter test than
the 10 cm it is at 5 cm.  On 16 overlapping pairs of the intel and
freiburg-079 logs mapped at each cell size (``python3 -m bench resolution``), the
decision at full resolution accepted 12/16 right at 1.75 cm and 14/16 at 2.5 cm,
against 15/16 at 5 cm; pooled, 16/16 and 16/16, and none of 18 negatives at any
cell size.  Counting its distances in metres instead accepted a disjoint intel
pair at 1.75 cm (margin 0.57): pooled, the maps are judged as the bench judged
them.  Matrices cross between the frames with :func:`to_pooled` and
:func:`from_pooled`, covariances with :func:`covariance_from_pooled`.
"""

from __future__ import annotations

import numpy as np

from pgvd.rotation import OCCUPIED

#: Cell size (m) of every map the decision's distances in cells were set on: each map of
#: the merge bench, and the ROS map_server default.
REFERENCE_RESOLUTION = 0.05


def coarsen(p: np.ndarray, k: int, occupied: float = OCCUPIED) -> np.ndarray:
    """Pool a probability grid by ``k x k`` blocks, keeping one-cell walls.

    A block holds its largest probability if that is a wall, otherwise its
    mean; cells beyond the map edge count as unknown (0.5).
    """
    if k == 1:
        return np.asarray(p, dtype=np.float32)
    h, w = p.shape
    hp, wp = -(-h // k) * k, -(-w // k) * k
    if (hp, wp) == (h, w):  # whole blocks: no padded copy of the map
        padded = np.asarray(p, dtype=np.float32)
    else:
        padded = np.full((hp, wp), 0.5, dtype=np.float32)
        padded[:h, :w] = p
    # each block's k*k cells made contiguous: one copy, then both reductions run
    # over a contiguous last axis instead of k-long strided pieces (3x faster)
    blocks = padded.reshape(hp // k, k, wp // k, k).transpose(0, 2, 1, 3)
    blocks = np.ascontiguousarray(blocks).reshape(hp // k, wp // k, k * k)
    top = blocks.max(axis=2)
    return np.where(top > occupied, top, blocks.mean(axis=2)).astype(np.float32)


def pooled(p: np.ndarray, k: int, occupied: float = OCCUPIED) -> np.ndarray:
    """``p`` pooled ``k x k`` (:func:`coarsen`) for the decision; ``p`` itself when ``k`` is 1,
    so that a map read as it is stays as it is (no float32 copy)."""
    return p if k == 1 else coarsen(p, k, occupied)


def block_scale(k: float) -> np.ndarray:
    """Pooled cell -> full-resolution pixel (cell centres at integers in both)."""
    c = (k - 1) / 2.0
    return np.array([[k, 0.0, c], [0.0, k, c], [0.0, 0.0, 1.0]])


def decision_pool(resolution: float) -> int:
    """Cells per side pooled into one for the decision: the multiple of ``resolution``
    nearest :data:`REFERENCE_RESOLUTION`, at least 1.

    Parameters
    ----------
    resolution : float
        Cell size (m) of the maps, > 0.

    Returns
    -------
    int
        1 at 3.4 cm cells and coarser (the maps as they are), 2 at 2.5 cm, 3 at 1.75 cm.
    """
    return max(1, round(REFERENCE_RESOLUTION / resolution))


def to_pooled(matrix: np.ndarray, k: int) -> np.ndarray:
    """A B->A pixel matrix of the full maps as one of the maps pooled ``k x k``."""
    if k == 1:
        return matrix
    s = block_scale(k)
    return np.linalg.inv(s) @ matrix @ s


def from_pooled(matrix: np.ndarray, k: int) -> np.ndarray:
    """A B->A pixel matrix of the maps pooled ``k x k`` as one of the full maps."""
    if k == 1:
        return matrix
    s = block_scale(k)
    return s @ matrix @ np.linalg.inv(s)


def covariance_from_pooled(cov: np.ndarray, matrix: np.ndarray, k: int) -> np.ndarray:
    """The covariance of ``(tx, ty, psi)`` (pixels, radians) of a pooled-frame pose as one
    of the full-frame pose :func:`from_pooled` gives.

    The full-frame translation is ``k t + (I - R) c`` with ``c`` the pooled cell's centre
    offset, so its Jacobian is ``k`` in translation and ``-dR/dpsi c`` in heading
    (eq. (1)'s rotation ``R = [[cos, sin], [-sin, cos]]``); the heading is unchanged.

    Parameters
    ----------
    cov : numpy.ndarray
        3x3 covariance in the pooled frame.
    matrix : numpy.ndarray
        The pooled-frame B->A matrix it is about.
    k : int
        Cells per side of a pooled cell.

    Returns
    -------
    numpy.ndarray
        3x3 covariance in the full frame.
    """
    if k == 1:
        return cov
    psi = np.arctan2(matrix[0, 1], matrix[0, 0])
    c = np.full(2, (k - 1) / 2.0)
    d_rot = np.array([[-np.sin(psi), np.cos(psi)], [-np.cos(psi), -np.sin(psi)]])
    jac = np.diag([float(k), float(k), 1.0])
    jac[:2, 2] = -d_rot @ c
    return jac @ cov @ jac.T
