"""pgvd.model_error: the disagreement of a bent map's parts, read from the fit's residuals."""

from __future__ import annotations

import numpy as np
import pytest

from pgvd.alignment import alignment_fit
from pgvd.merge import MergeParams
from pgvd.model_error import model_error_covariance
from pgvd.walls import WallMap

PARAMS = MergeParams()


def _walls(pair) -> tuple[WallMap, np.ndarray]:
    a = WallMap(pair.a.probability(), PARAMS.occupied, PARAMS.free)
    b = WallMap(pair.b.probability(), PARAMS.occupied, PARAMS.free)
    return a, b.walls


def _bent(walls: np.ndarray, degrees: float) -> np.ndarray:
    """``walls`` with the cells right of their median column turned by ``degrees`` about
    the median point: one map's far half swung by drift."""
    pivot = np.median(walls, axis=0)
    far = walls[:, 0] > pivot[0]
    c, s = np.cos(np.radians(degrees)), np.sin(np.radians(degrees))
    out = walls.astype(float)
    out[far] = (out[far] - pivot) @ np.array([[c, s], [-s, c]]) + pivot
    return out


def test_a_rigid_pair_gives_about_the_laplace_covariance(intel_split) -> None:
    a, b = _walls(intel_split)
    m = model_error_covariance(a.tree, b, intel_split.truth)
    assert np.linalg.eigvalsh(m).min() >= -1e-12 * np.abs(m).max()
    fit = alignment_fit(a.tree, b, intel_split.truth)
    laplace = fit.sigma2 * np.linalg.inv(fit.info) * (len(b) / 4000)
    ratio = np.diag(m) / np.diag(laplace)
    assert np.all((ratio > 0.1) & (ratio < 30.0))


def test_a_bent_map_is_far_less_certain_than_a_rigid_one(intel_split) -> None:
    a, b = _walls(intel_split)
    rigid = model_error_covariance(a.tree, b, intel_split.truth)
    bent = model_error_covariance(a.tree, _bent(b, 1.0), intel_split.truth)
    assert np.linalg.eigvalsh(bent - rigid).max() > 0
    assert bent[2, 2] > 10.0 * rigid[2, 2]


def test_too_few_matched_cells_give_no_term(intel_split) -> None:
    a, b = _walls(intel_split)
    m = model_error_covariance(a.tree, b[:30], intel_split.truth)
    assert np.array_equal(m, np.zeros((3, 3)))


def test_a_bad_radius_is_one_clear_error(intel_split) -> None:
    a, b = _walls(intel_split)
    with pytest.raises(ValueError, match="radius must be > 0 px"):
        model_error_covariance(a.tree, b, intel_split.truth, radius=0.0)
