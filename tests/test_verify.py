"""pgvd.verify: a predicted transform is confirmed cheaply, or rejected, never taken as it is."""

from __future__ import annotations

import importlib
import re

import numpy as np
import pytest
from scipy.stats import chi2

from bench.covariance import pose_error
from bench.data.pairs import make_pair
from pgvd.carmen import read_carmen
from pgvd.grid import Grid, relative_matrix, rigid_matrix
from pgvd.io import read_map
from pgvd.params import MergeParams
from pgvd.transform import resample
from pgvd.verify import BASIN_DEG, BASIN_M, basin_move, predicted_overlap, verify

PARAMS = MergeParams(diagnostics=False)


def _load(shared, rel: str) -> Grid:
    g = read_map(shared / "maps" / rel)
    return g if np.isclose(g.resolution, 0.05) else resample(g, 0.05)


@pytest.fixture(scope="module", params=["intel-log", "intel-split", "fr079-split"])
def pair(request, shared) -> tuple[Grid, Grid, np.ndarray]:
    """(A, B, true B->A matrix): two segments of the Intel log, and the two split maps."""
    if request.param == "intel-log":
        scans = read_carmen(shared / "logs" / "intel-corrected.log.gz")
        p = make_pair(scans, (0.0, 0.55), (0.45, 1.0), seed=3)
        return p.a, p.b, p.truth
    name = request.param.split("-")[0]
    a = _load(shared, f"{name}_split_gt/{name}_partA.yaml")
    b = _load(shared, f"{name}_split_gt/{name}_partB.yaml")
    return a, b, relative_matrix(a, b)


def _perturbed(truth: np.ndarray, b: Grid, metres: float, degrees: float, towards: float):
    """``truth`` turned by ``degrees`` about B's wall centroid and shifted ``metres``."""
    r, c = np.nonzero(b.probability() > 0.65)
    centre = (truth @ np.array([c.mean(), r.mean(), 1.0]))[:2]
    m = rigid_matrix(np.radians(degrees), 0.0, 0.0)
    step = metres / b.resolution * np.array([np.cos(towards), np.sin(towards)])
    m[:2, 2] = centre - m[:2, :2] @ centre + step
    return m @ truth


def _error_px(m: np.ndarray, truth: np.ndarray, b: Grid) -> float:
    """Mean displacement (cells) of B's walls between two B->A matrices."""
    r, c = np.nonzero(b.probability() > 0.65)
    pts = np.vstack([c, r, np.ones_like(c)])
    return float(np.hypot(*((m - truth) @ pts)[:2]).mean())


@pytest.mark.parametrize(("metres", "degrees"), [(0.0, 0.0), (0.3, 2.0), (0.3, -2.0)])
def test_near_prediction_accepted_and_refined(pair, metres, degrees):
    a, b, truth = pair
    for towards in (0.0, 2.0, 4.0):
        guess = _perturbed(truth, b, metres, degrees, towards)
        res = verify(a, b, guess, PARAMS)
        assert res.accepted, res.reason
        # the merge's own test: the pose stands out from itself shifted (pgvd.decision)
        assert res.margin >= PARAMS.min_margin, res.margin
        assert _error_px(res.matrix, truth, b) < 2.0
        assert np.isfinite(res.covariance).all() and np.all(np.linalg.eigvalsh(res.covariance) > 0)
        assert {"refine", "verify", "covariance", "total"} <= set(res.timings_ms)


@pytest.mark.parametrize(
    ("metres", "degrees"),
    [(2.0, 10.0), (3.0, -15.0), (5.0, 30.0), (2.0, -30.0), (0.0, 10.0), (2.0, 0.0)],
)
def test_wrong_prediction_rejected(pair, metres, degrees):
    a, b, truth = pair
    for towards in (0.5, 2.5, 4.5):
        res = verify(a, b, _perturbed(truth, b, metres, degrees, towards), PARAMS)
        assert not res.accepted, (metres, degrees, towards, res.score)
        assert np.isnan(res.covariance).all()
        assert res.reason != "accepted"


def test_verified_covariance_is_the_calibrated_one(pair):
    """The covariance covers the verified pose's true error, as the merge's does.

    It used to be the Laplace covariance alone, which put these errors at
    NEES 9 to 333 (sigma_psi 0.005-0.011 deg against the merge's 0.02-0.1 deg).
    """
    a, b, truth = pair
    res = verify(a, b, truth, PARAMS)
    assert res.accepted, res.reason
    error = pose_error(truth, res.matrix)
    assert error @ np.linalg.solve(res.covariance, error) < chi2.ppf(0.999, 3)


