"""pgvd.inflation: the merge covariance widened where the evidence is thin, never narrowed."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from pgvd.alignment import AlignmentFit, alignment_fit
from pgvd.covariance import calibrated_covariance
from pgvd.grid import rigid_matrix
from pgvd.inflation import (
    MEASURED,
    EvidenceModel,
    centroid_shift,
    direction_factors,
    dof_factor,
    inflate,
    inflated_covariance,
)
from pgvd.io import read_map
from pgvd.merge import MergeParams
from pgvd.model_error import MODEL_ERROR_SCALE, model_error_covariance
from pgvd.walls import WallMap

PARAMS = MergeParams()


def _fit(a_prob: np.ndarray, b_prob: np.ndarray, matrix: np.ndarray) -> AlignmentFit:
    a = WallMap(a_prob, PARAMS.occupied, PARAMS.free)
    b = WallMap(b_prob, PARAMS.occupied, PARAMS.free)
    fit = alignment_fit(a.tree, b.walls, matrix)
    assert fit is not None
    return fit


def _at_centroid(cov: np.ndarray, fit: AlignmentFit) -> np.ndarray:
    a = centroid_shift(fit.centroid, fit.psi)
    return a @ cov @ a.T


def _grown(before: np.ndarray, after: np.ndarray) -> np.ndarray:
    """Eigenvalues of ``before^-1 after``: how much the variance grew in each direction."""
    return np.sort(np.linalg.eigvals(np.linalg.solve(before, after)).real)


@pytest.fixture(scope="module")
def corridor(shared: Path) -> tuple[AlignmentFit, float]:
    """The straight corridor of the freiburg-079 map (two long walls and nothing across
    them), aligned on itself one cell along it."""
    grid = read_map(shared / "maps" / "fr079_split_gt" / "fr079_partA.yaml")
    crop = grid.probability()[150:230, 565:645]
    return _fit(crop, crop, rigid_matrix(0.0, 1.0, 0.0)), grid.resolution


@pytest.fixture(scope="module")
def rich(intel_split) -> tuple[AlignmentFit, float]:
    """The two halves of the Intel lab at their true pose: walls every way."""
    pair = intel_split
    return _fit(pair.a.probability(), pair.b.probability(), pair.truth), pair.a.resolution


def test_the_measured_constants_are_in_range() -> None:
    assert 0.0 < MEASURED.normal_noise < 0.5 and MEASURED.correlation_m > 0.0


@pytest.mark.parametrize("case", ["corridor", "rich"])
def test_real_overlaps_are_never_narrowed(case: str, request: pytest.FixtureRequest) -> None:
    fit, res = request.getfixturevalue(case)
    cov = calibrated_covariance(fit, res)
    out = inflate(cov, fit, res)
    assert _grown(cov, out)[0] >= 1.0 - 1e-9
    assert np.linalg.eigvalsh(out - cov).min() >= -1e-12 * np.abs(out).max()


def test_any_covariance_is_never_narrowed() -> None:
    rng = np.random.default_rng(7)
    for _ in range(200):
        j = rng.normal(size=(rng.integers(3, 40), 3)) * [1.0, 1.0, 50.0]
        info = j.T @ j * rng.uniform(1, 500)
        fit = AlignmentFit(info, 0.2, rng.uniform(-300, 300, 2), rng.uniform(-np.pi, np.pi))
        m = rng.normal(size=(3, 3)) * [1.0, 1.0, 0.01]
        cov = m @ m.T + 1e-12 * np.eye(3)
        model = EvidenceModel(rng.uniform(0, 0.4), rng.uniform(0.01, 2.0))
        out = inflate(cov, fit, rng.uniform(0.02, 0.2), model)
        assert _grown(cov, out)[0] >= 1.0 - 1e-7


def test_a_corridor_is_widened_along_it_more_than_across(corridor) -> None:
    fit, res = corridor
    cov = calibrated_covariance(fit, res)
    before, after = _at_centroid(cov, fit), _at_centroid(inflate(cov, fit, res), fit)
    along, across = after[0, 0] / before[0, 0], after[1, 1] / before[1, 1]
    assert along > 1.5 * across and across < 1.3


def test_a_rich_overlap_barely_changes(rich) -> None:
    fit, res = rich
    cov = calibrated_covariance(fit, res)
    assert _grown(cov, inflate(cov, fit, res))[-1] < 1.3


def test_the_merge_reports_the_inflated_fit(intel_split) -> None:
    pair = intel_split
    a = WallMap(pair.a.probability(), PARAMS.occupied, PARAMS.free)
    b = WallMap(pair.b.probability(), PARAMS.occupied, PARAMS.free)
    fit = alignment_fit(a.tree, b.walls, pair.truth)
    res = pair.a.resolution
    bent = model_error_covariance(a.tree, b.walls, pair.truth)
    expected = inflate(calibrated_covariance(fit, res), fit, res) + MODEL_ERROR_SCALE * bent
    assert inflated_covariance(a, b, pair.truth, res) == pytest.approx(expected)


def test_no_fit_and_an_infinite_covariance_pass_through() -> None:
    inf = np.diag([np.inf] * 3)
    assert np.array_equal(inflate(inf, None, 0.05), inf)
    fit = AlignmentFit(np.eye(3), 0.1, np.zeros(2), 0.0)
    assert np.array_equal(inflate(inf, fit, 0.05), inf)


def test_factors_follow_the_information() -> None:
    # walls every way: within a few per cent of the normal noise's own share
    k, _ = direction_factors(np.diag([2000.0, 2000.0]), 0.05, 8.0)
    assert k == pytest.approx([1.0 / 0.9 * 0.95] * 2, rel=1e-6)
    # all normals across x: what little information lies along x is the noise's
    k, vec = direction_factors(np.diag([60.0, 3940.0]), 0.05, 8.0)
    assert abs(vec[0, 0]) == pytest.approx(1.0) and k[0] == pytest.approx(60.0 / 8.0)
    assert k[1] == pytest.approx(3940.0 * 0.95 / (3940.0 - 200.0))
    assert dof_factor(3000.0, 10.0) == pytest.approx(1.01)
    assert dof_factor(0.0, 10.0) == np.inf


@pytest.mark.parametrize(
    ("call", "message"),
    [
        (lambda: inflate(np.eye(2), None, 0.05), "covariance must be 3x3"),
        (lambda: inflate(np.full((3, 3), np.nan), None, 0.05), "covariance holds NaN"),
        (lambda: inflate(np.triu(np.ones((3, 3))), None, 0.05), "covariance must be symmetric"),
        (lambda: inflate(np.eye(3), None, 0.0), "resolution must be > 0"),
        (lambda: direction_factors(np.diag([-5.0, 10.0]), 0.05, 8.0), "positive semi-definite"),
        (lambda: direction_factors(np.diag([np.inf, 1.0]), 0.05, 8.0), "must be finite"),
        (lambda: direction_factors(np.eye(2), 0.5, 8.0), "normal noise must be in"),
        (lambda: direction_factors(np.eye(2), 0.05, 0.0), "independent measurement must be > 0"),
        (lambda: dof_factor(-1.0, 8.0), "cells must be >= 0"),
        (lambda: dof_factor(float("nan"), 8.0), "cells must be >= 0"),
    ],
)
def test_bad_input_is_one_clear_error(call, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        call()
