"""The fleet scenario of ``pgvd demo`` and the fleet benchmarks: one run, split among robots.

Each robot replays an overlapping segment of one run -- by default the bundled Intel Research
Lab log (CC-BY 1.0, recorded by Dirk Haehnel; Radish, Howard and Roy 2003), or a user's CARMEN
log, or a simulated drive through a map image -- in a random frame of its own, so that the
robots' maps overlap pairwise but no two share a frame.  :func:`check_run` refuses a run
that cannot give every robot a map before any agent starts.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from agent.sources import SourceSpec, load_scans
from pgvd.integrate import select_segment

#: The corrected Intel Research Lab log, a CARMEN log shipped in the package.
LOG = Path(__file__).resolve().parent / "data" / "intel-corrected.log.gz"
#: Fewest scans a robot's segment must hold: fewer leave a map too small to register.
MIN_SEGMENT_SCANS = 50


def check_run(kind: str, path: Path, robots: int) -> int:
    """Read the run a fleet would split, and check that it holds a map for every robot.

    Parameters
    ----------
    kind : ``"carmen"`` (a CARMEN laser log, gzip or not) or ``"sim"`` (a map_server
        YAML whose image a simulated robot drives through).
    path : the log or the map's YAML.
    robots : how many robots share the run (:func:`segments`).

    Returns
    -------
    int
        The number of scans in the whole run.

    Raises
    ------
    ValueError
        One line: a missing or unreadable file, a log with no ``FLASER`` line, a corrupt
        gzip stream, a map with no free space to drive, or a run whose :func:`segments`
        hold fewer than :data:`MIN_SEGMENT_SCANS` scans each.
    """
    what = "log" if kind == "carmen" else "map"
    if not path.exists():
        raise ValueError(f"{what} not found: {path}")
    if not path.is_file():
        raise ValueError(f"{what} {path} is not a file")
    try:
        scans = load_scans(SourceSpec(kind, path))
    except OSError as exc:
        raise ValueError(f"cannot read {path}: {exc.strerror or exc}") from None
    except ValueError as exc:  # not every reader names the file
        line = str(exc).splitlines()[0]
        raise ValueError(line if str(path) in line else f"{path}: {line}") from None
    if not scans:
        raise ValueError(f"{path}: no FLASER lines, not a CARMEN laser log")
    fewest = min(len(select_segment(scans, seg)) for seg in segments(robots))
    if fewest < MIN_SEGMENT_SCANS:
        longer = "longer log" if kind == "carmen" else "bigger map"
        raise ValueError(
            f"{path}: its {len(scans)} scans give {robots} robots {fewest} each, "
            f"at least {MIN_SEGMENT_SCANS} needed: use fewer robots or a {longer}"
        )
    return len(scans)


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
