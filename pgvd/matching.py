"""Edge matching (25)-(32), the verification the paper leaves to future work, and refinement.

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
* :func:`map_agreement` overlays the whole maps: walls of one map that fall
  on walls of the other agree, walls that fall on clear free space disagree.
* :func:`refine` aligns the wall cells at full resolution (trimmed ICP);
  :func:`alignment_fit` gives the curvature of the alignment cost at its
  minimum, and :func:`calibrated_covariance` turns it into a covariance (a
  Laplace approximation inflated by the residual misfit, its heading widened,
  with constants fitted on real pairs) that matches the errors the merge makes.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy import fft as sfft
from scipy.spatial import cKDTree

from pgvd.graph import Edge
from pgvd.grid import heading, rigid_matrix
from pgvd.morphology import grow, grow_max, surface
from pgvd.sampling import subsample

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


@dataclass(frozen=True)
class Agreement:
    """Whole-map consistency counts of an overlay.

    Attributes
    ----------
    agree : wall cells of either map landing within the tolerance of a wall of the other.
    disagree : wall cells of either map landing on clear free space of the other.
    """

    agree: int
    disagree: int

    @property
    def ratio(self) -> float:
        """``agree / (agree + disagree)``, 0 without overlap."""
        total = self.agree + self.disagree
        return self.agree / total if total else 0.0


class MapView:
    """A coarse map prepared for :class:`OverlayScores`: wall, near-wall and free masks.

    ``near`` is the walls dilated by ``tolerance`` cells; ``clear`` is free
    space farther than ``2 tolerance`` cells from any wall, so that a wall
    that is off by the tolerance never counts as a disagreement; ``free`` is
    every free cell.
    """

    def __init__(self, prob: np.ndarray, occupied: float, free: float, tolerance: int) -> None:
        prob = np.asarray(prob)
        self.occ = prob > occupied
        self.near = grow(self.occ, tolerance)
        self.free = prob < free
        # growing ``near`` once more is the two-fold dilation of the walls, one pass cheaper
        self.clear = self.free & ~grow(self.near, tolerance)
        self.shape = prob.shape


@dataclass(frozen=True)
class OverlayWeights:
    """How the counts of an :class:`Overlay` add up to one evidence per translation.

    ``evidence = agree + free * free_agree - conflict * disagree``.

    Attributes
    ----------
    conflict : weight of a wall on clear free space of the other map.
    free : weight of a cell free in both maps.
    """

    conflict: float = 1.0
    free: float = 0.0


#: ``agree - disagree``: walls only, each conflict weighed as one agreeing wall.
WALLS_ONLY = OverlayWeights()


@dataclass(frozen=True)
class Overlay:
    """Agreement and disagreement counts of B on A for every integer translation.

    Attributes
    ----------
    agree, disagree : arrays indexed by ``(ty mod size[0], tx mod size[1])``.
    free_agree : cells free in both maps, indexed the same way (None when not counted).
    shape_a, shape_b : shapes of the two maps (bounds of meaningful translations).
    """

    agree: np.ndarray
    disagree: np.ndarray
    free_agree: np.ndarray | None
    shape_a: tuple[int, int]
    shape_b: tuple[int, int]
    _evidence: dict[OverlayWeights, np.ndarray] = field(
        default_factory=dict, repr=False, compare=False
    )

    def evidence(self, weights: OverlayWeights = WALLS_ONLY) -> np.ndarray:
        """``agree + free free_agree - conflict disagree`` for every translation (kept per
        weights)."""
        if weights not in self._evidence:
            ev = self.agree - weights.conflict * self.disagree
            if weights.free:
                if self.free_agree is None:
                    raise ValueError("free space was not counted: use OverlayScores(a, free=True)")
                ev = ev + weights.free * self.free_agree
            ev.setflags(write=False)
            self._evidence[weights] = ev
        return self._evidence[weights]

    def _index(self, t: tuple[int, int]) -> tuple[int, int]:
        return t[1] % self.agree.shape[0], t[0] % self.agree.shape[1]

    def at(self, t: tuple[int, int]) -> Agreement:
        """Counts at the translation ``t = (tx, ty)``."""
        idx = self._index(t)
        return Agreement(int(self.agree[idx]), int(self.disagree[idx]))

    def evidence_at(self, t: tuple[int, int], weights: OverlayWeights = WALLS_ONLY) -> float:
        """The evidence of :meth:`evidence` at the translation ``t = (tx, ty)``."""
        return float(self.evidence(weights)[self._index(t)])

    def best_evidence(self, weights: OverlayWeights = WALLS_ONLY) -> float:
        """Largest evidence (:meth:`evidence`) over all translations."""
        return float(np.max(self.evidence(weights)))

    def peaks(
        self, n: int, radius: int, weights: OverlayWeights = WALLS_ONLY
    ) -> list[tuple[int, int]]:
        """Translations of the largest overlay evidence that are local maxima.

        Parameters
        ----------
        n : int
            Number of translations returned at most.
        radius : int
            A peak is the largest evidence within this many cells.
        weights : OverlayWeights, optional
            How the counts add up to the evidence (:meth:`evidence`).

        Returns
        -------
        list of tuple of int
            ``(tx, ty)``, best first; only translations with positive evidence.
        """
        if n <= 0:
            return []
        ev = self.evidence(weights)
        top = _wrapped_max(ev, radius)
        rows, cols = np.nonzero((ev == top) & (ev > 0))
        order = np.argsort(-ev[rows, cols], kind="stable")[:n]
        (ha, wa), h, w = self.shape_a, *ev.shape
        out = []
        for r, c in zip(rows[order], cols[order], strict=True):
            ty = int(r) if r < ha else int(r) - h
            tx = int(c) if c < wa else int(c) - w
            out.append((tx, ty))
        return out

    def best_near_each(
        self, ts: list[tuple[int, int]], radius: int, weights: OverlayWeights = WALLS_ONLY
    ) -> list[tuple[int, int]]:
        """For every translation ``t`` of ``ts``, the translation ``(tx, ty)`` within
        ``radius`` of it of largest evidence (:meth:`evidence`), all windows read at once.

        A window's translations beyond the overlap (none of B on A) are skipped; the
        first largest in row-major order wins, as in the window cut to the overlap.  A
        ``t`` whose window has none within the overlap is returned as it is.
        """
        if not ts:
            return []
        (ha, wa), (hb, wb) = self.shape_a, self.shape_b
        t = np.asarray(ts, dtype=np.int64).reshape(-1, 2)
        step = np.arange(-radius, radius + 1)
        ty, tx = t[:, 1:] + step, t[:, :1] + step
        rows_in, cols_in = (ty >= 1 - hb) & (ty <= ha - 1), (tx >= 1 - wb) & (tx <= wa - 1)
        inside = rows_in[:, :, None] & cols_in[:, None, :]
        ev = self.evidence(weights)
        window = ev[(ty % ev.shape[0])[:, :, None], (tx % ev.shape[1])[:, None, :]]
        window = np.where(inside, window, -np.inf).reshape(len(t), -1)
        i, j = np.divmod(window.argmax(axis=1), step.size)
        rows = np.arange(len(t))
        found = inside.reshape(len(t), -1).any(axis=1)
        return [
            (int(x), int(y)) if ok else (int(t0[0]), int(t0[1]))
            for x, y, ok, t0 in zip(tx[rows, j], ty[rows, i], found, t, strict=True)
        ]


def _wrapped_max(values: np.ndarray, radius: int) -> np.ndarray:
    """The largest value within ``radius`` cells (a square) of each cell, the array wrapping
    around (``scipy.ndimage.maximum_filter(values, 2 radius + 1, mode="wrap")``).

    OpenCV's dilation of the wrap-padded array: a maximum is exact whichever way it
    is taken, and this one costs about half as much on the overlays of a merge.
    """
    import cv2

    padded = np.pad(values, radius, mode="wrap")
    top = cv2.dilate(padded, np.ones((2 * radius + 1, 2 * radius + 1), np.uint8))
    return top[radius : radius + values.shape[0], radius : radius + values.shape[1]]


class OverlayScores:
    """Dense form of :func:`map_agreement` for translations only, by FFT.

    ``agree(t)`` counts B's walls on A's near-wall cells plus A's walls on
    B's, ``disagree(t)`` the walls on the other map's clear free space,
    ``free_agree(t)`` the cells free in both, when ``free`` (one FFT more per
    overlay).  A's spectra are cached per FFT size and reused for every rotated B.
    """

    def __init__(self, a: MapView, free: bool = False) -> None:
        self.a = a
        self.layers = ("near", "clear", "occ", "free") if free else ("near", "clear", "occ")
        self._fa: dict[tuple[int, int], dict[str, np.ndarray]] = {}

    def _spectra(self, view: MapView, size: tuple[int, int]) -> dict[str, np.ndarray]:
        return {k: sfft.rfft2(getattr(view, k).astype(np.float32), s=size) for k in self.layers}

    def overlay(self, b: MapView) -> Overlay:
        """Agreement and disagreement of ``b`` on A for all translations."""
        size = tuple(
            sfft.next_fast_len(sa + sb) for sa, sb in zip(self.a.shape, b.shape, strict=True)
        )
        if size not in self._fa:
            self._fa[size] = self._spectra(self.a, size)
        fa = self._fa[size]
        fb = {k: np.conj(v) for k, v in self._spectra(b, size).items()}
        agree = sfft.irfft2(fa["near"] * fb["occ"] + fa["occ"] * fb["near"], s=size)
        disagree = sfft.irfft2(fa["clear"] * fb["occ"] + fa["occ"] * fb["clear"], s=size)
        free = np.rint(sfft.irfft2(fa["free"] * fb["free"], s=size)) if "free" in fa else None
        return Overlay(np.rint(agree), np.rint(disagree), free, self.a.shape, b.shape)


def _apply(m: np.ndarray, pts: np.ndarray) -> np.ndarray:
    return pts @ m[:2, :2].T + m[:2, 2]


class WallTree(cKDTree):
    """A k-d tree of wall cells ``(x, y)`` that keeps each cell's wall normal once computed.

    The point-to-line stages ask for the normals at the nearest wall cells
    over and over (every Gauss-Newton step, the residual distortion, the
    covariance); a normal depends on its cell alone, so each is computed once.
    """

    def __init__(self, walls: np.ndarray) -> None:
        # the sliding-midpoint tree builds in half the time and answers these
        # nearest-wall queries faster than the median-split default
        super().__init__(walls, balanced_tree=False, compact_nodes=False)
        self._normal = np.full((self.n, 2), np.nan)

    def normals(self, idx: np.ndarray) -> np.ndarray:
        """Unit wall normals at the cells ``idx`` of the tree (see :func:`_normals`)."""
        missing = np.unique(idx[np.isnan(self._normal[idx, 0])])
        if missing.size:
            self._normal[missing] = _normals(self, self.data[missing])
        return self._normal[idx]


class WallMap:
    """A full-resolution map for overlay checks: its probabilities and a k-d tree of its walls.

    With ``lookup``, nearest-wall queries (:meth:`nearest`) read a table of
    every cell's nearest wall cell instead of the tree, built on first use
    from a distance transform: an O(1) lookup a point for a transform of the
    whole map, which pays for the map every hypothesis is scored against
    (A), not for one only counted once per hypothesis (B).
    """

    def __init__(
        self, prob: np.ndarray, occupied: float, free: float, lookup: bool = False
    ) -> None:
        prob = np.asarray(prob)
        self.free = prob < free
        # only the faces of walls: inside a thick wall every cell has a wall cell at
        # distance 0, so the alignment cost is flat there and a refinement stops
        # wherever it enters (intel's map with 5-cell walls, merged onto a crop of
        # itself, came out 2.5 px off); thin walls, as a laser draws them, are all
        # face.  A map that is wall from edge to edge has no face: its wall cells
        # are all it has.
        walls = prob > occupied
        faces = surface(walls)
        # flat indices split by divmod: the same cells in the same (row-major) order as
        # np.nonzero, which is ~8x slower on a full-resolution map
        self._flat = np.flatnonzero(faces if faces.any() else walls)
        r, c = np.divmod(self._flat, prob.shape[1])
        self.walls = np.column_stack([c, r]).astype(float)
        self._x, self._y = c.astype(float), r.astype(float)
        self.tree = WallTree(self.walls)
        self.lookup = lookup
        self._table: np.ndarray | None = None

    def normals(self, idx: np.ndarray) -> np.ndarray:
        """Unit wall normals (:func:`_normals`) at the wall cells ``idx``, computed once each."""
        return self.tree.normals(idx)

    def _nearest_table(self) -> np.ndarray:
        """(H + 1, W + 1) index into :attr:`walls` of each cell's nearest wall cell (built
        once); the last row and column repeat the ones before."""
        if self._table is None:
            import cv2

            h, w = self.free.shape
            open_cells = np.ones((h, w), np.uint8)
            open_cells.flat[self._flat] = 0
            # one more row and column (copies of the last) so that every point has four
            # cells around it in the table.  The labels are written straight into the
            # table and made to count from 0 in place: no map-sized copy (17 MB at 2000^2)
            table = np.empty((h + 1, w + 1), np.int32)
            inner = table[:h, :w]
            # each wall cell is its own label, numbered from 1 in row-major order: the
            # order of self.walls.  The 5x5 chamfer transform finds a nearest wall to
            # within a few per cent of the distance; nearest() measures it exactly.
            _, label = cv2.distanceTransformWithLabels(
                open_cells, cv2.DIST_L2, 5, labels=inner, labelType=cv2.DIST_LABEL_PIXEL
            )
            if not np.shares_memory(label, table):  # an OpenCV that returned a new array
                inner[...] = label
            np.subtract(inner, 1, out=inner)
            table[:h, w] = table[:h, w - 1]
            table[h] = table[h - 1]
            self._table = table
        return self._table

    def nearest(self, points: np.ndarray, reach: float) -> tuple[np.ndarray, np.ndarray]:
        """Distance and index of a nearest wall cell of each point ``(x, y)``, within ``reach``.

        With ``lookup``, the wall is the nearest of those the table names for
        the four cells around the point (a point off the map: the cells on
        it nearest to it), at its exact distance.  Over the map it is the
        nearest wall for ~99.5 % of points and otherwise a fraction of a cell
        farther; off the map it can be farther by more.  As
        ``cKDTree.query``: ``inf`` and ``len(walls)`` beyond ``reach``.
        """
        if not self.lookup:
            return self.tree.query(points, distance_upper_bound=reach)
        n = len(self.walls)
        if n == 0 or len(points) == 0:
            return np.full(len(points), np.inf), np.full(len(points), n)
        table = self._nearest_table()
        h, w = table.shape
        px, py = points[:, 0], points[:, 1]
        # the cell at the lower corner of the point; the table's extra last row and
        # column make its right and lower neighbours valid cells too
        col = np.clip(np.floor(px), 0, w - 2).astype(np.intp)
        row = np.clip(np.floor(py), 0, h - 2).astype(np.intp)
        # the four candidates of every point, one corner a row (contiguous), squared
        # distances in place, then a scan of the corners that keeps the first of equals
        # (argmin's choice, without its per-point loop over a short axis)
        corners = np.array([0, 1, w, w + 1])[:, None] + (row * w + col)
        cand = table.ravel()[corners]
        d2 = self._x[cand]
        d2 -= px
        d2 *= d2
        dy = self._y[cand]
        dy -= py
        dy *= dy
        d2 += dy
        best, idx = d2[0], cand[0]
        for k in (1, 2, 3):
            closer = d2[k] < best
            best = np.where(closer, d2[k], best)
            idx = np.where(closer, cand[k], idx)
        idx = idx.astype(np.intp)
        dist = np.sqrt(best)
        far = dist > reach
        dist[far], idx[far] = np.inf, n
        return dist, idx

    def count(self, points: np.ndarray, tolerance: float) -> tuple[int, int]:
        """(agree, disagree) of another map's wall points ``(N, 2)`` (x, y) in this frame.

        A point agrees within ``tolerance`` of a wall here and disagrees on a
        free cell farther than ``2 tolerance`` from every wall.
        """
        dist, _ = self.nearest(points, 2 * tolerance + 1e-9)
        ij = np.rint(points).astype(np.int64)
        h, w = self.free.shape
        inside = (ij[:, 0] >= 0) & (ij[:, 0] < w) & (ij[:, 1] >= 0) & (ij[:, 1] < h)
        free = np.zeros(len(points), bool)
        free[inside] = self.free[ij[inside, 1], ij[inside, 0]]
        return int(np.sum(dist <= tolerance)), int(np.sum(free & ~np.isfinite(dist)))


Walls = cKDTree | WallMap
"""A's walls for the alignment stages: a k-d tree of wall cells, or a :class:`WallMap`."""


