"""Exhaustive reference: every heading at 1 degree, FFT cross-correlation for the translation.

The score of a pose is ``walls on walls - walls on free space``: B's wall cells
within one cell of an A wall, minus wall cells of either map on the other's
free space (free cells next to a wall do not count: a one-cell slack on both
sides).  Two FFT correlations per heading.  Free-on-free agreement is left out
on purpose: it rewards large overlaps, and in a long corridor building
(freiburg-079) it makes the 180-degree flip win over the true pose.  Every
heading in [0, 360) at ``step_deg`` is scored on maps pooled by ``coarse`` (an
occupied coarse cell wins over free, so that walls survive); the best
``refine`` headings are then re-correlated at full resolution, with their
neighbours at +-``step_deg``.  Slow by design: it marks the best accuracy a
search over the whole pose space achieves.  Accepted if the acceptance index
omega reaches OMEGA_ACCEPT, as for the Hough-spectrum baseline.
"""

from __future__ import annotations

import numpy as np
from scipy import fft, ndimage

from bench.baselines.common import (
    FREE,
    OCCUPIED,
    OMEGA_ACCEPT,
    BaselineResult,
    acceptance_index,
    classes,
    rotation_about,
    translation,
)
from pgvd.grid import Grid

_RING = np.ones((3, 3), bool)


def _channels(labels: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """Occupied and free indicator images, pooled by k (occupied wins, then free)."""
    if k > 1:
        h, w = (-(-labels.shape[0] // k)) * k, (-(-labels.shape[1] // k)) * k
        padded = np.zeros((h, w), labels.dtype)
        padded[: labels.shape[0], : labels.shape[1]] = labels
        labels = padded.reshape(h // k, k, w // k, k).max(axis=(1, 3))
    return (labels == OCCUPIED).astype(np.float32), (labels == FREE).astype(np.float32)


class _Correlator:
    """FFT correlation of a fixed A with rotated copies of B."""

    def __init__(self, labels_a: np.ndarray, labels_b: np.ndarray, k: int) -> None:
        occ_a, free_a = _channels(labels_a, k)
        occ_b, free_b = _channels(labels_b, k)
        near_a = ndimage.binary_dilation(occ_a > 0, _RING).astype(np.float32)
        # Encode B as one image: 2 occupied, 1 free, so a single nearest warp serves both.
        self.b = 2 * occ_b + free_b
        side = int(np.ceil(np.hypot(*self.b.shape))) + 2
        self.canvas = (side, side)
        self.shape = tuple(fft.next_fast_len(n + side - 1, real=True) for n in occ_a.shape)
        # B's walls score +1 near A's walls and -1 on A's free space away from them.
        self.f_vs_occ_b = fft.rfft2(near_a - free_a * (1 - near_a), self.shape, workers=1)
        self.f_occ = fft.rfft2(occ_a, self.shape, workers=1)
        self.centre_b = (np.array(self.b.shape[::-1]) - 1) / 2.0
        self.centre_c = (np.array(self.canvas[::-1]) - 1) / 2.0

    def best_shift(self, psi: float) -> tuple[float, np.ndarray]:
        """Peak score and B-pixel -> A-pixel matrix of the best shift at heading psi."""
        rot = rotation_about(psi, self.centre_b, self.centre_c)  # B -> canvas
        swap = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
        inv_rc = swap @ np.linalg.inv(rot) @ swap
        rb = ndimage.affine_transform(
            self.b, inv_rc[:2, :2], offset=inv_rc[:2, 2], output_shape=self.canvas, order=0
        )
        occ_b = rb == 2
        free_b = (rb == 1) & ~ndimage.binary_dilation(occ_b, _RING)
        # (near_A - far free_A) * occ_B - occ_A * far free_B, all shifts at once.
        spectrum = self.f_vs_occ_b * np.conj(
            fft.rfft2(occ_b.astype(np.float32), self.shape, workers=1)
        )
        spectrum -= self.f_occ * np.conj(
            fft.rfft2(free_b.astype(np.float32), self.shape, workers=1)
        )
        corr = fft.irfft2(spectrum, self.shape, workers=1)
        dy, dx = np.unravel_index(int(np.argmax(corr)), corr.shape)
        # corr[d] = sum_p A[p + d] * RB[p] (circular): wrap negative shifts back.
        dy = dy - self.shape[0] if dy > self.shape[0] - self.canvas[0] else dy
        dx = dx - self.shape[1] if dx > self.shape[1] - self.canvas[1] else dx
        return float(corr.max()), translation(dx, dy) @ rot


def merge(
    a: Grid, b: Grid, step_deg: float = 1.0, coarse: int = 4, refine: int = 2
) -> BaselineResult:
    """Search every heading; return the best B-pixel -> A-pixel transform, accepted by omega."""
    la, lb = classes(a), classes(b)
    if not (la == OCCUPIED).any() or not (lb == OCCUPIED).any():
        return BaselineResult(False, np.eye(3), 0.0)
    headings = np.deg2rad(np.arange(0.0, 360.0, step_deg))
    coarse_corr = _Correlator(la, lb, coarse)
    scores = np.array([coarse_corr.best_shift(psi)[0] for psi in headings])
    order = np.argsort(scores)[::-1]
    picked: list[int] = []
    for i in order:  # the best headings, skipping near-duplicates of ones already picked
        if all(min(abs(i - j), headings.size - abs(i - j)) > 2 for j in picked):
            picked.append(int(i))
        if len(picked) == refine:
            break
    fine = _Correlator(la, lb, 1)
    step = np.deg2rad(step_deg)
    candidates = [fine.best_shift(headings[i] + d) for i in picked for d in (-step, 0.0, step)]
    _, matrix = max(candidates, key=lambda c: c[0])
    omega = acceptance_index(la, lb, matrix)
    return BaselineResult(omega >= OMEGA_ACCEPT, matrix, omega)
