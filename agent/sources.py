"""Where a robot's own map comes from: a replayed laser log, a map_server file or a ROS 2 topic.

``carmen:LOG[@FROM-TO]``
    Replays the fraction ``FROM``-``TO`` of a laser log, ``speed`` times faster than it
    was recorded, integrating each scan by ray casting (:mod:`pgvd.integrate`) into a map
    in a frame of the robot's own: a rigid transform of the log's world frame, drawn
    deterministically from the robot id unless given.  The frame is reported so that a
    demo or a test can compute the true relative transforms.  A gap in the log's
    timestamps costs at most :data:`MAX_GAP_WALL_S` of wall time (:func:`compress_gaps`).
``sim:IMAGE.yaml[@FROM-TO]``
    The same replay of a simulated drive through a map_server image: one tour of its
    reachable free space (:func:`pgvd.trajectory.drive`, the same for every robot, so
    segments of it overlap as log segments do), scanned by a simulated laser
    (:mod:`pgvd.lidar`) whose world is the image's walls, in the image's own metric frame.
``rosbag:BAG[:TOPIC]``
    The same replay of a rosbag2's ``sensor_msgs/msg/LaserScan`` topic, each scan placed by
    the bag's TF or odometry (:func:`pgvd.rosbag.read_rosbag_scans`); or, when ``TOPIC`` is
    a recorded ``nav_msgs/msg/OccupancyGrid`` topic (a SLAM's ``/map``), a replay of its
    maps, each taken when its bag time comes as a ``ros2:`` source takes a live one.
``map:FILE.yaml``
    Follows a map_server file that an external SLAM rewrites: a new map is read only when
    the YAML and image have been unchanged for one poll (a writer may be half-way), and a
    file that fails to read is counted (``read_errors`` in the status) and retried on the
    next poll.
``ros2:/TOPIC``
    Follows a ``nav_msgs/msg/OccupancyGrid`` topic: the host subscribes
    (:class:`agent.ros2_io.RosMapSubscription`) and hands the source its ``take``.

A source bumps its *version* only through :class:`ChangeGate`, when the map changed
enough, so every version is worth registering again (:mod:`agent.links`).
"""

from __future__ import annotations

import hashlib
import logging
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from pgvd.grid import Grid, world_pose_to_pixel_matrix
from pgvd.io import MapFormatError, read_map
from pgvd.map_yaml import map_image_path
from protocol.ros2.occupancy import robot_map_frame

if TYPE_CHECKING:
    from pgvd.carmen import LaserScan
    from protocol.ros2.occupancy import RosMap

log = logging.getLogger("pgvd.agent")


#: What ``--source`` accepts, for one-line errors.
FORMS = (
    "carmen:LOG[@FROM-TO], sim:IMAGE.yaml[@FROM-TO], rosbag:BAG[:TOPIC], map:FILE.yaml "
    "or ros2:/TOPIC"
)
#: Wall seconds a gap in a recording's timestamps costs at most in a replay: a log that was
#: paused for hours replays its two halves one after the other, not hours apart.
MAX_GAP_WALL_S = 1.0
#: Seed of the tour a ``sim:`` source drives and of its range noise: the same drive on every
#: robot, so that their segments of it overlap.
SIM_SEED = 0


@dataclass(frozen=True)
class SourceSpec:
    """A parsed ``--source``: ``kind`` is "carmen", "sim", "rosbag", "map" or "ros2".

    ``path`` is the log, bag or map file (None for ``ros2``); ``segment`` the fraction of a
    ``carmen`` log or ``sim`` drive; ``topic`` the bag's LaserScan
    or OccupancyGrid topic (None: its only LaserScan topic) or the ROS 2 map topic.
    """

    kind: str
    path: Path | None
    segment: tuple[float, float] = (0.0, 1.0)
    topic: str | None = None