def _query(walls_a: Walls, points: np.ndarray, reach: float) -> tuple[np.ndarray, np.ndarray]:
    """Nearest wall cell of each point within ``reach``: (distance, index), as ``cKDTree.query``."""
    if isinstance(walls_a, WallMap):
        return walls_a.nearest(points, reach)
    return walls_a.query(points, distance_upper_bound=reach)


def _cells_of(walls_a: Walls) -> np.ndarray:
    """(N, 2) wall cells ``(x, y)`` that :func:`_query` indexes."""
    return walls_a.walls if isinstance(walls_a, WallMap) else walls_a.data


def map_agreement(
    a: WallMap,
    b: WallMap,
    matrix: np.ndarray,
    tolerance: float = 2.0,
    max_points: int = 0,
    scaled: bool = False,
) -> Agreement:
    """Overlay B on A with the B->A pixel ``matrix`` and count agreement both ways.

    This is the check the paper leaves to future work (Sec. VI): a transform
    counts only if the whole maps agree once overlaid.

    Parameters
    ----------
    a, b : WallMap
        Wall cells and free space of the two maps.
    matrix : numpy.ndarray
        3x3, B pixel -> A pixel.
    tolerance : float, optional
        A wall within this many cells of a wall of the other map agrees.
    max_points : int, optional
        When > 0, an even subsample of each map's walls of about this size
        is evaluated (a quick estimate).
    scaled : bool, optional
        Count each subsampled wall cell for the cells between it and the next,
        so that the counts estimate those of all walls.

    Returns
    -------
    Agreement
        Agreeing walls and walls on clear free space, summed over both directions.
    """
    wb, wa = b.walls, a.walls
    if max_points > 0:
        wb, wa = subsample(wb, max_points), subsample(wa, max_points)
    ag1, dis1 = a.count(_apply(matrix, wb), tolerance)
    ag2, dis2 = b.count(_apply(np.linalg.inv(matrix), wa), tolerance)
    if not scaled:
        return Agreement(ag1 + ag2, dis1 + dis2)
    sb, sa = len(b.walls) / max(1, len(wb)), len(a.walls) / max(1, len(wa))
    return Agreement(round(ag1 * sb + ag2 * sa), round(dis1 * sb + dis2 * sa))


