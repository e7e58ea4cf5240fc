"""Known initial poses, m-explore's ``known_init_poses``: a prior for each pair's transform.

``--known-pose ROBOT=x,y,yaw`` gives the pose of a robot's map frame in the merged (world)
frame, in metres and radians (REP 103), as m-explore's ``init_pose_x/_y/_yaw``. For two robots
with known poses, the prior of their maps' B-pixel -> A-pixel transform follows from the poses
and the grids' origins. The fusion worker checks a pair at its prior first (a local refinement
and the merge's own acceptance test, :func:`pgvd.verify.verify`, as in the merge of Saeedi et
al., IROS 2012, Sec. IV) and takes the link only if the check confirms it; otherwise the pair is
decided as if no pose were known (a chain's check or the full search), so a wrong prior is
never accepted as it stands, nor does it keep the true link from being found.
"""

from __future__ import annotations

import math
import re
from collections.abc import Iterable, Mapping

import numpy as np

from agent.keys import check_name
from agent.pose import POSE, Pose
from pgvd.grid import Grid, world_pose_to_pixel_matrix
from pgvd.integrate import se2

_KNOWN_POSE = re.compile(rf"(?P<robot>[^=]+)={POSE}")


def parse_known_pose(text: str) -> tuple[str, Pose]:
    """``ROBOT=x,y,yaw`` -> ``(robot, (x, y, yaw))``; ``ValueError`` (one line) otherwise."""
    m = _KNOWN_POSE.fullmatch(text.strip())
    if m is None:
        raise ValueError(
            f"known pose must be ROBOT=x,y,yaw (metres, radians), e.g. r2=4.0,-1.5,0.3; "
            f"got {text!r}"
        )
    robot = check_name(m["robot"], "robot id of a known pose")
    pose = (float(m["x"]), float(m["y"]), float(m["yaw"]))
    if not all(math.isfinite(v) for v in pose):
        raise ValueError(f"known pose of {robot} is not finite: {text!r}")
    return robot, pose


def parse_known_poses(texts: Iterable[str]) -> dict[str, Pose]:
    """Each ``--known-pose`` by robot; ``ValueError`` (one line) for a bad one or a robot twice."""
    poses: dict[str, Pose] = {}
    for text in texts:
        robot, pose = parse_known_pose(text)
        if robot in poses:
            raise ValueError(f"known pose of {robot} given twice")
        poses[robot] = pose
    return poses


def prior_matrix(a: Grid, pose_a: Pose, b: Grid, pose_b: Pose) -> np.ndarray:
    """The B-pixel -> A-pixel transform implied by both maps' known poses in the world frame.

    Parameters
    ----------
    a, b : the two robots' maps (their origins place cells in each robot's map frame).
    pose_a, pose_b : each map frame's pose ``(x, y, yaw)`` in the world frame.

    Returns
    -------
    3x3 matrix, B pixel -> A pixel (the convention of :func:`pgvd.merge`).
    """
    metric_b_to_a = np.linalg.inv(se2(*pose_a)) @ se2(*pose_b)
    return (
        world_pose_to_pixel_matrix(a) @ metric_b_to_a @ np.linalg.inv(world_pose_to_pixel_matrix(b))
    )


def pair_prior(
    poses: Mapping[str, Pose], a: str, grid_a: Grid, b: str, grid_b: Grid
) -> np.ndarray | None:
    """:func:`prior_matrix` of robots ``a`` and ``b`` if both poses are known, else None."""
    if a not in poses or b not in poses:
        return None
    return prior_matrix(grid_a, poses[a], grid_b, poses[b])