def parse_source(spec: str) -> SourceSpec:
    """Parse a ``--source`` (:data:`FORMS`); ``ValueError`` (one line) if bad."""
    if spec.startswith("map:"):
        path = Path(spec[4:])
        if not spec[4:]:
            raise ValueError("map source needs a file: map:FILE.yaml")
        return SourceSpec("map", path)
    if spec.startswith("ros2:"):
        from protocol.ros2.keys import check_topic

        return SourceSpec("ros2", None, topic=check_topic(spec[5:]))
    if spec.startswith("rosbag:"):
        return _parse_rosbag(spec[7:])
    for kind in ("carmen", "sim"):
        if spec.startswith(kind + ":") and spec[len(kind) + 1 :]:
            return _parse_segmented(kind, spec[len(kind) + 1 :])
    raise ValueError(f"source must be {FORMS}, got {spec!r}")


def _parse_segmented(kind: str, rest: str) -> SourceSpec:
    """``FILE[@FROM-TO]`` of a ``carmen`` or ``sim`` source: what follows the last ``@`` is
    the segment, unless the whole of ``rest`` names an existing file (a name holding ``@``)."""
    path, sep, segment = rest.rpartition("@")
    if not sep or Path(rest).is_file():
        return SourceSpec(kind, Path(rest))
    if not path:
        what = "log" if kind == "carmen" else "map"
        raise ValueError(
            f"{kind} source needs a {what} before @{segment}: {kind}:{what.upper()}[@FROM-TO]"
        )
    lo_text, _, hi_text = segment.partition("-")  # no "-": hi_text is "", no number
    try:
        lo, hi = float(lo_text), float(hi_text)
    except ValueError:
        raise ValueError(
            f"{kind} segment must be @FROM-TO, fractions of the run such as @0.2-0.6, "
            f"got @{segment}"
        ) from None
    if not 0.0 <= lo < hi <= 1.0:
        raise ValueError(f"segment must satisfy 0 <= FROM < TO <= 1, got {lo}-{hi}")
    return SourceSpec(kind, Path(path), (lo, hi))


def _parse_rosbag(rest: str) -> SourceSpec:
    """``BAG[:TOPIC]``: a topic is absolute, so ``:/`` splits it from the bag's path."""
    bag, sep, topic = rest.rpartition(":")
    if not sep or not topic.startswith("/"):
        bag, topic = rest, ""
    if not bag:
        raise ValueError("rosbag source needs a bag: rosbag:BAG[:TOPIC]")
    if topic:
        from protocol.ros2.keys import check_topic

        check_topic(topic)
    return SourceSpec("rosbag", Path(bag), topic=topic or None)


def frame_for_robot(robot: str, span_m: float = 20.0) -> tuple[float, float, float]:
    """A deterministic "random" rigid frame ``(x m, y m, theta rad)`` for a robot id.

    Different robots get unrelated frames, so nothing in the fleet can rely on maps
    sharing one; the same robot gets the same frame after a restart.
    """
    seed = int.from_bytes(hashlib.sha256(f"pgvd-frame:{robot}".encode()).digest()[:8], "big")
    rng = np.random.default_rng(seed)
    x, y = rng.uniform(-span_m, span_m, size=2)
    return (float(x), float(y), float(rng.uniform(0.0, 2.0 * np.pi)))


def parse_frame(text: str) -> tuple[float, float, float]:
    """``"x,y,theta_deg"`` -> ``(x, y, theta rad)``; ``ValueError`` (one line) if bad."""
    parts = text.split(",")
    try:
        x, y, deg = (float(p) for p in parts)
    except ValueError:
        raise ValueError(f"frame must be x,y,theta_deg, got {text!r}") from None
    if not np.isfinite([x, y, deg]).all():
        raise ValueError(f"frame must be finite, got {text!r}")
    return (x, y, float(np.deg2rad(deg)))


class ChangeGate:
    """Decides when a changing map deserves a new version.

    A new version is due when at least ``min_fraction`` of the known cells changed
    their occupancy class (free/unknown/occupied) since the last version and
    ``min_interval`` seconds passed, or when the source finished (the final map).
    """

    def __init__(self, min_fraction: float = 0.05, min_interval: float = 1.0) -> None:
        self.min_fraction = min_fraction
        self.min_interval = min_interval
        self._last: np.ndarray | None = None
        self._last_time = -np.inf

    def reset(self, grid: Grid | None, now: float) -> None:
        self._last = None if grid is None else _classes(grid.logodds)
        self._last_time = now

    def due(self, grid: Grid, now: float, final: bool = False) -> bool:
        cls = _classes(grid.logodds)
        if self._last is not None and self._last.shape == cls.shape:
            changed = int(np.count_nonzero(cls != self._last))
            if changed == 0:
                return False
            known = max(int(np.count_nonzero(cls)), 1)
            if not final and (
                changed < self.min_fraction * known or now - self._last_time < self.min_interval
            ):
                return False
        elif not final and now - self._last_time < self.min_interval:
            return False
        self._last = cls
        self._last_time = now
        return True


