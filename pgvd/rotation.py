"""Rotation alignment by Radon/Hough angle spectra, eq. (10).

The Radon transform of an occupancy grid projects the occupied cells along
every direction ``theta``; straight walls become sharp peaks.  Summarising
each projection by its energy (the sum of the squared projection bins) gives
an *angle spectrum* ``s(theta)`` over ``[0, 180)`` degrees whose peaks are the
map's dominant wall directions.  Eq. (10) takes the difference of the arg-max
of the two spectra; we use the circular cross-correlation of the whole
spectra instead, which uses every wall direction at once and degrades
gracefully when one map lacks the dominant direction of the other.

A spectrum has period 180 degrees and indoor maps are nearly symmetric under
90 degree turns, so the heading is ambiguous: several candidate headings are
returned (each correlation peak ``delta`` as ``delta`` and ``delta + 180``)
and the translation stage decides among them.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pgvd.sampling import subsample

#: Cells with an occupancy probability above this are walls for the spectrum.
OCCUPIED = 0.65
#: The Laplace variance of a correlation peak (``tau / -C''``) overstates the heading
#: error: on the development pairs (intel and freiburg-079 log pairs, pairs cut from the
#: development map images; ``python3 -m bench acceptance``) the mean of ``(error /
#: sigma)^2`` of the candidate nearest the truth was 0.11 with the raw variance.
#: Scaling the variance by this makes it 1, so the heading sigma of eq. (10) matches
#: the measured error of the rotation stage.
VARIANCE_CALIBRATION = 0.11
#: Angles of the angle spectrum projected per pass (memory locality, not results).
_ANGLES_PER_PASS = 24


@dataclass(frozen=True)
class HeadingCandidate:
    """One candidate relative heading.

    Attributes
    ----------
    psi : heading in radians, in the convention of :func:`pgvd.grid.rigid_matrix`:
        rotating B by ``psi`` aligns it with A.
    variance : variance of ``psi`` in rad^2, from the curvature (width) of the
        spectrum correlation peak relative to the correlation's noise level.
    score : normalised correlation of the two spectra at ``psi`` (<= 1).
    """

    psi: float
    variance: float
    score: float


def angle_spectrum(p: np.ndarray, n_angles: int = 360, max_points: int = 3000) -> np.ndarray:
    """Angle spectrum of an occupancy grid, the Radon image of eq. (10) reduced per angle.

    Parameters
    ----------
    p : numpy.ndarray
        (H, W) occupancy probabilities.
    n_angles : int, optional
        Number of angles ``theta_i = i * pi / n_angles`` in ``[0, pi)``.
    max_points : int, optional
        Occupied cells beyond this are subsampled (evenly, deterministically).

    Returns
    -------
    numpy.ndarray
        (n_angles,) float: ``s(theta) = sum_rho R_theta(rho)^2 / (sum w)^2`` where
        ``R_theta`` is the projection (1-cell bins) of the occupied cells weighted by
        their probability onto the normal ``(cos theta, sin theta)`` (x = column, y = row).

    Raises
    ------
    ValueError
        If ``p`` is not 2-D or has no occupied cell.

    References
    ----------
    .. [1] Saeedi, S., Paull, L., Trentini, M., Seto, M., and Li, H., "Map merging
       using probabilistic generalized Voronoi diagrams", IROS 2012, eq. (10).
    """
    p = np.asarray(p)
    if p.ndim != 2:
        raise ValueError(f"angle_spectrum needs a 2-D grid, got shape {p.shape}")
    cells = np.flatnonzero(p > OCCUPIED)
    if cells.size == 0:
        raise ValueError("angle_spectrum: the map has no occupied cells")
    rows, cols = np.divmod(subsample(cells, max_points), p.shape[1])
    # only the kept cells are widened to float64, not the whole map
    w = p[rows, cols].astype(np.float64)
    theta = np.arange(n_angles) * (np.pi / n_angles)
    reach = int(np.ceil(np.hypot(*p.shape))) + 1
    n_bins = 2 * reach + 1
    energy = np.empty(n_angles)
    # a few angles at a time, so that the (angles, cells) arrays stay in cache
    for a in range(0, n_angles, _ANGLES_PER_PASS):
        i = np.arange(a, min(a + _ANGLES_PER_PASS, n_angles))
        # bin = floor(rho + 0.5) + reach, with rho + reach + 0.5 > 0 so truncation is the
        # floor; each angle's row offset goes into the same pass
        keys = np.outer(np.cos(theta[i]), cols)
        keys += np.outer(np.sin(theta[i]), rows)
        keys += (i * n_bins + reach + 0.5)[:, None]
        flat = keys.astype(np.int64).ravel() - a * n_bins
        proj = np.bincount(flat, np.broadcast_to(w, keys.shape).ravel(), i.size * n_bins)
        energy[i] = (proj.reshape(i.size, n_bins) ** 2).sum(axis=1)
    return energy / w.sum() ** 2


def spectrum_correlation(s_a: np.ndarray, s_b: np.ndarray) -> np.ndarray:
    """Normalised circular correlation ``C(delta) = corr(s_a(theta), s_b(theta + delta))``.

    A rotation of B by ``psi`` (eq. (2)) turns a wall normal at ``theta`` into
    ``theta - psi``, so ``s_a(theta) = s_b(theta + psi)`` and ``C`` peaks at
    ``delta = psi`` (mod 180 degrees).  Values are Pearson correlations in [-1, 1].

    Parameters
    ----------
    s_a, s_b : numpy.ndarray
        Angle spectra of A and B (:func:`angle_spectrum`), of one length.

    Returns
    -------
    numpy.ndarray
        ``C(delta)`` for every shift of one spectrum bin.

    References
    ----------
    .. [1] Saeedi, S., Paull, L., Trentini, M., Seto, M., and Li, H., "Map merging
       using probabilistic generalized Voronoi diagrams", IROS 2012, eqs. (2), (10).
    """
    a = (s_a - s_a.mean()) / (s_a.std() + 1e-300)
    b = (s_b - s_b.mean()) / (s_b.std() + 1e-300)
    return np.fft.irfft(np.conj(np.fft.rfft(a)) * np.fft.rfft(b), n=a.size) / a.size


def _peak_variance(c: np.ndarray, i: int, bin_rad: float) -> float:
    """Variance (rad^2) of the heading at correlation peak ``i`` (Laplace approximation).

    The correlation is read as a log-likelihood whose temperature is its own
    noise level ``tau`` (robust spread of ``C`` over all shifts), so that
    ``var = tau / -C''(peak)``: a sharp, tall peak over a quiet background is
    a precise heading, a broad or low one is not.  The result is scaled by
    :data:`VARIANCE_CALIBRATION`, measured against the true headings of the
    development pairs, and floored at a quarter of a bin squared.  ``C`` is concave
    at ``i`` (:func:`peak_bins`), so ``-C''`` is positive.
    """
    n = c.size
    curvature = -(c[(i - 1) % n] - 2 * c[i] + c[(i + 1) % n]) / bin_rad**2
    tau = 1.4826 * float(np.median(np.abs(c - np.median(c))))
    return float(max((0.5 * bin_rad) ** 2, VARIANCE_CALIBRATION * tau / curvature))


def _refined_peak(c: np.ndarray, i: int, bin_rad: float) -> float:
    """Sub-bin location (rad) of the maximum at bin ``i`` by a parabola through 3 bins."""
    n = c.size
    y0, y1, y2 = c[(i - 1) % n], c[i], c[(i + 1) % n]
    denom = y0 - 2 * y1 + y2
    offset = 0.5 * (y0 - y2) / denom if denom < 0 else 0.0
    return (i + offset) * bin_rad


def peak_bins(c: np.ndarray, sep: int, count: int) -> list[tuple[int, int]]:
    """The correlation's peaks and their quarter-turn twins, best first.

    Every peak ``i`` of ``C`` (strongest first) is chosen, and so is its twin, the
    best bin within ``sep`` bins of ``i`` plus a quarter turn, until ``count`` are
    chosen; bins closer than ``sep`` to one chosen before are not.  A chosen bin's
    heading variance is measured by the curvature of ``C`` (:func:`_peak_variance`):
    its own where ``C`` is concave there, or, for a twin where it is not (a twin
    needs not be a peak), its parent's, whose walls it is turned by a quarter.

    Parameters
    ----------
    c : numpy.ndarray
        The spectrum correlation (:func:`spectrum_correlation`) over 180 degrees.
    sep : int
        Fewest bins between two chosen bins.
    count : int
        How many to choose at most (a twin may take the last place).

    Returns
    -------
    list of tuple of int
        ``(bin, width)`` pairs, best correlation first: ``width`` is the bin whose
        curvature gives ``bin``'s variance.
    """
    n = c.size
    is_peak = (c >= np.roll(c, 1)) & (c > np.roll(c, -1))
    concave = 2 * c > np.roll(c, 1) + np.roll(c, -1)
    chosen: dict[int, int] = {}

    def distinct(i: int) -> bool:
        return all(min((i - j) % n, (j - i) % n) >= sep for j in chosen)

    for i in (int(i) for i in np.argsort(-c) if is_peak[i]):
        window = (i + n // 2 + np.arange(-sep + 1, sep)) % n
        twin = int(window[np.argmax(c[window])])
        for j in (i, twin):
            if distinct(j):
                chosen[j] = j if concave[j] else i
        if len(chosen) >= count:
            break
    return sorted(chosen.items(), key=lambda jp: -c[jp[0]])


def estimate_headings(
    a: np.ndarray,
    b: np.ndarray,
    max_candidates: int = 6,
    n_angles: int = 360,
    min_separation_deg: float = 5.0,
) -> list[HeadingCandidate]:
    """Candidate relative headings of B with respect to A, eq. (10).

    Every peak ``delta`` of the spectrum correlation (strongest first) is a
    candidate, and so is its quarter-turn twin (the best bin within
    ``min_separation_deg`` of ``delta + 90``): a building whose walls run two
    ways gives a spectrum that looks alike under a quarter turn, and a
    partial map may favour the wrong one.  Candidates are ranked by their
    correlation and each stands for ``delta`` and ``delta + 180`` degrees.

    Parameters
    ----------
    a, b : numpy.ndarray
        Occupancy probabilities of the two maps (any sizes).
    max_candidates : int, optional
        Number of headings returned (pairs ``delta``, ``delta + pi``).
    n_angles : int, optional
        Spectrum resolution over 180 degrees; peaks are interpolated below it.
    min_separation_deg : float, optional
        Correlation peaks closer than this are one peak.

    Returns
    -------
    list of HeadingCandidate
        Best correlation first, ``psi`` in ``(-pi, pi]``.

    Raises
    ------
    ValueError
        If ``max_candidates < 1``, or a map is not 2-D or has no occupied cell.

    References
    ----------
    .. [1] Saeedi, S., Paull, L., Trentini, M., Seto, M., and Li, H., "Map merging
       using probabilistic generalized Voronoi diagrams", IROS 2012, eq. (10), Sec. IV-A.
    """
    if max_candidates < 1:
        raise ValueError(f"max_candidates must be >= 1, got {max_candidates}")
    c = spectrum_correlation(angle_spectrum(a, n_angles), angle_spectrum(b, n_angles))
    n = c.size
    bin_rad = np.pi / n
    sep = max(1, round(np.radians(min_separation_deg) / bin_rad))
    out: list[HeadingCandidate] = []
    for j, peak in peak_bins(c, sep, (max_candidates + 1) // 2):
        delta = _refined_peak(c, j, bin_rad)
        var = _peak_variance(c, peak, bin_rad)
        for psi in (delta, delta + np.pi):
            out.append(HeadingCandidate(float(np.angle(np.exp(1j * psi))), var, float(c[j])))
    return out[:max_candidates]
