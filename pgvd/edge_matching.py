"""Edge matching (25)-(32): Gamma by batched FFT, the existence test rho, and pair support.

* :func:`similarity` builds the similarity matrix Gamma (27) from the 2-D
  cross-correlations (26) of every pair of probabilistic edge sub-matrices
  (25), batched by size class and computed with real FFTs; the peak of each
  correlation gives that pair's translation (29).  A's edges are grey-dilated
  by ``tolerance`` cells first, so a skeleton that moved by one cell between
  the two maps still matches; ``max(E)`` then stays ``alpha_1 alpha_2 L`` with
  ``L`` the number of matched cells within that tolerance (31).
* :func:`rho_test` is the existence test (32).
* :func:`pair_support` re-evaluates every edge pair at one translation, so a
  translation counts only when *several* edge pairs pass (32) there.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import fft as sfft

from pgvd.graph import Edge
from pgvd.morphology import grow_max

#: Upper bound on complex cells of one batched correlation block (memory, not speed).
_BLOCK_CELLS = 1 << 21
#: Weight of the undilated edge inside a tolerance-dilated one (breaks ties, see _dilated).
_TIE_BREAK = 1e-3


@dataclass(frozen=True)
class Similarity:
    """Gamma (27) with the translation of each pair's correlation peak (29).

    Attributes
    ----------
    gamma : (N1, N2) ``max(E(i1, i2))``.
    shift : (N1, N2, 2) ``(tx, ty)`` moving B's edge onto A's edge at the peak (B -> A, cells).
    """

    gamma: np.ndarray
    shift: np.ndarray


def _size_class(h: int, w: int) -> tuple[int, int]:
    return max(8, 1 << (h - 1).bit_length()), max(8, 1 << (w - 1).bit_length())


def _dilated(edge: Edge, tolerance: int) -> tuple[np.ndarray, tuple[int, int]]:
    """A's edge grey-dilated by ``tolerance`` cells (and its new origin).

    A small share of the undilated edge is kept on top so that the exact
    alignment wins the plateau of equally good shifts the dilation creates.
    """
    if tolerance <= 0:
        return edge.matrix, edge.origin
    padded = np.pad(edge.matrix, tolerance)
    m = (1.0 - _TIE_BREAK) * grow_max(padded, tolerance)
    m += _TIE_BREAK * padded
    return m, (edge.origin[0] - tolerance, edge.origin[1] - tolerance)


def _groups(mats: list[np.ndarray]) -> dict[tuple[int, int], list[int]]:
    groups: dict[tuple[int, int], list[int]] = {}
    for i, m in enumerate(mats):
        groups.setdefault(_size_class(*m.shape), []).append(i)
    return groups


def _stack(mats: list[np.ndarray], idx: list[int], size: tuple[int, int]) -> np.ndarray:
    out = np.zeros((len(idx), *size), dtype=np.float32)
    for k, i in enumerate(idx):
        h, w = mats[i].shape
        out[k, :h, :w] = mats[i]
    return out


class EdgeCorrelator:
    """A's probabilistic edges (25), ready to be correlated (26) with any number of B edge sets.

    A's tolerance-dilated sub-matrices, their size classes and their spectra
    (per FFT size) are kept, so that trying several candidate headings of B
    costs one pass over B's edges each.
    """

    def __init__(self, edges_a: list[Edge], tolerance: int = 1) -> None:
        dil = [_dilated(e, tolerance) for e in edges_a]
        self.mats = [m for m, _ in dil]
        self.origins = np.array([o for _, o in dil], dtype=float).reshape(-1, 2)
        self.groups = _groups(self.mats)
        self._spectra: dict[tuple[tuple[int, int], tuple[int, int]], np.ndarray] = {}
        self._edge_map: tuple[np.ndarray, np.ndarray] | None = None

    def edge_map(self, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
        """(label, value) maps of A's dilated edges over a map of ``shape`` (label -1: none).

        Where dilated edges overlap, the larger value (and its edge) wins.
        """
        if self._edge_map is None or self._edge_map[0].shape != shape:
            value = np.zeros(shape)
            label = np.full(shape, -1, dtype=np.int64)
            h, w = shape
            for i, (m, (r0, c0)) in enumerate(
                zip(self.mats, self.origins.astype(int), strict=True)
            ):
                rs = slice(max(r0, 0), min(r0 + m.shape[0], h))
                cs = slice(max(c0, 0), min(c0 + m.shape[1], w))
                sub = m[rs.start - r0 : rs.stop - r0, cs.start - c0 : cs.stop - c0]
                better = sub > value[rs, cs]
                value[rs, cs][better] = sub[better]
                label[rs, cs][better] = i
            self._edge_map = (label, value)
        return self._edge_map

    def _spectrum(self, ka: tuple[int, int], size: tuple[int, int]) -> np.ndarray:
        key = (ka, size)
        if key not in self._spectra:
            self._spectra[key] = sfft.rfft2(_stack(self.mats, self.groups[ka], ka), s=size)
        return self._spectra[key]

    def similarity(self, edges_b: list[Edge]) -> Similarity:
        """Gamma (27) against B's edges and each pair's peak translation (29)."""
        na, nb = len(self.mats), len(edges_b)
        gamma = np.zeros((na, nb))
        shift = np.zeros((na, nb, 2))
        if na == 0 or nb == 0:
            return Similarity(gamma, shift)
        mats_b = [e.matrix for e in edges_b]
        groups_b = _groups(mats_b)
        # Peaks are written in size-class order, where every block is a plain
        # slice, and put back in edge order once at the end; so are the flat
        # indices of the peaks, turned into shifts once for all blocks.
        peak, at = np.zeros((na, nb)), np.zeros((na, nb), dtype=np.intp)
        b0 = 0
        for kb, ib in groups_b.items():
            stack_b = _stack(mats_b, ib, kb)
            cols = slice(b0, b0 + len(ib))
            a0 = 0
            for ka, ia in self.groups.items():
                size = (ka[0] + kb[0], ka[1] + kb[1])
                fb = np.conj(sfft.rfft2(stack_b, s=size))
                fa_all = self._spectrum(ka, size)
                chunk = max(1, _BLOCK_CELLS // (len(ib) * size[0] * (size[1] // 2 + 1)))
                for start in range(0, len(ia), chunk):
                    corr = sfft.irfft2(fa_all[start : start + chunk, None] * fb[None], s=size)
                    flat = corr.reshape(corr.shape[0], len(ib), -1)
                    rows = slice(a0 + start, a0 + start + corr.shape[0])
                    # the value at the first maximum is the maximum: one pass, not two
                    best = flat.argmax(axis=2)
                    at[rows, cols] = best
                    peak[rows, cols] = np.take_along_axis(flat, best[..., None], axis=2)[..., 0]
                a0 += len(ia)
            b0 += len(ib)
        # the size class of every row (A's edges) and column (B's), in size-class order:
        # a block's FFT size is the sum of the two
        class_a, class_b = (
            np.array([k for k, idx in g.items() for _ in idx]).reshape(-1, 2)
            for g in (self.groups, groups_b)
        )
        size0, size1 = class_a[:, :1] + class_b[:, 0], class_a[:, 1:] + class_b[:, 1]
        du, dv = np.divmod(at, size1)
        u = np.where(du < class_a[:, :1], du, du - size0)
        v = np.where(dv < class_a[:, 1:], dv, dv - size1)
        order = np.ix_(*(np.concatenate(list(g.values())) for g in (self.groups, groups_b)))
        gamma[order], shift[..., 0][order], shift[..., 1][order] = peak, v, u
        org_b = np.array([e.origin for e in edges_b], dtype=float)
        shift[..., 0] += self.origins[:, 1][:, None] - org_b[:, 1][None]
        shift[..., 1] += self.origins[:, 0][:, None] - org_b[:, 0][None]
        return Similarity(gamma, shift)


def similarity(edges_a: list[Edge], edges_b: list[Edge], tolerance: int = 1) -> Similarity:
    """Similarity matrix Gamma (27) by batched FFT cross-correlation (26) of edge sub-matrices.

    Edges are batched by size class (powers of two); every pair of classes
    is one stack of real FFTs, so there is no Python loop over edge pairs.

    Parameters
    ----------
    edges_a, edges_b : list of Edge
        Probabilistic edges (25) of the two maps in a common orientation.
    tolerance : int, optional
        A's edges are grey-dilated by this many cells before correlating.

    Returns
    -------
    Similarity
        Gamma and, per pair, the translation ``(tx, ty)`` at the correlation
        peak: B's edge cell ``(x, y)`` lands on A's edge at ``(x + tx, y + ty)``.

    References
    ----------
    .. [1] Saeedi, S., Paull, L., Trentini, M., Seto, M., and Li, H., "Map merging
       using probabilistic generalized Voronoi diagrams", IROS 2012, eqs. (25)-(29).
    """
    return EdgeCorrelator(edges_a, tolerance).similarity(edges_b)


def rho_threshold(edges_a: list[Edge], edges_b: list[Edge], rho: float) -> np.ndarray:
    """Right-hand side of (32): ``rho * alpha_1 * alpha_2 * min(l_1, l_2)`` for every pair.

    Parameters
    ----------
    edges_a, edges_b : list of Edge
        The edges; ``confidence`` is ``alpha`` (31), ``length`` is ``l``.
    rho : float
        Matching percentage.

    Returns
    -------
    numpy.ndarray
        (N1, N2) thresholds.

    References
    ----------
    .. [1] Saeedi, S., Paull, L., Trentini, M., Seto, M., and Li, H., "Map merging
       using probabilistic generalized Voronoi diagrams", IROS 2012, eqs. (31)-(32).
    """
    alpha_a = np.array([e.confidence for e in edges_a])
    alpha_b = np.array([e.confidence for e in edges_b])
    len_a = np.array([e.length for e in edges_a], dtype=float)
    len_b = np.array([e.length for e in edges_b], dtype=float)
    return rho * np.outer(alpha_a, alpha_b) * np.minimum.outer(len_a, len_b)


def rho_test(gamma: np.ndarray, edges_a: list[Edge], edges_b: list[Edge], rho: float) -> np.ndarray:
    """Existence test (32): pairs with ``max(E) > rho alpha_1 alpha_2 min(l1, l2)``.

    Parameters
    ----------
    gamma : numpy.ndarray
        (N1, N2) similarity matrix Gamma, eq. (27).
    edges_a, edges_b : list of Edge
        The edges Gamma was computed from.
    rho : float
        Matching percentage, in (0, 1].

    Returns
    -------
    numpy.ndarray
        (N1, N2) bool; no True entry means the maps do not match.

    Raises
    ------
    ValueError
        If ``rho`` is outside (0, 1].

    References
    ----------
    .. [1] Saeedi, S., Paull, L., Trentini, M., Seto, M., and Li, H., "Map merging
       using probabilistic generalized Voronoi diagrams", IROS 2012, eqs. (31)-(32), Sec. IV-E.1.
    """
    if not 0.0 < rho <= 1.0:
        raise ValueError(f"rho must lie in (0, 1], got {rho}")
    return gamma > rho_threshold(edges_a, edges_b, rho)


class PairSupport:
    """Evaluates the correlation of every edge pair at given translations, sparsely.

    ``E_(i1,i2)(t)`` of (26) at one ``t`` is a sum over B's edge cells, so
    all pairs are computed at once by looking B's cells up in A's dilated
    edge matrix: ``O(cells of B)`` per translation instead of an FFT.
    """

    def __init__(
        self, correlator: EdgeCorrelator, shape_a: tuple[int, int], edges_b: list[Edge]
    ) -> None:
        self.label, self.value = correlator.edge_map(shape_a)
        cells = [e.cells() for e in edges_b]
        self.rows = np.concatenate([r for r, _ in cells]) if cells else np.zeros(0, int)
        self.cols = np.concatenate([c for _, c in cells]) if cells else np.zeros(0, int)
        self.owner = np.repeat(np.arange(len(edges_b)), [r.size for r, _ in cells])
        self.weight = (
            np.concatenate([e.matrix[e.matrix > 0] for e in edges_b]) if cells else np.zeros(0)
        )
        self.na, self.nb = len(correlator.mats), len(edges_b)

    def correlations(self, ts: list[tuple[int, int]]) -> np.ndarray:
        """(T, N1, N2): the matrix of ``E_(i1,i2)`` at each translation ``t = (tx, ty)`` of
        ``ts``, in one pass.

        One bincount for all translations instead of one each; every sum adds the
        same terms in the same order, so each matrix is the one a list of that
        translation alone gives.
        """
        h, w = self.value.shape
        t = np.asarray(ts, dtype=np.int64).reshape(-1, 2)
        r, c = self.rows + t[:, 1:], self.cols + t[:, :1]
        # (translation, cell) of every B cell that lands on an edge of A, translation by
        # translation and each in cell order
        which, cell = np.nonzero((r >= 0) & (r < h) & (c >= 0) & (c < w))
        r, c = r[which, cell], c[which, cell]
        lab = self.label[r, c]
        hit = lab >= 0
        which, cell, r, c = which[hit], cell[hit], r[hit], c[hit]
        pairs = self.na * self.nb
        keys = which * pairs + lab[hit] * self.nb + self.owner[cell]
        vals = self.weight[cell] * self.value[r, c]
        return np.bincount(keys, vals, len(t) * pairs).reshape(len(t), self.na, self.nb)


def pair_support(passing: np.ndarray) -> int:
    """Number of distinct edge pairs in a pass mask, counting each edge of either map once."""
    ia, ib = np.nonzero(passing)
    return int(min(np.unique(ia).size, np.unique(ib).size))