def epoch_due(base: Grid | None, grid: Grid, min_fraction: float) -> bool:
    """Whether ``grid`` starts a new registration epoch after the epoch begun by ``base``.

    Yes when there is no base, the canvas moved (shape, resolution or origin: pixel
    frames differ, so links of the old epoch do not apply), or at least ``min_fraction``
    of the known cells changed class since the base.
    """
    if base is None or base.shape != grid.shape:
        return True
    if base.resolution != grid.resolution or tuple(base.origin) != tuple(grid.origin):
        return True
    cls = _classes(grid.logodds)
    changed = int(np.count_nonzero(cls != _classes(base.logodds)))
    return changed >= min_fraction * max(int(np.count_nonzero(cls)), 1)


def _classes(logodds: np.ndarray) -> np.ndarray:
    """-1 free, 0 unknown, 1 occupied: what registration sees of a map."""
    return np.sign(logodds).astype(np.int8)


def load_scans(spec: SourceSpec) -> list[LaserScan]:
    """The scans of a ``carmen:`` log, a ``sim:`` drive or a ``rosbag:`` bag, in the CARMEN form.

    Raises
    ------
    ValueError
        A log, map or bag that cannot be read (:class:`pgvd.rosbag.BagFormatError` for
        bags, :class:`pgvd.io.MapFormatError` for map images), or a map with no room to drive.
    """
    assert spec.path is not None
    if spec.kind == "rosbag":
        from pgvd.rosbag import read_rosbag_scans

        return read_rosbag_scans(spec.path, spec.topic)
    if spec.kind == "sim":
        from pgvd.trajectory import drive

        return drive(read_map(spec.path), SIM_SEED)
    from pgvd.carmen import read_carmen

    try:
        return read_carmen(spec.path)
    except OSError as exc:  # e.g. a directory: one line, not a traceback
        raise ValueError(f"cannot read {spec.path}: {exc.strerror or exc}") from None


def compress_gaps(stamps: np.ndarray, speed: float, max_wall: float = MAX_GAP_WALL_S) -> np.ndarray:
    """A recording's timestamps with every gap cut to what ``max_wall`` s replay at ``speed``.

    Parameters
    ----------
    stamps : recording times, seconds, in replay order.
    speed : replay speed, times real time (``inf``: no gap is cut, none is waited for).
    max_wall : wall seconds a gap may cost at most.

    Returns
    -------
    numpy.ndarray
        Stamps that start at the first one and keep every step up to ``max_wall * speed``
        seconds (steps backwards too), so a replay paced by them waits at most ``max_wall``
        between two records.
    """
    stamps = np.asarray(stamps, dtype=np.float64)
    if stamps.size == 0:
        return stamps
    steps = np.minimum(np.diff(stamps), max_wall * speed)
    return stamps[0] + np.concatenate([[0.0], np.cumsum(steps)])


class ReplayClock:
    """The recording's time that is due at a monotonic ``now``, replayed at ``speed``.

    Shared by the log and bag replays: the clock starts at the first :meth:`horizon`,
    at the record the replay resumes from, so a restarted agent goes on where it stopped
    instead of jumping ahead by the time it was down.
    """

    def __init__(self, speed: float) -> None:
        self.speed = speed
        self._t0: float | None = None

    def horizon(self, now: float, first: float, resume: float) -> float:
        """Recording time due at ``now``; ``first`` is the recording's first stamp and
        ``resume`` the stamp of the record the replay starts (or resumes) at."""
        if self._t0 is None:
            self._t0 = now - (resume - first) / self.speed
        return first + (now - self._t0) * self.speed


