"""A rejection keeps its best pose, and says whether it lies in the grey zone (a candidate)."""

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from pgvd.grid import Grid
from pgvd.io import read_map, write_map
from pgvd.merge import merge
from pgvd.params import DecisionParams, MergeParams

ROOT = Path(__file__).resolve().parents[1]
EXAMPLES = ROOT / "examples"
EXIT_NO_OVERLAP = 3


@pytest.fixture(scope="module")
def intel_pair() -> tuple[Grid, Grid]:
    return read_map(EXAMPLES / "intel_a.yaml"), read_map(EXAMPLES / "intel_b.yaml")


@pytest.fixture(scope="module")
def mirror(shared) -> tuple[Grid, Grid]:
    a = read_map(shared / "maps" / "fr079_split_gt" / "fr079_partA.yaml")
    return a, Grid(np.ascontiguousarray(a.logodds[:, ::-1]), a.resolution)


def test_a_pose_rejected_in_the_grey_zone_is_the_pose_and_a_candidate(intel_pair):
    a, b = intel_pair
    accepted = merge(a, b, MergeParams(diagnostics=False))
    assert accepted.accepted and not accepted.candidate
    # the same pair with the bar above its margin: rejected in the grey zone
    strict = MergeParams(diagnostics=False, min_margin=accepted.margin + 1.0)
    grey = merge(a, b, strict)
    assert not grey.accepted and "does not stand out" in grey.reason
    assert DecisionParams.GREY_MARGIN <= grey.margin < strict.decision.min_margin
    assert grey.candidate and grey.to_json()["candidate"] is True
    # the rejection keeps the pose the acceptance returned, not the identity
    np.testing.assert_array_equal(grey.matrix, accepted.matrix)
    assert grey.rotation_deg == accepted.rotation_deg
    assert grey.translation_px == accepted.translation_px
    assert np.isnan(grey.covariance).all()


def test_a_pose_below_the_grey_zone_is_kept_but_no_candidate(mirror):
    a, b = mirror
    r = merge(a, b, MergeParams(diagnostics=False))
    assert not r.accepted and r.margin < DecisionParams.GREY_MARGIN
    assert not r.candidate and r.to_json()["candidate"] is False
    assert not np.allclose(r.matrix, np.eye(3))


def test_cli_prints_the_rejected_pose_after_the_reason(mirror, tmp_path):
    a, b = mirror
    write_map(tmp_path / "a.yaml", a)
    write_map(tmp_path / "b.yaml", b)
    proc = subprocess.run(
        [sys.executable, "-m", "agent.cli", "merge", tmp_path / "a.yaml", tmp_path / "b.yaml"],
        capture_output=True,
        text=True,
        cwd=ROOT,
        timeout=300,
    )
    assert proc.returncode == EXIT_NO_OVERLAP, proc.stderr
    reason, pose = proc.stdout.splitlines()
    assert reason.startswith("no overlap: the best pose does not stand out")
    assert pose.startswith("best pose, not merged: rotation ") and "margin -" in pose