def _cells(points: np.ndarray, block: float) -> np.ndarray:
    """One int64 code per point for the ``block`` square it falls in."""
    keys = np.floor(points / block).astype(np.int64)
    return (keys[:, 0] << 32) + keys[:, 1]


def _block_shifts(
    a: WallMap, moved: np.ndarray, group: np.ndarray, max_shift: float, iterations: int = 2
) -> np.ndarray:
    """The translation of each square that re-aligns its points ``moved`` on A's walls.

    Within each square (``group`` indexes the squares of the points) the
    translation ``d`` minimises the point-to-line misfit
    ``sum (n_i . (d - r_i))^2`` of the points within ``max_shift + 2`` of A's
    walls (``n_i`` A's wall normal at the nearest wall cell, ``r_i`` the
    offset to it), refitted once from the shifted points, as in
    :func:`residual_distortion`.  A ridge keeps a square whose walls all run
    one way from sliding along them; ``|d|`` is capped at ``max_shift``.

    Returns
    -------
    numpy.ndarray
        ``(n_squares, 2)``; 0 for a square with no point near A's walls.
    """
    n_groups = int(group.max()) + 1
    d = np.zeros((n_groups, 2))
    count = np.bincount(group, minlength=n_groups)
    ridge = 0.1 * np.maximum(count, 1)
    for it in range(iterations):
        pts = moved + d[group]
        # the first pass reaches as far as the shift may go; later ones only refine it
        reach = max_shift + 2.0 if it == 0 else 3.0
        dist, idx = a.nearest(pts, reach)
        ok = np.isfinite(dist)
        if not ok.any():
            break
        g, n = group[ok], a.normals(idx[ok])
        r = np.sum(n * (a.walls[idx[ok]] - pts[ok]), axis=1)
        sxx, sxy, syy, bx, by = (
            np.bincount(g, v, minlength=n_groups)
            for v in (n[:, 0] ** 2, n[:, 0] * n[:, 1], n[:, 1] ** 2, n[:, 0] * r, n[:, 1] * r)
        )
        sxx, syy = sxx + ridge, syy + ridge
        det = sxx * syy - sxy**2
        d += np.column_stack([syy * bx - sxy * by, sxx * by - sxy * bx]) / det[:, None]
        norm = np.hypot(d[:, 0], d[:, 1])
        d *= np.minimum(1.0, max_shift / np.maximum(norm, 1e-12))[:, None]
    return d


