"""GVD by morphology and the probabilistic GVD (PGVD), eqs. (13)-(24).

The GVD ``S`` (13) is the morphological skeleton of the free space: thinning
keeps the cells that are (discretely) equidistant from two obstacles and
guarantees a connected, one-cell-thin result, the role of the paper's
hit-or-miss masks.  Obstacles are all cells that are not free, so unknown
space bounds the skeleton like a wall does -- with its own probability 0.5,
which is what the PGVD exploits.

Contact points (Definition 1) come from an exact Euclidean distance
transform: its feature transform gives, for every cell, the nearest obstacle
cell.  The contact points of a skeleton cell ``G_i`` are the nearest obstacle
cells of ``G_i`` and its 8 neighbours that lie on ``G_i``'s maximal inscribed
circle (within one cell of its radius ``d_i``).  On a grid one obstacle
touches that circle in a few adjacent cells, and counting them separately
would let a single wall satisfy "two occupied contact points", so contacts
closer to each other than ``max(2.1, 0.9 d_i)`` cells are one contact point
(the Maximal Inscribed Circle reading of the GVD, Sec. II).

Each contact point ``c_j`` is occupied with its grid probability ``p(c_j)``;
:func:`count_distribution` is the recursion (15)-(17) for the number of
occupied contacts and :func:`pgvd` returns ``p(G_i) = 1 - f(n,0) - f(n,1)``
(23) on the skeleton cells (24).
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage as ndi
from skimage.morphology import skeletonize

from pgvd.morphology import drop_small

#: Offsets of a cell and its 8 neighbours, (row, col).
_NEIGHBOURHOOD = np.array([(dr, dc) for dr in (-1, 0, 1) for dc in (-1, 0, 1)])


def gvd(free: np.ndarray) -> np.ndarray:
    """The GVD ``S`` of eq. (13): the morphological skeleton of the free cells.

    Parameters
    ----------
    free : numpy.ndarray
        (H, W) bool, True where the map is free.

    Returns
    -------
    numpy.ndarray
        (H, W) bool, True on the GVD.

    Raises
    ------
    ValueError
        If ``free`` is not 2-D.

    References
    ----------
    .. [1] Saeedi, S., Paull, L., Trentini, M., Seto, M., and Li, H., "Map merging
       using probabilistic generalized Voronoi diagrams", IROS 2012, eq. (13), Sec. IV-C.
    """
    free = np.asarray(free, dtype=bool)
    if free.ndim != 2:
        raise ValueError(f"gvd needs a 2-D mask, got shape {free.shape}")
    return skeletonize(free)


def contact_points(
    free: np.ndarray, cells: tuple[np.ndarray, np.ndarray], tolerance: float = 1.0
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Contact points (Definition 1) of the given free cells, from an exact EDT.

    Parameters
    ----------
    free : numpy.ndarray
        (H, W) bool free-space mask; every other cell is an obstacle.
    cells : tuple of numpy.ndarray
        ``(rows, cols)`` of the cells (normally the GVD cells), length ``s``.
    tolerance : float, optional
        A candidate contact lies within ``d_i + tolerance`` of the cell,
        ``d_i`` being the cell's exact distance to the nearest obstacle.

    Returns
    -------
    rows, cols : numpy.ndarray
        (s, 9) int arrays of contact cells, padded where ``valid`` is False.
    valid : numpy.ndarray
        (s, 9) bool, the real contact points of each cell (at least one).

    Raises
    ------
    ValueError
        If the map has no free cell or no obstacle cell.

    References
    ----------
    .. [1] Saeedi, S., Paull, L., Trentini, M., Seto, M., and Li, H., "Map merging
       using probabilistic generalized Voronoi diagrams", IROS 2012, Definition 1, Sec. IV-C.
    """
    free = np.asarray(free, dtype=bool)
    rows, cols = (np.asarray(v, dtype=np.intp) for v in cells)
    if not free.any() or free.all():
        raise ValueError("contact_points needs both free and obstacle cells")
    fr, fc = ndi.distance_transform_edt(free, return_distances=False, return_indices=True)
    h, w = free.shape
    nr = np.clip(rows[:, None] + _NEIGHBOURHOOD[:, 0], 0, h - 1)
    nc = np.clip(cols[:, None] + _NEIGHBOURHOOD[:, 1], 0, w - 1)
    cr, cc = fr[nr, nc], fc[nr, nc]
    # each cell's exact distance to its nearest obstacle, from the feature transform as
    # distance_transform_edt derives it (the same sum and root), at these cells only
    dr = (cr[:, 4] - rows).astype(np.float64)
    dc = (cc[:, 4] - cols).astype(np.float64)
    d = np.sqrt(dr * dr + dc * dc)[:, None]
    valid = np.hypot(cr - rows[:, None], cc - cols[:, None]) <= d + tolerance
    # One obstacle touches the inscribed circle in several adjacent cells: keep
    # one contact per obstacle patch (the first in neighbourhood order).
    merge = np.maximum(2.1, 0.9 * d[:, 0])
    # contact j is dropped when an earlier contact i, itself kept, is close to it (one
    # patch): sequential in j, all i < j at once, and only those 36 of the 81 pairs
    for j in range(1, 9):
        close = np.hypot(cr[:, j, None] - cr[:, :j], cc[:, j, None] - cc[:, :j]) < merge[:, None]
        valid[:, j] &= ~np.any(valid[:, :j] & close, axis=1)
    return cr, cc, valid