def test_basin_bounds_how_far_refinement_may_move(pair, monkeypatch):
    """A correction larger than the basin is a rejection, even where the overlay would pass."""
    a, b, truth = pair
    guess = _perturbed(truth, b, 0.3, 2.0, 1.0)
    assert verify(a, b, guess, PARAMS).accepted
    monkeypatch.setattr(importlib.import_module("pgvd.verify"), "BASIN_M", 0.05)
    res = verify(a, b, guess, PARAMS)
    assert not res.accepted and "basin" in res.reason


def test_basin_move_measures_at_the_centroid():
    walls = np.array([[100.0, 100.0], [120.0, 100.0], [110.0, 120.0]])
    centre = walls.mean(axis=0)
    turn = rigid_matrix(np.radians(3.0), 0.0, 0.0)
    turn[:2, 2] = centre - turn[:2, :2] @ centre  # about the centroid: no shift there
    shift, deg = basin_move(np.eye(3), turn, walls)
    assert shift == pytest.approx(0.0, abs=1e-9) and deg == pytest.approx(3.0)
    shift, deg = basin_move(np.eye(3), rigid_matrix(0.0, 3.0, 4.0), walls)
    assert shift == pytest.approx(5.0) and deg == pytest.approx(0.0)
    assert BASIN_M > 0.3 and BASIN_DEG > 2.0  # the tested near predictions lie inside


def test_bad_predictions_are_errors(shared):
    a = _load(shared, "intel_split_gt/intel_partA.yaml")
    with pytest.raises(ValueError, match="finite 3x3"):
        verify(a, a, np.full((3, 3), np.nan))
    with pytest.raises(ValueError, match="finite 3x3"):
        verify(a, a, np.eye(2))
    with pytest.raises(ValueError, match="not a rigid"):
        verify(a, a, np.diag([2.0, 2.0, 1.0]))
    with pytest.raises(ValueError, match="resolutions"):
        verify(a, resample(a, 0.1), np.eye(3))
    # a cell size of a nanometre or a gigametre (a wrong or hostile one) is refused, not
    # pooled into an array of petabytes
    for res in (1e-9, 1e9):
        odd = Grid(a.logodds, res, a.origin)
        why = re.escape(f"map A: a cell size of {res:g} m is outside")
        with pytest.raises(ValueError, match=why):
            verify(odd, odd, np.eye(3))
    small = Grid(a.logodds[:10, :10], a.resolution, a.origin)
    with pytest.raises(ValueError, match=r"map A spans .* too small to merge at 0.05 m/cell"):
        verify(small, small, np.eye(3))


def test_empty_map_is_a_rejection(shared):
    a = _load(shared, "intel_split_gt/intel_partA.yaml")
    blank = Grid(np.zeros((50, 50), np.float32), a.resolution)
    res = verify(a, blank, np.eye(3))
    assert not res.accepted and "wall cells" in res.reason


def test_small_crisp_overlap_is_confirmed(shared):
    """A 4 m square of intel's part B, 11 m of walls in all, checked at its true place in part
    A: confirmed, as the merge accepts a small crisp overlap.  The fixed floor the check had
    before (an overlay agreement of 0.92 over at least 15 m of walls) refused every overlap
    this small.  Slid 2 m along either axis, it is rejected (by whichever test)."""
    a = _load(shared, "intel_split_gt/intel_partA.yaml")
    b = _load(shared, "intel_split_gt/intel_partB.yaml")
    row, col = 480, 120
    square = Grid(b.logodds[row : row + 80, col : col + 80].copy(), b.resolution, b.origin)
    truth = relative_matrix(a, b) @ rigid_matrix(0.0, col, row)
    res = verify(a, square, truth, PARAMS)
    assert res.accepted, res.reason
    # walls of either map on the other's known space, agreeing or not: the old floor counted
    # only the agreeing ones
    assert predicted_overlap(a, square, truth, res.matrix, PARAMS).overlap_m < 15.0
    assert _error_px(res.matrix, truth, square) < 1.0
    for dx, dy in ((40, 0), (0, 40), (-40, 0), (0, -40)):
        wrong = rigid_matrix(0.0, dx, dy) @ truth
        assert not verify(a, square, wrong, PARAMS).accepted, (dx, dy)