def local_agreement(
    a: WallMap,
    b: WallMap,
    matrix: np.ndarray,
    block: float,
    max_shift: float,
    tolerance: float = 2.0,
    max_points: int = 0,
) -> Agreement:
    """:func:`map_agreement` after a small re-alignment of every ``block`` square of the overlap.

    A drifted map has no single rigid fit: after the best rigid ``matrix``
    its walls still run a few cells beside A's away from the overlap's
    centre, and a plain count calls them walls on free space.  Here B's
    walls, moved into A, are cut into squares of A's frame and each square
    is shifted by its own translation (at most ``max_shift``, fitted
    point-to-line, :func:`_block_shifts`) before counting; A's walls in a
    square are moved back by the same shift before being mapped into B.  A
    wall on clear free space farther than ``max_shift`` from every wall still
    disagrees.

    Parameters
    ----------
    a, b : WallMap
        Wall cells and free space of the two maps.
    matrix : numpy.ndarray
        3x3 rigid transform (eqs. (1)-(2)), B pixel -> A pixel.
    block : float
        Side of the squares, pixels.
    max_shift : float
        Largest local shift, pixels.
    tolerance : float, optional
        As in :func:`map_agreement`.
    max_points : int, optional
        As in :func:`map_agreement`.

    Returns
    -------
    Agreement
        Counts summed over both directions.

    Raises
    ------
    ValueError
        If ``block`` is not positive or ``max_shift`` is negative.
    """
    if not block > 0 or not max_shift >= 0:
        raise ValueError(f"block must be > 0 and max_shift >= 0, got {block} and {max_shift}")
    wb, wa = b.walls, a.walls
    if max_points > 0:
        wb, wa = subsample(wb, max_points), subsample(wa, max_points)
    if len(wb) == 0 or len(wa) == 0:
        return map_agreement(a, b, matrix, tolerance, max_points)
    moved = _apply(matrix, wb)
    squares, group = np.unique(_cells(moved, block), return_inverse=True)
    shift = _block_shifts(a, moved, group.ravel(), max_shift)
    ag1, dis1 = a.count(moved + shift[group.ravel()], tolerance)
    # A's walls take the shift of the square they fall in (fitted on B's walls there).
    codes = _cells(wa, block)
    at = np.minimum(np.searchsorted(squares, codes), len(squares) - 1)
    back = np.where((squares[at] == codes)[:, None], shift[at], 0.0)
    ag2, dis2 = b.count(_apply(np.linalg.inv(matrix), wa - back), tolerance)
    return Agreement(ag1 + ag2, dis1 + dis2)


