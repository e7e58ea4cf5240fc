"""Placements snapped to a lattice before they are fused: small, pure, and still valid."""

from __future__ import annotations

import numpy as np
import pytest

from agent.placement import TRANSLATION_STEP_PX, heading_step, snap_placement
from pgvd.grid import heading, rigid_matrix
from pgvd.uncertainty import check_covariance

SHAPE = (400, 600)


def test_a_snapped_placement_is_within_half_a_step_and_on_the_lattice() -> None:
    m = rigid_matrix(0.7312345, 123.456789, -45.678901)
    cov = np.array([[2.0, 0.3, 1e-3], [0.3, 1.5, -2e-3], [1e-3, -2e-3, 4e-5]])
    snapped, snapped_cov = snap_placement(m, cov, SHAPE)
    step = heading_step(SHAPE)
    assert abs(heading(snapped) - heading(m)) <= step / 2 + 1e-12
    assert np.abs(snapped[:2, 2] - m[:2, 2]).max() <= TRANSLATION_STEP_PX / 2
    assert np.all(snapped[:2, 2] / TRANSLATION_STEP_PX == np.round(snapped[:2, 2] * 32))
    sigma, got = np.sqrt(np.diag(cov)), np.sqrt(np.diag(snapped_cov))
    assert np.abs(got / sigma - 1).max() < 0.012
    corr = cov / np.outer(sigma, sigma)
    assert np.abs(snapped_cov / np.outer(got, got) - corr).max() <= 0.0101
    assert np.array_equal(snap_placement(m, cov, SHAPE)[1], snapped_cov)  # pure
    # the far corner moves by the heading's snap by at most half a step's arc
    corner = np.array([SHAPE[1] - 1, SHAPE[0] - 1, 1.0])
    turn = rigid_matrix(heading(snapped) - heading(m), 0.0, 0.0) @ corner - corner
    assert np.hypot(*turn[:2]) <= 1 / 64 + 1e-9


def test_a_placement_a_hair_away_snaps_to_the_same_bytes() -> None:
    m = rigid_matrix(0.31, 10.3, 20.7)
    cov = np.diag([1.0, 1.2, 1e-5])
    hair = rigid_matrix(1e-12, 1e-10, -1e-10) @ m
    one, other = snap_placement(m, cov, SHAPE), snap_placement(hair, cov * (1 + 1e-12), SHAPE)
    assert one[0].tobytes() == other[0].tobytes() and one[1].tobytes() == other[1].tobytes()


def test_the_anchor_stays_exactly_the_identity() -> None:
    snapped, cov = snap_placement(np.eye(3), np.zeros((3, 3)), SHAPE)
    assert snapped.tobytes() == np.eye(3).tobytes() and cov.tobytes() == bytes(72)


@pytest.mark.parametrize(
    "cov",
    [
        np.array([[1.0, 0.999, 0.0], [0.999, 1.0, 0.999], [0.0, 0.999, 1.0]]) * 0.5,
        np.diag([0.0, 2.0, 1e-6]),
    ],
)
def test_a_snapped_covariance_stays_positive_semi_definite(cov: np.ndarray) -> None:
    _, snapped = snap_placement(np.eye(3), cov, SHAPE)
    check_covariance(snapped)
    assert (snapped[np.diag(cov) == 0] == 0).all()


def test_inputs_that_are_not_finite_are_left_for_the_fusion_to_refuse() -> None:
    cov = np.diag([1.0, np.nan, 1e-5])
    _, got = snap_placement(np.eye(3), cov, SHAPE)
    assert np.array_equal(got, cov, equal_nan=True)
