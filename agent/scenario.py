"""The fleet scenario of ``pgvd demo`` and the fleet benchmarks: one log, split among robots.

Each robot replays an overlapping segment of the bundled Intel Research Lab log (CC-BY 1.0,
recorded by Dirk Haehnel; Radish, Howard and Roy 2003) in a random frame of its own, so that
the robots' maps overlap pairwise but no two share a frame.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

#: The corrected Intel Research Lab log, a CARMEN log shipped in the package.
LOG = Path(__file__).resolve().parent / "data" / "intel-corrected.log.gz"


def segments(n: int) -> list[tuple[float, float]]:
    """Overlapping parts of the log for ``n`` robots, as fractions of its length.

    Parameters
    ----------
    n : int
        Number of robots, at least 2.

    Returns
    -------
    list of (float, float)
        ``(start, end)`` per robot, in [0, 1]: each segment is twice as long as its overlap
        with the next, and together they cover the whole log.
    """
    width = 2.0 / (n + 1)
    step = (1.0 - width) / (n - 1)
    return [(round(i * step, 4), round(min(1.0, i * step + width), 4)) for i in range(n)]


def random_frames(n: int, seed: int) -> list[tuple[float, float, float]]:
    """A random frame per robot: where its map's origin lies in the log's world.

    Parameters
    ----------
    n : int
        Number of robots.
    seed : int
        Seed of the generator: the same seed gives the same frames.

    Returns
    -------
    list of (float, float, float)
        ``(x m, y m, theta deg)`` per robot: rotations anywhere, shifts up to 20 m.
    """
    rng = np.random.default_rng(seed)
    return [
        (float(rng.uniform(-20, 20)), float(rng.uniform(-20, 20)), float(rng.uniform(0, 360)))
        for _ in range(n)
    ]


def known_pose(frame: tuple[float, float, float]) -> tuple[float, float, float]:
    """The pose of a robot's map frame in the log's world frame, for ``--known-pose``.

    Parameters
    ----------
    frame : ``(x m, y m, theta deg)``, a robot's frame as :func:`random_frames` draws it (the
        rigid transform from the log's world frame to the robot's map frame).

    Returns
    -------
    ``(x m, y m, yaw rad)``: the inverse transform, m-explore's ``init_pose_x/_y/_yaw``.
    """
    x, y, deg = frame
    yaw = math.radians(deg)
    c, s = math.cos(yaw), math.sin(yaw)
    return -(c * x + s * y), s * x - c * y, -yaw