class CarmenSource:
    """Replays laser scans into a growing local map, in the robot's own frame.

    The scans come from a CARMEN log segment, a simulated drive or a rosbag2
    (:func:`load_scans`); either way they are cast the same, at the pace they were recorded
    but for gaps (:func:`compress_gaps`).

    Parameters
    ----------
    spec : a ``carmen:``, ``sim:`` or ``rosbag:`` :class:`SourceSpec`.
    frame : ``(x, y, theta)`` rigid transform from the log's world frame to the robot's.
    resolution : metres per cell.
    speed : replay speed, times real time (log timestamps); ``inf`` integrates at once.
    resume : ``(logodds, cursor)`` persisted by an earlier run, to continue where it stopped.
    """

    def __init__(
        self,
        spec: SourceSpec,
        frame: tuple[float, float, float],
        resolution: float,
        speed: float,
        resume: tuple[np.ndarray, int] | None = None,
    ) -> None:
        from pgvd.integrate import frame_for, se2, select_segment

        self.kind = spec.kind
        self.scans = select_segment(load_scans(spec), spec.segment)
        if not self.scans:
            raise ValueError(f"{spec.path}: segment {spec.segment} holds no scans")
        self.spec = spec
        self.frame = frame
        self.map_frame = frame_for(self.scans, resolution, se2(*frame))
        self.cursor = 0
        self.logodds = np.zeros(self.map_frame.shape, dtype=np.float32)
        if resume is not None and resume[0].shape == self.logodds.shape:
            self.logodds = resume[0].astype(np.float32, copy=True)
            self.cursor = min(int(resume[1]), len(self.scans))
        self._clock = ReplayClock(speed)
        self._stamps = compress_gaps(np.array([s.timestamp for s in self.scans]), speed)

    @property
    def done(self) -> bool:
        return self.cursor >= len(self.scans)

    def step(self, now: float) -> bool:
        """Integrate the scans due by ``now`` (monotonic seconds); True if any was."""
        from pgvd.integrate import integrate_scan

        if self.done:
            return False
        stamps = self._stamps
        horizon = self._clock.horizon(now, stamps[0], stamps[self.cursor])
        start = self.cursor
        while self.cursor < len(self.scans) and stamps[self.cursor] <= horizon:
            integrate_scan(self.logodds, self.scans[self.cursor], self.map_frame)
            self.cursor += 1
        return self.cursor > start

    def grid(self) -> Grid:
        return self.map_frame.grid(self.logodds.copy())

    def resume_state(self) -> dict[str, object]:
        return {"cursor": self.cursor}

    def describe(self) -> dict[str, object]:
        """Status entry; ``world_to_pixel`` (log world metres -> map pixels) and
        ``canvas_shape`` (the map's rows, columns) give the truth."""
        to_pixel = world_pose_to_pixel_matrix(self.map_frame.grid(self.logodds))
        return {
            "kind": self.kind,
            "path": str(self.spec.path),
            "segment": list(self.spec.segment),
            "frame": list(self.frame),
            "world_to_pixel": (to_pixel @ self.map_frame.world_to_map).tolist(),
            "canvas_shape": list(self.map_frame.shape),
            "progress": [self.cursor, len(self.scans)],
            "done": self.done,
        }