def count_distribution(p: np.ndarray, max_count: int | None = None) -> np.ndarray:
    """Distribution ``f(n, k)`` of the number of occupied contact points, eqs. (15)-(17).

    Parameters
    ----------
    p : numpy.ndarray
        (s, n) occupancy probabilities of the contact points of ``s`` cells.
        Cells with fewer contacts are padded with 0 (a contact that is surely
        free leaves the distribution unchanged).
    max_count : int, optional
        Only ``k <= max_count``: ``f(j, k)`` needs ``f(j - 1, k - 1)`` and ``f(j - 1, k)``
        alone, so these columns are those of the whole distribution, bit for bit, and
        the PGVD (23), which reads ``k = 0, 1``, needs no more.  Default: every ``k``.

    Returns
    -------
    numpy.ndarray
        (s, m + 1) with ``m = min(n, max_count)``, ``f[i, k] = P(N_i = k)``, eq. (14);
        with every ``k``, every row sums to 1 (Theorem 1).

    Raises
    ------
    ValueError
        If ``p`` is not 2-D or holds values outside [0, 1].

    References
    ----------
    .. [1] Saeedi, S., Paull, L., Trentini, M., Seto, M., and Li, H., "Map merging
       using probabilistic generalized Voronoi diagrams", IROS 2012, eqs. (14)-(18).
    """
    p = np.asarray(p, dtype=np.float64)
    if p.ndim != 2:
        raise ValueError(f"count_distribution needs (cells, contacts), got shape {p.shape}")
    if np.any((p < 0) | (p > 1)) or not np.all(np.isfinite(p)):
        raise ValueError("contact probabilities must lie in [0, 1]")
    if max_count is not None and max_count < 0:
        raise ValueError(f"max_count must be >= 0, got {max_count}")
    s, n = p.shape
    m = n if max_count is None else min(n, max_count)
    f = np.zeros((s, m + 1))
    f[:, 0] = 1.0
    for j in range(n):
        pj = p[:, j : j + 1]
        top = min(j + 1, m)  # the highest k that step j changes
        # eq. (15): f(j, k) = p(c_j) f(j-1, k-1) + (1 - p(c_j)) f(j-1, k), from k = j down.
        f[:, 1 : top + 1] = pj * f[:, :top] + (1.0 - pj) * f[:, 1 : top + 1]
        f[:, 0] *= 1.0 - pj[:, 0]
    return f


def free_space(prob: np.ndarray, free_threshold: float = 0.3, min_area: int = 8) -> np.ndarray:
    """Free cells of a probability grid, cleaned for the skeleton.

    Isolated free specks (fewer than ``min_area`` cells) are dropped and
    obstacle islands of fewer than ``min_area`` cells are filled, so that noise
    does not add GVD branches and loops.

    Parameters
    ----------
    prob : numpy.ndarray
        (H, W) occupancy probabilities.
    free_threshold : float, optional
        Cells below this probability are free.
    min_area : int, optional
        Free specks and obstacle islands up to this many cells are removed.

    Returns
    -------
    numpy.ndarray
        (H, W) bool free-space mask.
    """
    free = np.asarray(prob) < free_threshold
    free = drop_small(free, min_area)
    # A hole is a small component of the complement, as in skimage's remove_small_holes.
    return ~drop_small(~free, min_area)


def pgvd(
    prob: np.ndarray, free_threshold: float = 0.3, min_area: int = 8
) -> tuple[np.ndarray, np.ndarray]:
    """The GVD and the probabilistic GVD of an occupancy grid, eqs. (13)-(24).

    Parameters
    ----------
    prob : numpy.ndarray
        (H, W) occupancy probabilities (0.5 = unknown).
    free_threshold : float, optional
        Cells below this probability are free.
    min_area : int, optional
        See :func:`free_space`.

    Returns
    -------
    S : numpy.ndarray
        (H, W) bool GVD, eq. (13).
    Sp : numpy.ndarray
        (H, W) float, ``p(G_i) = 1 - f(n_i, 0) - f(n_i, 1)`` on the GVD (23)-(24),
        0 elsewhere.

    Raises
    ------
    ValueError
        If ``prob`` is not 2-D.

    References
    ----------
    .. [1] Saeedi, S., Paull, L., Trentini, M., Seto, M., and Li, H., "Map merging
       using probabilistic generalized Voronoi diagrams", IROS 2012, eqs. (13)-(24).
    """
    prob = np.asarray(prob, dtype=np.float64)
    if prob.ndim != 2:
        raise ValueError(f"pgvd needs a 2-D grid, got shape {prob.shape}")
    free = free_space(prob, free_threshold, min_area)
    s = gvd(free)
    sp = np.zeros(prob.shape)
    if not s.any() or free.all():
        return s, sp
    cells = np.nonzero(s)
    cr, cc, valid = contact_points(free, cells)
    pc = np.where(valid, np.clip(prob[cr, cc], 0.0, 1.0), 0.0)
    f = count_distribution(pc, max_count=1)
    sp[cells] = np.clip(1.0 - f[:, 0] - f[:, 1], 0.0, 1.0)
    return s, sp
