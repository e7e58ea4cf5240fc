"""Rotation alignment by angle spectra, eq. (10), on real maps."""

from __future__ import annotations

import numpy as np
import pytest

from pgvd.grid import rigid_matrix
from pgvd.io import read_map
from pgvd.rotation import angle_spectrum, estimate_headings, peak_bins, spectrum_correlation
from pgvd.transform import warp


def _rotated(p: np.ndarray, psi: float) -> np.ndarray:
    """``p`` rotated by ``psi`` (eq. (2)) about its centre onto a canvas that holds it whole."""
    h, w = p.shape
    side = int(np.hypot(h, w)) + 4
    m = rigid_matrix(psi, 0.0, 0.0)
    m[:2, 2] = (side - 1) / 2.0 - m[:2, :2] @ np.array([(w - 1) / 2.0, (h - 1) / 2.0])
    return warp(p, m, (side, side), order=0, cval=0.5)


def _angle_error(a: float, b: float) -> float:
    return abs(float(np.angle(np.exp(1j * (a - b)))))


@pytest.fixture(scope="module")
def intel_a(shared):
    return read_map(shared / "maps/intel_split_gt/intel_partA.yaml").probability()


@pytest.mark.parametrize("deg", [7.0, 93.5, 211.0, 334.0])
def test_heading_recovered_on_rotated_real_map(intel_a, deg):
    # B = A rotated by +deg, so rotating B by -deg aligns it with A.
    b = _rotated(intel_a, np.radians(deg))
    cands = estimate_headings(intel_a, b)
    assert len(cands) == 6
    errors = [np.degrees(_angle_error(c.psi, -np.radians(deg))) for c in cands]
    assert min(errors) < 1.0, errors
    assert all(c.variance > 0 for c in cands)
    # the best candidate is the top one, and its 180 and 90 degree twins are offered too
    best = cands[int(np.argmin(errors))]
    assert best is cands[0] or best is cands[1]
    assert any(_angle_error(c.psi, best.psi + np.pi) < 1e-9 for c in cands)
    assert any(abs(_angle_error(c.psi, best.psi) - np.pi / 2) < np.radians(5) for c in cands)


def test_spectrum_peaks_at_wall_normal():
    p = np.full((101, 101), 0.1)
    p[50, 10:90] = 0.9  # a horizontal wall: its normal points along the rows (theta = 90 deg)
    s = angle_spectrum(p, n_angles=180)
    assert int(np.argmax(s)) == 90


def test_spectrum_correlation_finds_circular_shift():
    rng = np.random.default_rng(0)
    s = rng.random(360)
    # b(theta) = s(theta - 37 bins), so s(theta) = b(theta + 37): the peak is at delta = 37.
    c = spectrum_correlation(s, np.roll(s, 37))
    assert int(np.argmax(c)) == 37
    assert c.max() == pytest.approx(1.0)


def test_no_occupied_cells_is_an_error():
    with pytest.raises(ValueError, match="no occupied"):
        angle_spectrum(np.full((20, 20), 0.1))
    with pytest.raises(ValueError, match="max_candidates"):
        estimate_headings(np.eye(5), np.eye(5), max_candidates=0)


def test_a_twin_where_the_correlation_is_not_concave_has_its_parents_width() -> None:
    # One peak at bin 60; a quarter turn away (bin 240) the correlation only falls.
    bins = np.arange(360)
    c = np.exp(-0.5 * ((bins - 60) / 4.0) ** 2) - 0.001 * bins
    assert peak_bins(c, sep=10, count=2) == [(60, 60), (231, 60)]


def test_every_candidate_heading_has_a_width_of_its_own_walls(intel_a) -> None:
    # intel turned by 334 deg: a twin where the correlation is not concave had variance
    # (pi / 4)^2 (a 45 deg sigma), which blurred B's walls away at that heading (8)
    # before its PGVD was built.  It now has the width of the peak it twins.
    b = _rotated(intel_a, np.radians(334.0))
    sigmas = [np.degrees(np.sqrt(c.variance)) for c in estimate_headings(intel_a, b)]
    assert len(sigmas) == 6 and max(sigmas) < 2.0, sigmas