class MapFileSource:
    """Follows a map_server YAML that another process rewrites.

    A changed file is read once its YAML and image stat (size, mtime) are the same on two
    consecutive polls, so a writer caught half-way is simply read later; a file that
    still fails to parse is counted in :attr:`errors` and retried.
    """

    kind = "map"

    def __init__(self, spec: SourceSpec, poll: float = 0.5) -> None:
        self.spec = spec
        self.poll = poll
        self.errors = 0
        self.last_error: str | None = None
        self._grid: Grid | None = None
        self._seen: tuple[object, ...] | None = None
        self._stable: tuple[object, ...] | None = None
        self._next = 0.0

    done = False

    def step(self, now: float) -> bool:
        if now < self._next:
            return False
        self._next = now + self.poll
        stamp = self._stat()
        if stamp is None or stamp == self._seen:
            return False
        if stamp != self._stable:
            self._stable = stamp  # changed since last poll: may be mid-write, wait one poll
            return False
        try:
            grid = read_map(self.spec.path)
        except (MapFormatError, OSError, ValueError) as exc:
            self.errors += 1
            self.last_error = str(exc).splitlines()[0]
            return False
        # the file reads again: an error that comes back later is a new one, said again
        self.last_error = None
        self._seen = stamp
        if self._grid is not None and _same_grid(grid, self._grid):
            return False
        self._grid = grid
        return True

    def _stat(self) -> tuple[object, ...] | None:
        """Size and mtime of the YAML and its image; None while there is no YAML yet.

        An image that cannot be found (bad YAML, missing file) is stamped None
        rather than skipped, so once the files hold still :func:`read_map` runs
        and its error is counted: a map that never loads never goes unnoticed.
        """
        try:
            yaml_stat = self.spec.path.stat()
        except OSError:
            return None
        try:
            image_stat = map_image_path(self.spec.path).stat()
            image: tuple[int, int] | None = (image_stat.st_size, image_stat.st_mtime_ns)
        except (MapFormatError, OSError):
            image = None
        return (yaml_stat.st_size, yaml_stat.st_mtime_ns, image)

    def grid(self) -> Grid:
        if self._grid is None:
            raise RuntimeError("no map read yet")
        return self._grid

    def resume_state(self) -> dict[str, object]:
        return {}

    def describe(self) -> dict[str, object]:
        return {
            "kind": self.kind,
            "path": str(self.spec.path),
            "done": False,
            "read_errors": self.errors,
            "last_error": self.last_error,
        }


def _same_grid(a: Grid, b: Grid) -> bool:
    return (
        a.shape == b.shape
        and a.resolution == b.resolution
        and tuple(a.origin) == tuple(b.origin)
        and np.array_equal(a.logodds, b.logodds)
    )


class RosTopicSource:
    """Follows a ROS 2 ``nav_msgs/msg/OccupancyGrid`` topic (slam_toolbox's ``/map``).

    The host declares the subscription once its Zenoh session is open and hands over its
    ``take`` (:meth:`attach`); each map taken that differs from the last is a new map for
    the change gate, which alone decides versions, as for map files. Refused samples are
    counted by the host, not here.
    """

    kind = "ros2"
    done = False

    def __init__(self, spec: SourceSpec, frame: str) -> None:
        """``frame`` is the TF frame the agent places this robot's map in (``<robot>/map``)."""
        self.spec = spec
        self.frame = frame
        self.received = 0
        self._take: Callable[[], RosMap | None] | None = None
        self._map: RosMap | None = None

    def attach(self, take: Callable[[], RosMap | None]) -> None:
        """Read maps from ``take`` (None when nothing new came)."""
        self._take = take

    def step(self, now: float) -> bool:
        ros = None if self._take is None else self._take()
        if ros is None:
            return False
        self.received += 1
        if self._map is not None and _same_grid(ros.grid, self._map.grid):
            return False  # a latched map sent again (a reconnect, another cache)
        if ros.frame_id != self.frame and (self._map is None or self._map.frame_id != ros.frame_id):
            # said when such a frame first arrives or comes back, not with every map: the
            # merge is right either way, but the TF the agent publishes hangs under a frame
            # the robot's own tree does not have
            log.warning(
                "%s: maps arrive in frame %r, but the agent places this robot's map as %r: "
                "its TF tree stays apart from the merged frame (set slam_toolbox's map_frame "
                "to %r)",
                self.spec.topic, ros.frame_id, self.frame, self.frame,
            )  # fmt: skip
        self._map = ros
        return True

    def grid(self) -> Grid:
        if self._map is None:
            raise RuntimeError("no map received yet")
        return self._map.grid

    def resume_state(self) -> dict[str, object]:
        return {}

    def describe(self) -> dict[str, object]:
        return {
            "kind": self.kind,
            "topic": self.spec.topic,
            "done": False,
            "received": self.received,
            "frame_id": None if self._map is None else self._map.frame_id,
            "stamp_ns": None if self._map is None else self._map.stamp_ns,
        }