def _fit_rigid(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """Least-squares rigid matrix (eq. (1) convention) with ``dst ~ R src + t``."""
    ms, md = src.mean(axis=0), dst.mean(axis=0)
    s, d = src - ms, dst - md
    phi = np.arctan2(np.sum(s[:, 0] * d[:, 1] - s[:, 1] * d[:, 0]), np.sum(s * d))
    m = rigid_matrix(-phi, 0.0, 0.0)
    t = md - m[:2, :2] @ ms
    m[:2, 2] = t
    return m


def refine(
    walls_a: Walls,
    walls_b: np.ndarray,
    matrix: np.ndarray,
    radii: tuple[float, ...] = (12.0, 8.0, 5.0, 3.0, 2.0),
    iterations: int = 4,
    max_points: int = 3000,
) -> np.ndarray:
    """Trimmed point-to-point ICP of B's wall cells onto A's, from ``matrix`` (B->A pixels).

    Correspondences farther than the current radius are dropped; the radius
    shrinks over ``radii`` so the coarse estimate is pulled in, then tightened.
    All but the last radius use an even subsample of ``max_points`` cells.

    Parameters
    ----------
    walls_a : scipy.spatial.cKDTree or WallMap
        A's wall cells ``(x, y)``.
    walls_b : numpy.ndarray
        (N, 2) B's wall cells ``(x, y)``.
    matrix : numpy.ndarray
        3x3 starting transform, B pixel -> A pixel.
    radii : tuple of float, optional
        Correspondence radii in cells, one stage each.
    iterations : int, optional
        Iterations per radius at most.
    max_points : int, optional
        Subsample size of the early stages.

    Returns
    -------
    numpy.ndarray
        The refined 3x3 rigid matrix (eqs. (1)-(2)), B pixel -> A pixel.
    """
    m = matrix.copy()
    sub = subsample(walls_b, max_points)
    for k, radius in enumerate(radii):
        pts = walls_b if k == len(radii) - 1 else sub
        for _ in range(iterations):
            dist, idx = _query(walls_a, _apply(m, pts), radius)
            ok = np.isfinite(dist)
            if ok.sum() < 10:
                return m
            new = _fit_rigid(pts[ok], _cells_of(walls_a)[idx[ok]])
            step = np.abs(new - m).max()
            m = new
            if step < 1e-3:
                break
    return m


@dataclass(frozen=True)
class _LineFit:
    """Point-to-line residuals of B's walls near A's at one pose (see :func:`_point_to_line`)."""

    cells: np.ndarray  # (M, 2) B's wall cells within the radius, in B's frame
    moved: np.ndarray  # (M, 2) the same cells moved into A
    res: np.ndarray  # (M,) n_i . (R x_i + t - y_i)
    jac: np.ndarray  # (M, 3) d res / d (tx, ty, psi)


def _point_to_line(walls_a: Walls, pts: np.ndarray, matrix: np.ndarray, radius: float) -> _LineFit:
    """Residuals along A's wall normals, and their Jacobian, of B's cells within ``radius``.

    ``r_i = n_i . (R x_i + t - y_i)`` with ``y_i`` the nearest wall cell of A and
    ``n_i`` A's wall normal there; ``J_i = [n_x, n_y, n_i . dR/dpsi x_i]``
    (eqs. (1)-(2)).
    """
    moved = _apply(matrix, pts)
    dist, idx = _query(walls_a, moved, radius)
    ok = np.isfinite(dist)
    x, y = pts[ok], _cells_of(walls_a)[idx[ok]]
    n = _wall_normals(walls_a, idx[ok]) if ok.any() else np.zeros((0, 2))
    psi = heading(matrix)
    c, s = np.cos(psi), np.sin(psi)
    dx = np.column_stack([-s * x[:, 0] + c * x[:, 1], -c * x[:, 0] - s * x[:, 1]])
    jac = np.column_stack([n[:, 0], n[:, 1], np.sum(n * dx, axis=1)])
    return _LineFit(x, moved[ok], np.sum(n * (moved[ok] - y), axis=1), jac)


def refine_point_to_line(
    walls_a: Walls,
    walls_b: np.ndarray,
    matrix: np.ndarray,
    radius: float = 3.0,
    scale: float = 1.0,
    iterations: int = 8,
    max_points: int = 4000,
) -> np.ndarray:
    """Robust point-to-line alignment of B's walls on A's, from ``matrix`` (B->A pixels).

    Point-to-point ICP (:func:`refine`) stops a fraction of a degree off along
    straight corridors, where a wall cell may slide along the wall at no cost.
    Here each B wall cell within ``radius`` of A's walls pulls only along A's
    wall normal ``n_i`` (residual ``r_i = n_i . (R x_i + t - y_i)``, Jacobian as
    in :func:`alignment_fit`, eqs. (1)-(2)), and Gauss-Newton steps
    weigh it by the Cauchy weight ``1 / (1 + (r_i / scale)^2)``: a drifted map
    has no single rigid fit, and the robust loss lets the consistent part of
    the overlap decide instead of averaging the misfit over all of it.

    Parameters
    ----------
    walls_a : scipy.spatial.cKDTree or WallMap
        A's wall cells ``(x, y)``.
    walls_b : numpy.ndarray
        (N, 2) B's wall cells ``(x, y)``.
    matrix : numpy.ndarray
        3x3 starting rigid transform, B pixel -> A pixel.
    radius : float, optional
        Correspondences farther than this (pixels) are dropped.
    scale : float, optional
        Scale (pixels) of the Cauchy loss.
    iterations : int, optional
        Gauss-Newton steps at most.
    max_points : int, optional
        Even subsample of B's walls used.

    Returns
    -------
    numpy.ndarray
        The refined 3x3 rigid matrix, B pixel -> A pixel.
    """
    pts = subsample(walls_b, max_points)
    m = matrix.copy()
    for _ in range(iterations):
        fit = _point_to_line(walls_a, pts, m, radius)
        if len(fit.res) < 10:
            break
        jac, res = fit.jac, fit.res
        psi = heading(m)
        w = 1.0 / (1.0 + (res / scale) ** 2)
        # a tiny ridge keeps a corridor's free direction from blowing the step up
        step = np.linalg.solve((jac * w[:, None]).T @ jac + 1e-6 * np.eye(3), -(jac.T @ (w * res)))
        m = rigid_matrix(psi + step[2], m[0, 2] + step[0], m[1, 2] + step[1])
        if np.abs(step).max() < 1e-4:
            break
    return m


def residual_distortion(
    walls_a: Walls,
    walls_b: np.ndarray,
    matrix: np.ndarray,
    block: float = 100.0,
    radius: float = 10.0,
    min_points: int = 60,
    max_points: int = 20000,
) -> float:
    """Largest local misfit (pixels) of B's walls on A's after the rigid ``matrix``.

    A drifted map has no single rigid fit: the overlap is cut into
    ``block``-pixel squares (A's frame) and each square's own translation
    ``d`` is fitted point-to-line, ``min sum (n_i . (d - r_i))^2`` over the
    residuals ``r_i`` of B's walls within ``radius`` of A's (``n_i`` A's wall
    normals, as in :func:`alignment_fit`).  Squares whose walls run one
    way only (the fit along the wall is free) or with fewer than
    ``min_points`` walls are skipped.

    Parameters
    ----------
    walls_a : scipy.spatial.cKDTree or WallMap
        A's wall cells ``(x, y)``.
    walls_b : numpy.ndarray
        (N, 2) B's wall cells ``(x, y)``.
    matrix : numpy.ndarray
        3x3 rigid transform (eqs. (1)-(2)), B pixel -> A pixel.
    block : float, optional
        Side of the squares, pixels.
    radius : float, optional
        B's walls farther than this from A's are not part of the overlap.
    min_points : int, optional
        Fewest wall cells of a square that is fitted.
    max_points : int, optional
        An even subsample of at most this many of B's walls is used, each kept
        cell counting for the cells between it and the next (``min_points``).

    Returns
    -------
    float
        The largest ``|d|`` over the squares, pixels; 0 when none qualifies.
        On the development log pairs at their true pose it is a few pixels
        for rigid pairs (map noise, thick walls: median 2.5) and more with
        odometry drift (median 4.0), so it flags drift, it does not measure
        it exactly.
    """
    pts = subsample(walls_b, max_points)
    stride = len(walls_b) / max(1, len(pts))
    fit = _point_to_line(walls_a, pts, matrix, radius)
    if len(fit.res) * stride < min_points:
        return 0.0
    n, r = fit.jac[:, :2], -fit.res
    keys = np.floor(fit.moved / block).astype(np.int64)
    keys -= keys.min(axis=0)
    _, group, counts = np.unique(
        keys[:, 0] * (keys[:, 1].max() + 1) + keys[:, 1], return_inverse=True, return_counts=True
    )
    # per square: the normal equations sum n n^T d = sum n r, summed by bincount
    terms = (n[:, 0] ** 2, n[:, 0] * n[:, 1], n[:, 1] ** 2, n[:, 0] * r, n[:, 1] * r)
    sxx, sxy, syy, bx, by = (np.bincount(group, t, counts.size) for t in terms)
    info = np.stack([np.stack([sxx, sxy], -1), np.stack([sxy, syy], -1)], -2)
    lo, hi = np.linalg.eigvalsh(info).T
    fitted = (counts * stride >= min_points) & (lo >= 0.1 * hi)
    if not fitted.any():
        return 0.0
    d = np.linalg.solve(info[fitted], np.column_stack([bx, by])[fitted][..., None])[..., 0]
    return float(np.hypot(d[:, 0], d[:, 1]).max())


def _wall_normals(walls_a: Walls, idx: np.ndarray) -> np.ndarray:
    """Unit wall normals at the cells ``idx`` of ``walls_a``, from its cache when it keeps one."""
    if isinstance(walls_a, WallMap | WallTree):
        return walls_a.normals(idx)
    return _normals(walls_a, walls_a.data[idx])


def _normals(tree: cKDTree, points: np.ndarray, k: int = 8) -> np.ndarray:
    """Unit wall normals at ``points``: the minor axis of the ``k`` nearest cells of the tree."""
    _, idx = tree.query(points, k=k)
    # x and y of the neighbours as two contiguous (N, k) arrays: the same sums, in the
    # same order, as over the (N, k, 2) gather, without its strided passes
    x, y = tree.data[:, 0][idx], tree.data[:, 1][idx]
    x -= x.mean(axis=1, keepdims=True)
    y -= y.mean(axis=1, keepdims=True)
    sxx = np.mean(x * x, axis=1)
    syy = np.mean(y * y, axis=1)
    sxy = np.mean(x * y, axis=1)
    # closed-form eigenvector of the smaller eigenvalue of [[sxx, sxy], [sxy, syy]]
    theta = 0.5 * np.arctan2(2 * sxy, sxx - syy) + np.pi / 2
    return np.column_stack([np.cos(theta), np.sin(theta)])


@dataclass(frozen=True)
class AlignmentFit:
    """The point-to-line alignment of B's walls on A's at a given matrix (Gauss-Newton terms).

    Attributes
    ----------
    info : 3x3 ``J^T J`` over ``(tx, ty, psi)`` (psi about B's pixel origin, eq. (1)).
    sigma2 : residual variance along A's wall normals, px^2 (at least 1/12, quantisation).
    centroid : ``(x, y)`` mean of those cells in B's pixels.
    psi : heading of the matrix, eq. (2).
    """

    info: np.ndarray
    sigma2: float
    centroid: np.ndarray
    psi: float


def alignment_fit(
    walls_a: Walls,
    walls_b: np.ndarray,
    matrix: np.ndarray,
    radius: float = 2.0,
    max_points: int = 4000,
) -> AlignmentFit | None:
    """Gauss-Newton terms of the point-to-line alignment of B's walls on A's at ``matrix``.

    Each wall cell of B that lands within ``radius`` of A's walls gives a
    residual ``r_i = n_i . (R x_i + t - y_i)`` along A's wall normal ``n_i``
    with Jacobian ``J_i = [n_x, n_y, n_i . dR/dpsi x_i]`` (the ``r1, r2`` of
    eq. (7)).  An even subsample of at most ``max_points`` cells is used
    (:func:`pgvd.sampling.subsample`); ``info`` is scaled back to all of B's
    walls, each kept cell standing for the cells between it and the next.

    Parameters
    ----------
    walls_a : scipy.spatial.cKDTree or WallMap
        A's wall cells ``(x, y)``.
    walls_b : numpy.ndarray
        (N, 2) B's wall cells ``(x, y)``.
    matrix : numpy.ndarray
        3x3 transform at the optimum, B pixel -> A pixel.
    radius : float, optional
        Cells of B farther than this from A's walls are not counted.
    max_points : int, optional
        Subsample size of B's walls.

    Returns
    -------
    AlignmentFit or None
        None when fewer than 3 cells of B land near A's walls.
    """
    pts = subsample(walls_b, max_points)
    fit = _point_to_line(walls_a, pts, matrix, radius)
    if len(fit.res) < 3:
        return None
    x, res = fit.cells, fit.res
    psi = heading(matrix)
    info = fit.jac.T @ fit.jac
    # a tiny prior keeps a degenerate direction finite instead of singular
    info += np.diag([1e-9, 1e-9, 1e-9 * max(1.0, float(np.abs(x).max())) ** 2])
    return AlignmentFit(
        info=info * (len(walls_b) / len(pts)),
        sigma2=max(float(np.mean(res**2)), 1.0 / 12.0),
        centroid=x.mean(axis=0),
        psi=float(psi),
    )


@dataclass(frozen=True)
class CovarianceModel:
    """Constants of :func:`calibrated_covariance`.

    Attributes
    ----------
    correlation : wall cells per independent residual at a residual of grid
        quantisation (scales the Laplace covariance).
    misfit_power : how steeply the covariance grows with the residual variance
        ``sigma^2`` beyond quantisation: ``(12 sigma^2) ** (misfit_power - 1)``.
    floor_m : isotropic translation floor (metres) at the centroid of the matched walls.
    floor_rad : heading floor (radians).
    heading_scale : factor on the heading standard deviation of the inflated Laplace
        term, about the centroid of the matched walls (1: the Laplace shape as it is).
    """

    correlation: float
    misfit_power: float
    floor_m: float
    floor_rad: float
    heading_scale: float = 1.0


#: Fitted by ``python3 -m bench.covariance fit`` (maximum likelihood) on one half of
#: the development pairs (intel and freiburg-079 logs, 0.05 m cells) as the merge in use
#: accepts them; reported on the other half in ``bench/results/covariance.md``.  The floors
#: come out at nothing: on these pairs the misfit term carries it all.  The heading scale
#: (1.34) brings the heading of the fitted half to its chi2(1) mean; on the held-out half
#: the heading NEES is 0.96 (band 0.73-1.27; 1.36 without it).  Refitted when the walls
#: became their faces (2.92, was 5.18), and again on the pairs of the decision of c597ba2
#: (208 of the 240 accepted, where the earlier collection's decision accepted 217): the
#: earlier constants gave 2.89 and 98.1 % inside there, one pair over the 98 % bound.
CALIBRATED = CovarianceModel(
    correlation=1.9401,
    misfit_power=3.6557,
    floor_m=1.8153e-27,
    floor_rad=6.6729e-13,
    heading_scale=1.3372,
)


def calibrated_covariance(
    fit: AlignmentFit | None, resolution: float, model: CovarianceModel = CALIBRATED
) -> np.ndarray:
    """Covariance of ``(tx, ty, psi)`` (eq. (3); px, px, rad) calibrated on real pairs.

    The model, with ``S = (J^T J)^-1``, ``sigma^2`` the residual variance
    (px^2) of :func:`alignment_fit`, ``q = 1/12`` that of grid quantisation
    and ``L = correlation sigma^2 (sigma^2 / q) ** (misfit_power - 1) S``::

        Sigma = A^-1 (D A L A^T D + diag(f^2, f^2, f_psi^2)) A^-T,
        D = diag(1, 1, heading_scale)

    * ``L`` is the Laplace approximation ``sigma^2 (J^T J)^-1`` of the fit
      (noise of the residuals, shrinking as one over the matched walls, with
      the shape of ``S``: a corridor stays uncertain along its length),
      inflated as the residuals grow beyond quantisation.  On real pairs the
      errors are biased by map content (walls seen from one side, drift
      within a map); the residual misfit is what signals it, and the error
      grows faster than the residual variance (``misfit_power`` > 1).
    * ``D`` scales the heading of ``L`` alone, about the centroid ``c`` of
      the matched walls.  ``S`` takes the heading's precision from the spread
      of the walls about ``c``, as if every wall pinned it independently;
      the heading of real pairs is biased by map content more than that (a
      drift that bends one map's far walls, short walls at the ends of the
      overlap), so one factor on the heading's standard deviation, fitted
      with the others, brings it to its errors.  About ``c`` the heading is
      nearly uncorrelated with the translation; scaling it there also moves
      B's origin through the lever arm, as a heading error does (scaling the
      heading about B's origin instead would keep its variance from the lever
      arm and break the link between the two).
    * ``f, f_psi`` are a floor on translation (metres over ``resolution``)
      and heading at ``c``.
    * ``A = [[I, -dR/dpsi c], [0, 1]]`` moves the pose error from B's pixel
      origin, the reference point of eq. (1), to ``c`` (a heading error
      about ``c`` moves the origin by ``-dR/dpsi c dpsi``).

    Parameters
    ----------
    fit : AlignmentFit or None
        The alignment at the merge's result (:func:`alignment_fit`).
    resolution : float
        Metres per cell of the maps.
    model : CovarianceModel, optional
        The constants; by default those fitted on the development pairs.

    Returns
    -------
    numpy.ndarray
        3x3 covariance over ``(tx px, ty px, psi rad)`` of eq. (1) about B's
        pixel origin, eq. (3); ``inf`` on the diagonal when ``fit`` is None.

    Raises
    ------
    ValueError
        If ``resolution`` is not positive.
    """
    if fit is None:
        return np.diag([np.inf, np.inf, np.inf])
    if not resolution > 0:
        raise ValueError(f"resolution must be > 0, got {resolution}")
    misfit = (12.0 * fit.sigma2) ** (model.misfit_power - 1.0)
    laplace = model.correlation * fit.sigma2 * misfit * np.linalg.inv(fit.info)
    floor = model.floor_m / resolution
    # T = T_c - R c, so a heading error about the centroid moves B's origin by -dR/dpsi c
    (cx, cy), c, sn = fit.centroid, np.cos(fit.psi), np.sin(fit.psi)
    a_inv, a = np.eye(3), np.eye(3)
    a_inv[:2, 2] = [sn * cx - c * cy, c * cx + sn * cy]
    a[:2, 2] = -a_inv[:2, 2]
    d = np.diag([1.0, 1.0, model.heading_scale])
    at_centroid = d @ a @ laplace @ a.T @ d
    at_centroid += np.diag([floor**2, floor**2, model.floor_rad**2])
    cov = a_inv @ at_centroid @ a_inv.T
    return 0.5 * (cov + cov.T)


def pose_covariance(
    fine_a: WallMap, fine_b: WallMap, matrix: np.ndarray, resolution: float
) -> np.ndarray:
    """The covariance reported for the pose ``matrix`` of B on A, eq. (3).

    :func:`calibrated_covariance` of the point-to-line fit of all B's walls on A's
    at ``matrix`` (:func:`alignment_fit`).  The merge and :mod:`pgvd.verify` both
    report this one, so that a link verified later carries the covariance its merge
    would have (verify once computed its own, uncalibrated).

    Parameters
    ----------
    fine_a, fine_b : WallMap
        The two maps at full resolution.
    matrix : numpy.ndarray
        3x3 B pixel -> A pixel.
    resolution : float
        Metres per cell.

    Returns
    -------
    numpy.ndarray
        3x3 covariance over ``(tx px, ty px, psi rad)`` about B's pixel origin.
    """
    return calibrated_covariance(alignment_fit(fine_a.tree, fine_b.walls, matrix), resolution)
