"""The decision on maps pooled to about 5 cm cells: frames, covariance, and a real pair."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from pgvd.grid import Grid, heading, rigid_matrix
from pgvd.inputs import registration_probability
from pgvd.io import read_map
from pgvd.merge import merge
from pgvd.params import MergeParams
from pgvd.pooling import (
    block_scale,
    covariance_from_pooled,
    decision_pool,
    from_pooled,
    to_pooled,
)
from pgvd.scoring import fine_maps
from pgvd.verify import pooled_maps, predicted_overlap, verify, wall_maps

EXAMPLES = Path(__file__).resolve().parent.parent / "examples"
PARAMS = MergeParams(diagnostics=False)

angles = st.floats(-np.pi, np.pi, allow_nan=False)
shifts = st.floats(-500.0, 500.0, allow_nan=False)
pools = st.integers(1, 6)


@pytest.mark.parametrize(
    ("resolution", "pool"), [(0.1, 1), (0.05, 1), (0.035, 1), (0.025, 2), (0.0175, 3), (0.01, 5)]
)
def test_decision_pool_is_the_multiple_nearest_5_cm(resolution: float, pool: int) -> None:
    assert decision_pool(resolution) == pool


@given(angles, shifts, shifts, pools)
def test_frames_round_trip_and_agree_on_points(psi: float, tx: float, ty: float, k: int) -> None:
    full = rigid_matrix(psi, tx, ty)
    pooled = to_pooled(full, k)
    assert np.allclose(from_pooled(pooled, k), full, atol=1e-9)
    # a B pixel taken to A through the pooled frames lands where the full matrix takes it
    x = np.array([37.0, -12.5, 1.0])
    through = block_scale(k) @ pooled @ np.linalg.solve(block_scale(k), x)
    assert np.allclose(through, full @ x, atol=1e-9)
    assert np.isclose(heading(pooled), heading(full))


@given(angles, shifts, shifts, pools)
def test_covariance_moves_with_the_frame_jacobian(psi: float, tx: float, ty: float, k: int) -> None:
    pooled = rigid_matrix(psi, tx, ty)
    cov = np.array([[0.3, 0.05, 1e-3], [0.05, 0.2, -2e-3], [1e-3, -2e-3, 1e-4]])

    def pose(m: np.ndarray) -> np.ndarray:
        full = from_pooled(m, k)
        return np.array([full[0, 2], full[1, 2], heading(full)])

    # numerical Jacobian of the full-frame (tx, ty, psi) in the pooled (tx, ty, psi)
    eps = 1e-6
    jac = np.zeros((3, 3))
    for j, step in enumerate(np.eye(3) * eps):
        hi = rigid_matrix(psi + step[2], tx + step[0], ty + step[1])
        lo = rigid_matrix(psi - step[2], tx - step[0], ty - step[1])
        diff = pose(hi) - pose(lo)
        diff[2] = np.angle(np.exp(1j * diff[2]))
        jac[:, j] = diff / (2 * eps)
    expected = jac @ cov @ jac.T
    assert np.allclose(covariance_from_pooled(cov, pooled, k), expected, rtol=1e-5, atol=1e-9)


def _finer(g: Grid, k: int) -> Grid:
    """The same map with every cell split into ``k x k``."""
    logodds = np.repeat(np.repeat(g.logodds, k, axis=0), k, axis=1)
    return Grid(logodds, g.resolution / k, g.origin)


@pytest.mark.slow
def test_a_finer_copy_of_a_pair_is_judged_as_the_pair() -> None:
    # Counted in cells at 1.67 cm, the decision's 2-cell tolerance was 3.3 cm: the
    # example pair's margin fell from 0.90 to 0.64 and its heading variance to a third.
    a, b = read_map(EXAMPLES / "intel_a.yaml"), read_map(EXAMPLES / "intel_b.yaml")
    params = MergeParams(diagnostics=False)
    base = merge(a, b, params)
    fine = merge(_finer(a, 3), _finer(b, 3), params)
    assert base.accepted and fine.accepted
    assert fine.margin == pytest.approx(base.margin, abs=0.05)
    assert fine.covariance[2, 2] == pytest.approx(base.covariance[2, 2], rel=0.05)
    truth = np.asarray(json.loads((EXAMPLES / "truth.json").read_text())["matrix"])
    to_fine = block_scale(3)
    fine_truth = to_fine @ truth @ np.linalg.inv(to_fine)
    assert abs(np.degrees(heading(fine.matrix) - heading(fine_truth))) < 0.2
    # within one 5 cm cell, three cells of the finer maps, at B's centre
    centre = np.array([b.shape[1] * 1.5, b.shape[0] * 1.5, 1.0])
    assert np.hypot(*((fine.matrix - fine_truth) @ centre)[:2]) < 3.0


def test_a_predicted_pose_on_finer_maps_is_checked_as_on_the_maps() -> None:
    a, b = read_map(EXAMPLES / "intel_a.yaml"), read_map(EXAMPLES / "intel_b.yaml")
    truth = np.asarray(json.loads((EXAMPLES / "truth.json").read_text())["matrix"])
    base = verify(a, b, truth)
    to_fine = block_scale(3)
    fine_truth = to_fine @ truth @ np.linalg.inv(to_fine)
    fine = verify(_finer(a, 3), _finer(b, 3), fine_truth)
    assert base.accepted and fine.accepted
    assert fine.margin == pytest.approx(base.margin, abs=0.05)
    # the same pose in metres: the finer matrix is the base one in the finer pixels
    assert np.allclose(fine.matrix, to_fine @ base.matrix @ np.linalg.inv(to_fine), atol=1e-6)
    assert fine.covariance[2, 2] == pytest.approx(base.covariance[2, 2], rel=1e-6)
    assert fine.covariance[0, 0] == pytest.approx(9 * base.covariance[0, 0], rel=0.05)


@pytest.mark.parametrize("metres", [0.0, 5.0, 30.0])
def test_where_a_prediction_puts_finer_maps_is_measured_as_on_the_maps(metres: float) -> None:
    # What the agent's chain check reads after a failed verify (agent.worker.verify_check).
    # Counted in cells at 1.67 cm, the overlap of these copies came out 1.4-1.8x longer.
    a, b = read_map(EXAMPLES / "intel_a.yaml"), read_map(EXAMPLES / "intel_b.yaml")
    truth = np.asarray(json.loads((EXAMPLES / "truth.json").read_text())["matrix"])
    predicted = rigid_matrix(0.0, metres / a.resolution, 0.0) @ truth
    refined = rigid_matrix(np.radians(1.0), 4.0, 0.0) @ predicted
    base = predicted_overlap(a, b, predicted, refined, PARAMS)
    to_fine = block_scale(3)
    fine = predicted_overlap(
        _finer(a, 3),
        _finer(b, 3),
        to_fine @ predicted @ np.linalg.inv(to_fine),
        to_fine @ refined @ np.linalg.inv(to_fine),
        PARAMS,
    )
    assert base.overlap_m > PARAMS.min_overlap
    assert fine.overlap_m == pytest.approx(base.overlap_m, rel=0.01)
    assert fine.shift_m == pytest.approx(base.shift_m, abs=0.05)
    assert fine.turn_deg == pytest.approx(base.turn_deg, abs=1e-6) == pytest.approx(1.0)


@pytest.mark.parametrize("metres", [0.0, 3.0])
def test_maps_read_once_give_what_each_check_reads_itself(metres: float) -> None:
    a, b = (
        _finer(read_map(EXAMPLES / "intel_a.yaml"), 2),
        _finer(read_map(EXAMPLES / "intel_b.yaml"), 2),
    )
    to_fine = block_scale(2)
    truth = np.asarray(json.loads((EXAMPLES / "truth.json").read_text())["matrix"])
    predicted = (
        rigid_matrix(0.0, metres / a.resolution, 0.0) @ to_fine @ truth @ np.linalg.inv(to_fine)
    )
    maps = pooled_maps(a, b, PARAMS)
    assert maps.pool == 2 and maps.cell == pytest.approx(0.05)
    alone, shared = verify(a, b, predicted, PARAMS), verify(a, b, predicted, PARAMS, maps)
    assert alone.accepted == shared.accepted == (metres == 0.0)
    assert alone.reason == shared.reason and np.array_equal(alone.matrix, shared.matrix)
    assert predicted_overlap(a, b, predicted, alone.matrix, PARAMS) == predicted_overlap(
        a, b, predicted, alone.matrix, PARAMS, maps
    )


def test_a_prediction_off_the_map_overlaps_nothing() -> None:
    a, b = read_map(EXAMPLES / "intel_a.yaml"), read_map(EXAMPLES / "intel_b.yaml")
    far = rigid_matrix(0.0, 5000.0, 0.0)
    seen = predicted_overlap(a, b, far, far, PARAMS)
    assert seen.overlap_m == 0.0 and seen.shift_m == 0.0 and seen.turn_deg == 0.0


def test_merge_says_when_it_pools() -> None:
    a, b = read_map(EXAMPLES / "intel_a.yaml"), read_map(EXAMPLES / "intel_b.yaml")
    lines: list[str] = []
    merge(_finer(a, 2), _finer(b, 2), MergeParams(diagnostics=False), progress=lines.append)
    assert "decision on the maps pooled 2x2: 0.050 m cells" in lines
    lines.clear()
    merge(a, b, MergeParams(diagnostics=False), progress=lines.append)
    assert not any("pooled" in line for line in lines)


def test_verify_reads_the_decisions_maps_as_the_merge_does() -> None:
    # verify pooled with the default wall threshold whatever MergeParams.occupied said:
    # a block holding a 0.7 cell and free cells was a 0.7 block to it, free to the merge
    a = read_map(EXAMPLES / "intel_a.yaml")
    params = MergeParams(diagnostics=False, occupied=0.8)
    fine = _finer(a, 2)
    logodds = fine.logodds.copy()
    free = np.argwhere(fine.probability() < 0.2)[0]
    logodds[free[0] - free[0] % 2, free[1] - free[1] % 2] = np.log(0.7 / 0.3)
    fine = Grid(logodds, fine.resolution, fine.origin)
    checked, _ = wall_maps(fine, fine, params, 2)
    decided, _ = fine_maps(*(registration_probability(fine, params),) * 2, params, 2)
    np.testing.assert_array_equal(checked.free, decided.free)
    np.testing.assert_array_equal(checked.walls, decided.walls)
