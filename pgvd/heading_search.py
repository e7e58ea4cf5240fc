"""The heading stage of the search: candidate headings (10), B turned by each (12) and
overlaid on A for every translation, best overlay first.

Optionally (``OffParams.heading_span``) the heading of best whole-map overlay near each
Radon candidate is a candidate too (:func:`with_refined`).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from pgvd.grid import rigid_matrix
from pgvd.overlay import MapView, Overlay, OverlayScores, OverlayWeights
from pgvd.params import MergeParams
from pgvd.pooling import coarsen
from pgvd.rotation import HeadingCandidate
from pgvd.transform import warp


def translation(tx: float, ty: float) -> np.ndarray:
    """The 3x3 homogeneous matrix of the translation ``(tx, ty)`` (cells)."""
    return np.array([[1.0, 0.0, tx], [0.0, 1.0, ty], [0.0, 0.0, 1.0]])


def rotation_about_centre(psi: float, shape: tuple[int, int]) -> tuple[np.ndarray, tuple[int, int]]:
    """Rotation by ``psi`` (eq. (2)) of a map of ``shape`` into a canvas that holds it whole."""
    h, w = shape
    side = int(np.ceil(np.hypot(h, w))) + 2
    rot = rigid_matrix(psi, 0.0, 0.0)
    centre = np.array([(w - 1) / 2.0, (h - 1) / 2.0])
    rot[:2, 2] = (side - 1) / 2.0 - rot[:2, :2] @ centre
    return rot, (side, side)


def turned_by(headings: list[HeadingCandidate], degrees: float) -> list[HeadingCandidate]:
    """``headings`` each turned by ``degrees`` (``OffParams.heading_offset``)."""
    if not degrees:
        return headings
    turn = np.radians(degrees)
    return [replace(h, psi=float(np.angle(np.exp(1j * (h.psi + turn))))) for h in headings]


def described(h: HeadingCandidate) -> str:
    """``"147.0 deg (sigma 1.11)"``: a candidate heading and its sigma (10), in degrees."""
    return f"{np.degrees(h.psi):.1f} deg (sigma {np.degrees(np.sqrt(h.variance)):.2f})"


def known_box(p: np.ndarray, margin: int = 2) -> tuple[slice, slice]:
    """Row and column slices of the cells that are not unknown, grown by ``margin``."""
    known = np.abs(p - 0.5) > 0.05
    rows, cols = np.flatnonzero(known.any(axis=1)), np.flatnonzero(known.any(axis=0))
    if rows.size == 0:
        return slice(0, p.shape[0]), slice(0, p.shape[1])
    return (
        slice(max(0, rows[0] - margin), min(p.shape[0], rows[-1] + margin + 1)),
        slice(max(0, cols[0] - margin), min(p.shape[1], cols[-1] + margin + 1)),
    )


@dataclass
class Rotated:
    """B turned by one candidate heading, at the coarse scale, cropped to its known cells."""

    heading: HeadingCandidate
    prob: np.ndarray  # rotated coarse B (not yet blurred)
    rotation: np.ndarray  # coarse B -> this crop
    centre: tuple[float, float]  # rotation centre in the crop, (x, y)
    overlay: Overlay


def rotate(
    heading: HeadingCandidate,
    cb: np.ndarray,
    scores: OverlayScores,
    params: MergeParams,
    canvases: dict[float, np.ndarray],
) -> Rotated:
    """Rotate coarse B by a candidate heading (12) and overlay it on A for all translations.

    ``canvases`` holds the whole rotated canvases by heading.  Headings come in
    pairs ``psi``, ``psi + pi`` (:func:`pgvd.rotation.estimate_headings`), and
    the canvas is centred on a cell-centre grid, so a half-turn twin is the
    canvas flipped on both axes: it is taken from there instead of warped again.
    """
    rot, shape = rotation_about_centre(heading.psi, cb.shape)
    twin = next(
        (
            c
            for psi, c in canvases.items()
            if abs(np.angle(np.exp(1j * (heading.psi - psi - np.pi)))) < 1e-9
        ),
        None,
    )
    rb = warp(cb, rot, shape, order=1, cval=0.5) if twin is None else twin[::-1, ::-1].copy()
    canvases[heading.psi] = rb
    # The heading blur spreads walls by a few cells at most: keep that margin.
    rows, cols = known_box(rb, margin=2 + int(np.ceil(3 * np.sqrt(heading.variance) * shape[0])))
    rb = rb[rows, cols]
    centre = ((shape[1] - 1) / 2.0 - cols.start, (shape[0] - 1) / 2.0 - rows.start)
    overlay = scores.overlay(MapView(rb, params.reading.occupied, params.reading.free, 1))
    rot = translation(-cols.start, -rows.start) @ rot
    return Rotated(heading, rb, rot, centre, overlay)


def _overlay_evidence(
    psi: float, cb: np.ndarray, scores: OverlayScores, params: MergeParams
) -> float:
    """Best whole-map overlay evidence over all translations of coarse B turned by ``psi`` (12)."""
    rot, shape = rotation_about_centre(psi, cb.shape)
    rb = warp(cb, rot, shape, order=1, cval=0.5)
    rows, cols = known_box(rb)
    view = MapView(rb[rows, cols], params.reading.occupied, params.reading.free, 1)
    return scores.overlay(view).best_evidence(params.overlay_rankings()[0])


def _refined_heading(
    heading: HeadingCandidate, cb: np.ndarray, scores: OverlayScores, params: MergeParams
) -> HeadingCandidate | None:
    """The heading of best whole-map overlay evidence near a Radon candidate (10); None if
    that is the candidate itself.

    Headings ``psi + i * heading_step`` within ``heading_span`` of the candidate are
    overlaid on A (best evidence over all translations), and a parabola through the
    best one and its neighbours places the maximum between steps.  The refined heading
    keeps the candidate's variance.
    """
    step = np.radians(params.off.heading_step)
    reach = int(params.off.heading_span / params.off.heading_step)
    steps = np.arange(-reach, reach + 1)
    ev = np.array([_overlay_evidence(heading.psi + i * step, cb, scores, params) for i in steps])
    j = int(np.argmax(ev))
    if steps[j] == 0:
        return None
    offset = 0.0
    if 0 < j < steps.size - 1:
        y0, y1, y2 = ev[j - 1 : j + 2]
        curve = y0 - 2 * y1 + y2
        offset = 0.5 * (y0 - y2) / curve if curve < 0 else 0.0
    psi = float(np.angle(np.exp(1j * (heading.psi + (steps[j] + offset) * step))))
    return HeadingCandidate(psi, heading.variance, heading.score)


def with_refined(
    headings: list[HeadingCandidate], ca: np.ndarray, cb: np.ndarray, params: MergeParams
) -> list[HeadingCandidate]:
    """The Radon candidates and, after them, their refined headings (:func:`_refined_heading`).

    Both are kept: near a candidate that is right, the best overlay of a partial map
    is sometimes a look-alike a few degrees away.  The refinement runs at twice the
    coarse cell (4x fewer cells per overlay); a refined heading within half a step of
    another candidate is dropped.
    """
    if params.off.heading_span <= 0:
        return headings
    reading = params.reading
    view = MapView(coarsen(ca, 2, reading.occupied), reading.occupied, reading.free, 1)
    scores, cb2 = OverlayScores(view), coarsen(cb, 2, reading.occupied)
    gap = np.radians(params.off.heading_step / 2)
    out = list(headings)
    for h in headings:
        r = _refined_heading(h, cb2, scores, params)
        if r is not None and all(abs(np.angle(np.exp(1j * (r.psi - o.psi)))) >= gap for o in out):
            out.append(r)
    return out


def ranked(turned: list[Rotated], weights: OverlayWeights) -> list[Rotated]:
    """Rotated B's, best whole-map overlay evidence first."""
    return sorted(turned, key=lambda r: -r.overlay.best_evidence(weights))