class RosbagGridSource:
    """Replays the maps a rosbag2 recorded on a ``nav_msgs/msg/OccupancyGrid`` topic.

    The maps due by the replay clock (bag time, ``speed`` times real time) are skipped to the
    latest, which replaces the robot's map whole, as a SLAM node's next ``/map`` does; the
    change gate alone decides versions. A map that does not decode is refused for the reason
    a live ``ros2:`` topic would refuse it, counted (``refused`` in the status), and the map
    before it stays.

    Parameters
    ----------
    spec : a ``rosbag:BAG:TOPIC`` :class:`SourceSpec` whose topic is an OccupancyGrid one.
    speed : replay speed, times real time; ``inf`` takes the last map at once.
    cursor : maps already replayed by an earlier run (resuming).
    """

    kind = "rosbag"

    def __init__(self, spec: SourceSpec, speed: float, cursor: int = 0) -> None:
        from pgvd.rosbag import read_rosbag_grids

        assert spec.path is not None and spec.topic is not None
        self.spec = spec
        self.recorded = read_rosbag_grids(spec.path, spec.topic)
        if not self.recorded:
            raise ValueError(f"{spec.path}: no map recorded on {spec.topic}")
        self.cursor = min(cursor, len(self.recorded))
        self.refused = 0
        self.last_error: str | None = None
        self._map: RosMap | None = None
        self._clock = ReplayClock(speed)

    @property
    def done(self) -> bool:
        return self.cursor >= len(self.recorded)

    def step(self, now: float) -> bool:
        """Take the latest map due by ``now`` (monotonic seconds); True if one was taken."""
        from protocol.ros2.occupancy import GridRefused, decode_occupancy_grid

        if self.done:
            return False
        horizon = self._clock.horizon(now, self.recorded[0][0], self.recorded[self.cursor][0])
        due = self.cursor
        while due < len(self.recorded) and self.recorded[due][0] <= horizon:
            due += 1
        if due == self.cursor:
            return False
        self.cursor = due
        try:
            self._map = decode_occupancy_grid(self.recorded[due - 1][1])
        except GridRefused as exc:
            self.refused += 1
            self.last_error = f"{exc.what}: {exc}"
            # The bag's last map refused: the one before it is the final one.
            return self.done and self._map is not None
        return True

    def grid(self) -> Grid:
        if self._map is None:
            raise RuntimeError("no map replayed yet")
        return self._map.grid

    def resume_state(self) -> dict[str, object]:
        return {"cursor": self.cursor}

    def describe(self) -> dict[str, object]:
        return {
            "kind": self.kind,
            "path": str(self.spec.path),
            "topic": self.spec.topic,
            "progress": [self.cursor, len(self.recorded)],
            "done": self.done,
            "refused": self.refused,
            "last_error": self.last_error,
            "frame_id": None if self._map is None else self._map.frame_id,
        }


Source = CarmenSource | MapFileSource | RosTopicSource | RosbagGridSource


def make_source(
    spec: SourceSpec,
    robot: str,
    frame: tuple[float, float, float] | None,
    resolution: float,
    speed: float,
    resume: object | None = None,
) -> Source:
    """The source of ``spec``; ``resume`` is the robot's persisted :class:`StoredMap`.

    Raises
    ------
    ValueError
        A missing or unreadable log/map (one line).
    """
    if spec.kind == "ros2":
        return RosTopicSource(spec, robot_map_frame(robot))
    assert spec.path is not None
    if not spec.path.exists():
        raise ValueError(f"source file not found: {spec.path}")
    if spec.kind == "map":
        return MapFileSource(spec)
    state = None
    if resume is not None:
        extra = getattr(resume, "extra", {}) or {}
        grid = getattr(resume, "grid", None)
        if grid is not None and "cursor" in extra:
            state = (grid.logodds, int(extra["cursor"]))
    if spec.kind == "rosbag" and spec.topic is not None:
        from pgvd.rosbag import GRID, topic_types

        if topic_types(spec.path).get(spec.topic) == GRID:
            return RosbagGridSource(spec, speed, 0 if state is None else state[1])
    return CarmenSource(spec, frame or frame_for_robot(robot), resolution, speed, state)
