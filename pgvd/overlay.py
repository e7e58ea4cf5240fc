"""The coarse overlay of one map on another for every translation at once, by FFT.

The search ranks translations by it: walls of one map that fall on walls of the
other agree, walls that fall on clear free space disagree (the check the paper
leaves to future work, Sec. VI, counted densely), optionally with the cells free
in both maps as evidence too (:class:`OverlayWeights`).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy import fft as sfft

from pgvd.morphology import grow


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

    A square's maximum is the maximum of the rows' maxima; each is taken by doubling
    (:func:`_wrapped_max_along`), which costs about a third of SciPy's filter on the
    overlays of a merge.
    """
    return _wrapped_max_along(_wrapped_max_along(values, radius, 0), radius, 1)


def _wrapped_max_along(values: np.ndarray, radius: int, axis: int) -> np.ndarray:
    """The largest of the ``2 radius + 1`` values around each along ``axis``, wrapping:
    maxima over spans of 1, 2, 4, ... cells, then the two largest spans that cover the
    window (they overlap: a maximum is the same however often a cell is counted)."""
    n, side, span = values.shape[axis], 2 * radius + 1, 1
    pad = [(radius, radius) if k == axis else (0, 0) for k in range(values.ndim)]
    top = np.moveaxis(np.pad(values, pad, mode="wrap"), axis, 0)
    while 2 * span <= side:
        top = np.maximum(top[:-span], top[span:])
        span *= 2
    return np.moveaxis(np.maximum(top[:n], top[side - span : side - span + n]), 0, axis)


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
