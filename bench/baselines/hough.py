"""Carpin's Hough-spectrum map merging (S. Carpin, "Fast and accurate map merging for
multi-robot systems", Autonomous Robots 25, 2008).

1. Hough transform of each map's occupied cells; the Hough spectrum is
   ``HS(theta) = sum_rho HT(rho, theta)^2``, normalised.
2. The circular cross-correlation of the two spectra over [0, pi) peaks at the
   relative rotation; its ``n_rotations`` best local maxima are candidates, each
   with its pi-ambiguous twin.
3. For each candidate, B's occupied cells are rotated; the X- and Y-spectra
   (projections of the occupied cells, here onto A's dominant wall direction and
   its normal, so that walls give sharp peaks) are cross-correlated, and the best
   ``n_shifts`` peaks of each give translation candidates.
4. The candidate with the best acceptance index omega (agree / (agree +
   disagree)) wins; it is accepted if omega >= OMEGA_ACCEPT.
"""

from __future__ import annotations

import numpy as np
from scipy.signal import find_peaks
from skimage.transform import hough_line

from bench.baselines.common import (
    OCCUPIED,
    OMEGA_ACCEPT,
    BaselineResult,
    acceptance_index,
    classes,
    rotation_about,
)
from pgvd.grid import Grid

#: Angular resolution of the Hough transform, degrees.
THETA_STEP = 0.5


def hough_spectrum(occupied: np.ndarray) -> np.ndarray:
    """Normalised Hough spectrum over theta in [-90, 90) degrees at THETA_STEP."""
    theta = np.deg2rad(np.arange(-90.0, 90.0, THETA_STEP))
    ht, _, _ = hough_line(occupied, theta=theta)
    hs = (ht.astype(np.float64) ** 2).sum(axis=0)
    return hs / max(hs.max(), 1e-12)


def _circular_xcorr(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``cc[k] = sum_i a[i] * b[i + k]`` (circular), by FFT."""
    return np.real(np.fft.ifft(np.conj(np.fft.fft(a)) * np.fft.fft(b)))


def _top_peaks(signal: np.ndarray, n: int, circular: bool = False) -> np.ndarray:
    padded = np.concatenate([signal[-1:], signal, signal[:1]]) if circular else signal
    peaks, _ = find_peaks(padded)
    if circular:
        peaks = (peaks - 1) % signal.size
    if peaks.size == 0:
        peaks = np.array([int(np.argmax(signal))])
    return peaks[np.argsort(signal[peaks])[::-1][:n]]


def _spectrum(points: np.ndarray, axis: np.ndarray, lo: float, size: int) -> np.ndarray:
    coord = np.rint(points @ axis - lo).astype(np.int64)
    return np.bincount(coord, minlength=size).astype(np.float64)


def merge(a: Grid, b: Grid, n_rotations: int = 3, n_shifts: int = 2) -> BaselineResult:
    """Estimate the B-pixel -> A-pixel transform by Hough spectra; accept by omega."""
    la, lb = classes(a), classes(b)
    occ_a, occ_b = la == OCCUPIED, lb == OCCUPIED
    if occ_a.sum() < 2 or occ_b.sum() < 2:
        return BaselineResult(False, np.eye(3), 0.0)
    hs_a, hs_b = hough_spectrum(occ_a), hough_spectrum(occ_b)
    # A line of B with normal angle phi has normal phi - psi after rigid_matrix(psi):
    # HS_A(theta) = HS_B(theta + psi), so the correlation peaks at k = psi.
    cc = _circular_xcorr(hs_a, hs_b)
    dominant = np.deg2rad(-90.0 + THETA_STEP * float(np.argmax(hs_a)))
    u = np.array([np.cos(dominant), np.sin(dominant)])  # A's dominant wall normal
    v = np.array([-u[1], u[0]])
    pts_a = np.argwhere(occ_a)[:, ::-1].astype(np.float64)
    pts_b = np.argwhere(occ_b)[:, ::-1].astype(np.float64)
    centre_b = (np.array(b.shape[::-1]) - 1) / 2.0
    best = BaselineResult(False, np.eye(3), -1.0)
    for k in _top_peaks(cc, n_rotations, circular=True):
        for psi in (np.deg2rad(k * THETA_STEP), np.deg2rad(k * THETA_STEP) + np.pi):
            rot = rotation_about(psi, centre_b, centre_b)
            rb = pts_b @ rot[:2, :2].T + rot[:2, 2]
            shifts = []
            for axis in (u, v):
                lo = min((pts_a @ axis).min(), (rb @ axis).min()) - 1
                size = int(max((pts_a @ axis).max(), (rb @ axis).max()) - lo) + 2
                sa, sb = _spectrum(pts_a, axis, lo, size), _spectrum(rb, axis, lo, size)
                full = np.correlate(sa, sb, mode="full")  # lag d: A ~ B shifted by d
                lags = _top_peaks(full, n_shifts) - (size - 1)
                shifts.append(lags)
            for du in shifts[0]:
                for dv in shifts[1]:
                    t = du * u + dv * v
                    m = rot.copy()
                    m[:2, 2] += t
                    omega = acceptance_index(la, lb, m)
                    if omega > best.score:
                        best = BaselineResult(omega >= OMEGA_ACCEPT, m, omega)
    return best
