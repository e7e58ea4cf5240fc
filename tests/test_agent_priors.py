"""agent.priors: known initial poses give the true transform of real maps that share a frame."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from agent.pose import parse_pose
from agent.priors import (
    pair_prior,
    parse_known_pose,
    parse_known_poses,
    prior_matrix,
)
from pgvd.grid import Grid, relative_matrix
from pgvd.integrate import se2
from pgvd.io import read_map


def test_poses_of_a_shared_frame_give_the_ground_truth(shared) -> None:
    # The halves of a log rendered in one world frame: the truth is their origins' difference.
    a, b = (read_map(p) for p in sorted((shared / "maps" / "intel_split_gt").glob("*.yaml")))
    np.testing.assert_allclose(
        prior_matrix(a, (0.0, 0.0, 0.0), b, (0.0, 0.0, 0.0)), relative_matrix(a, b), atol=1e-9
    )


def test_a_moved_map_frame_is_undone_by_its_pose(shared) -> None:
    """B re-expressed in a frame turned by 0.4 rad and shifted: its pose there gives the truth."""
    a, b = (read_map(p) for p in sorted((shared / "maps" / "intel_split_gt").glob("*.yaml")))
    x, y, yaw = 3.0, -2.0, 0.4
    c, s = math.cos(yaw), math.sin(yaw)
    # B's origin seen from a frame whose pose in the world is (x, y, yaw).
    ox, oy, oyaw = b.origin
    local = (c * (ox - x) + s * (oy - y), -s * (ox - x) + c * (oy - y), oyaw - yaw)
    moved = Grid(b.logodds, b.resolution, local)
    np.testing.assert_allclose(
        prior_matrix(a, (0.0, 0.0, 0.0), moved, (x, y, yaw)), relative_matrix(a, b), atol=1e-6
    )


poses = st.tuples(st.floats(-50, 50), st.floats(-50, 50), st.floats(-3.1, 3.1))


@given(poses, poses, poses)
def test_priors_compose_around_a_chain(pa, pb, pc) -> None:
    grids = [
        Grid(np.zeros((h, w), np.float32), 0.05, o)
        for h, w, o in [
            (40, 30, (1.0, 2.0, 0.0)),
            (25, 50, (-3.0, 0.5, 0.2)),
            (60, 20, (0.0, 0.0, -1.0)),
        ]
    ]
    a, b, c = grids
    np.testing.assert_allclose(
        prior_matrix(a, pa, b, pb) @ prior_matrix(b, pb, c, pc),
        prior_matrix(a, pa, c, pc),
        atol=1e-6,
    )


def test_a_prior_needs_both_poses() -> None:
    g = Grid(np.zeros((4, 4), np.float32))
    assert pair_prior({"r1": (0.0, 0.0, 0.0)}, "r1", g, "r2", g) is None
    assert pair_prior({"r1": (0, 0, 0), "r2": (1, 0, 0)}, "r1", g, "r2", g) is not None


def test_known_poses_parse() -> None:
    assert parse_known_pose("robot_2=4.0,-1.5,0.3") == ("robot_2", (4.0, -1.5, 0.3))
    assert parse_known_pose("r1=0,0,0") == ("r1", (0.0, 0.0, 0.0))
    assert parse_known_pose("r1=1e1,.5,-3.14") == ("r1", (10.0, 0.5, -3.14))


@pytest.mark.parametrize("text", ["r1", "r1=1,2", "r1=1,2,3,4", "=1,2,3", "r1=a,2,3", "r1=1;2;3"])
def test_bad_known_poses_get_one_line(text: str) -> None:
    with pytest.raises(ValueError, match="ROBOT=x,y,yaw"):
        parse_known_pose(text)


finite = st.floats(allow_nan=False, allow_infinity=False, width=64)


@given(st.from_regex(r"[A-Za-z0-9][A-Za-z0-9_-]{0,11}", fullmatch=True), finite, finite, finite)
def test_known_poses_round_trip(robot: str, x: float, y: float, yaw: float) -> None:
    assert parse_known_pose(f"{robot}={x!r},{y!r},{yaw!r}") == (robot, (x, y, yaw))


@given(finite, finite, finite)
def test_bare_poses_round_trip(x: float, y: float, yaw: float) -> None:
    """``pgvd merge --prior x,y,yaw``: the pose alone, as after ``ROBOT=``."""
    assert parse_pose(f"{x!r},{y!r},{yaw!r}") == (x, y, yaw)


@given(st.text(max_size=40))
def test_any_text_is_a_bare_pose_or_gets_one_line(text: str) -> None:
    try:
        pose = parse_pose(text)
    except ValueError as exc:
        why = str(exc)
        assert "\n" not in why and ("x,y,yaw" in why or "finite" in why)
    else:
        assert len(pose) == 3 and all(math.isfinite(v) for v in pose)


@given(st.text(max_size=40))
def test_any_text_parses_or_gets_one_line(text: str) -> None:
    try:
        robot, pose = parse_known_pose(text)
    except ValueError as exc:
        assert "\n" not in str(exc)
    else:
        assert "=" not in robot and all(math.isfinite(v) for v in pose)


def test_a_robot_known_twice_is_refused() -> None:
    assert parse_known_poses(["r1=0,0,0", "r2=1,2,3"]) == {"r1": (0, 0, 0), "r2": (1, 2, 3)}
    with pytest.raises(ValueError, match="known pose of r1 given twice"):
        parse_known_poses(["r1=0,0,0", "r1=1,2,3"])


@pytest.mark.parametrize("text", ["r/1=1,2,3", "r 1=1,2,3"])
def test_a_known_pose_needs_a_robot_id(text: str) -> None:
    with pytest.raises(ValueError, match="robot id"):
        parse_known_pose(text)


def test_a_huge_known_pose_is_not_finite() -> None:
    with pytest.raises(ValueError, match="not finite"):
        parse_known_pose("r1=1e999,0,0")


@given(st.floats(-20, 20), st.floats(-20, 20), st.floats(0, 360))
def test_a_replay_frame_gives_the_pose_of_its_map_frame(x: float, y: float, deg: float) -> None:
    """:func:`agent.scenario.known_pose` inverts the world -> map transform a replay uses."""
    from agent.scenario import known_pose

    world_to_map = se2(x, y, math.radians(deg))
    np.testing.assert_allclose(se2(*known_pose((x, y, deg))) @ world_to_map, np.eye(3), atol=1e-9)
