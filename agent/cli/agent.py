"""``pgvd agent``: run one robot's daemon until SIGINT or SIGTERM."""

from __future__ import annotations

import argparse
import logging
import re
import signal
import sys
import threading
from pathlib import Path

import zenoh

from agent.cli.common import (
    EXIT_OK,
    CliError,
    check_resolution_option,
    read_fleet_key,
    require_extra,
)
from agent.failpoints import check_armed
from agent.inbox import MAX_BYTES
from agent.keys import check_name
from agent.outputs import OutputOptions
from agent.priors import parse_known_poses
from agent.ros2_io import RosOptions, agent_node_name
from agent.sources import parse_frame, parse_source
from agent.view import parse_endpoint
from agent.zenoh_config import (
    MODES,
    ZenohOptions,
    build_config,
    tile_session_options,
    zenoh_error,
)
from protocol.ros2.keys import FORMS, check_domain, check_topic
from protocol.ros2.occupancy import robot_map_frame
from protocol.ros2.types import DISTROS

#: A TF frame id: tf2 refuses a leading slash; the rest as ROS names.
_FRAME_ID = re.compile(r"[A-Za-z_][A-Za-z0-9_]*(/[A-Za-z_][A-Za-z0-9_]*)*")


def configure(p: argparse.ArgumentParser) -> None:
    """Add the arguments of ``pgvd agent`` to its parser."""
    p.description = __doc__
    p.add_argument("--robot", required=True, help="this robot's id ([A-Za-z0-9_-])")
    p.add_argument(
        "--source",
        required=True,
        help="carmen:LOG[@FROM-TO] (fractions), sim:IMAGE.yaml[@FROM-TO] (a simulated "
        "robot's drive through a map image), rosbag:BAG[:TOPIC] (a rosbag2's LaserScan "
        "and TF, or its recorded OccupancyGrid TOPIC), map:FILE.yaml, or ros2:/TOPIC (a ROS 2 "
        "OccupancyGrid, e.g. ros2:/robot1/map)",
    )
    p.add_argument("--state-dir", required=True, type=Path, help="persistent state directory")
    p.add_argument("--fleet", default="default", help="fleet name (key prefix pgvd/<fleet>/)")
    p.add_argument("--out", type=Path, help="where global.yaml/.pgm/.png go (default: state dir)")
    p.add_argument("--zenoh-config", type=Path, help="Zenoh JSON5 config the options extend")
    p.add_argument("--key-file", type=Path, help="fleet key file: messages carry an HMAC")
    p.add_argument("--listen", action="append", default=[], metavar="EP", help="listen endpoint")
    p.add_argument("--connect", action="append", default=[], metavar="EP", help="seed endpoint")
    p.add_argument("--mode", choices=MODES, default="peer", help="Zenoh mode (default peer)")
    p.add_argument("--multicast", action="store_true", help="multicast scouting (LAN)")
    # Off by default: a map travels as tiles of under 60 kB, for which a copy costs nothing,
    # while with it on every agent on a host maps a 16 MB pool per peer (measured at 8 agents:
    # 358 MB RSS per agent with it, 218 MB without; bench/results/fleet.md).
    p.add_argument(
        "--shm",
        choices=("on", "off"),
        default="off",
        help="Zenoh shared memory between agents on one host (default off)",
    )
    p.add_argument("--lease-ms", type=int, help="Zenoh transport lease (ms)")
    p.add_argument(
        "--tiles-listen",
        action="append",
        default=[],
        metavar="EP",
        help="publish map tiles best-effort on a second Zenoh session listening here (e.g. "
        "udp/IP:PORT); lost tiles are fetched over the main session",
    )
    p.add_argument(
        "--tiles-connect",
        action="append",
        default=[],
        metavar="EP",
        help="a peer's tile endpoint (with --tiles-listen: the tile session's seeds)",
    )
    p.add_argument("--frame", help="own frame x,y,theta_deg (default: drawn from the robot id)")
    p.add_argument("--resolution", type=float, default=0.1, help="carmen map cell size (m)")
    p.add_argument("--speed", type=float, default=50.0, help="carmen replay speed x real time")
    p.add_argument(
        "--link-timeout",
        type=float,
        default=6.0,
        help="s to wait for a live peer's link before registering the pair here",
    )
    p.add_argument("--announce", type=float, default=2.0, help="manifest re-announce period (s)")
    p.add_argument(
        "--min-change",
        type=float,
        default=0.05,
        help="fraction of known cells changing class that makes a new map version",
    )
    p.add_argument("--min-interval", type=float, default=1.0, help="s between own versions")
    p.add_argument(
        "--epoch-change",
        type=float,
        default=0.15,
        help="fraction of known cells changing class since the last registration epoch that "
        "makes peers register this map again",
    )
    p.add_argument(
        "--forget-after",
        type=float,
        default=300.0,
        help="s after a robot left (its liveliness token went away) before its map and links "
        "are forgotten, so memory does not grow with every robot ever seen",
    )
    p.add_argument(
        "--min-agreement",
        type=float,
        help="overlay agreement a link needs (default: the merge's own threshold)",
    )
    p.add_argument(
        "--known-pose",
        action="append",
        default=[],
        metavar="ROBOT=X,Y,YAW",
        help="a robot's map frame in the merged frame (m, rad; m-explore's init_pose_x/y/yaw); "
        "a pair of robots with known poses is checked there first and searched only if the "
        "check fails (repeat for each robot; give every agent the same poses)",
    )
    p.add_argument(
        "--inbox-mib",
        type=int,
        default=MAX_BYTES >> 20,
        help="MiB of received messages held for decoding; beyond, drops count as overload",
    )
    ros = p.add_argument_group("ROS 2 (over Zenoh: rmw_zenoh or zenoh-bridge-ros2dds)")
    ros.add_argument("--ros-domain", type=int, default=0, help="ROS_DOMAIN_ID (default 0)")
    ros.add_argument(
        "--ros-distro", choices=DISTROS, default="jazzy", help="the robots' distro (type hashes)"
    )
    ros.add_argument(
        "--ros-keys",
        choices=FORMS,
        default="rmw_zenoh",
        help="rmw_zenoh keys, attachments and tokens, or zenoh-bridge-ros2dds's bare topics",
    )
    ros.add_argument(
        "--ros-publish",
        metavar="TOPIC",
        help="publish the global map as a latched nav_msgs/OccupancyGrid here "
        "(e.g. /map_merged), with /tf_static from --ros-frame to each <robot>/map",
    )
    ros.add_argument(
        "--ros-links",
        metavar="TOPIC",
        help="publish the links between robots' maps as a latched visualization_msgs/MarkerArray "
        "here (e.g. /map_merged_links), one LINE_LIST per state, in --ros-frame, for RViz",
    )
    ros.add_argument("--ros-frame", default="world", help="the merged map's frame (default world)")
    ros.add_argument(
        "--ros-rate",
        type=float,
        default=1.0,
        help="Hz at which a new global map is looked for, Foxglove and the link markers sent "
        "(default 1)",
    )
    p.add_argument(
        "--foxglove", metavar="HOST:PORT", help="serve a live view to Foxglove or Lichtblick"
    )
    p.add_argument("-v", "--verbose", action="store_true", help="log timings too")
    p.set_defaults(func=run)


def options_from_args(args: argparse.Namespace):
    """Validate the arguments into :class:`agent.daemon.AgentOptions` (CliError if bad)."""
    from agent.daemon import AgentOptions

    try:
        robot = check_name(args.robot, "robot id")
        fleet = check_name(args.fleet, "fleet name")
        source = parse_source(args.source)
        frame = parse_frame(args.frame) if args.frame else None
        known_poses = parse_known_poses(args.known_pose)
        outputs = _output_options(args)
        check_armed()  # a misspelt failpoint must not let a crash test pass without a crash
    except ValueError as exc:
        raise CliError(str(exc)) from None
    _require_extras(source.kind, outputs)
    if source.path is not None and not source.path.exists():
        raise CliError(f"source file not found: {source.path}")
    if source.kind in ("carmen", "sim", "map") and source.path is not None and source.path.is_dir():
        raise CliError(f"source {source.kind}:{source.path} is a directory, not a file")
    check_resolution_option(args.resolution)
    for name in (
        "speed",
        "link_timeout",
        "announce",
        "min_interval",
        "inbox_mib",
        "ros_rate",
    ):
        if not getattr(args, name) > 0:
            raise CliError(f"--{name.replace('_', '-')} must be > 0")
    if not 0 <= args.min_change <= 1 or not 0 <= args.epoch_change <= 1:
        raise CliError("--min-change and --epoch-change must be in [0, 1]")
    if args.lease_ms is not None and not args.lease_ms > 0:
        raise CliError("--lease-ms must be > 0")
    if not args.forget_after > 0:
        raise CliError("--forget-after must be > 0")
    if args.min_agreement is not None and not 0 < args.min_agreement <= 1:
        raise CliError("--min-agreement must be in (0, 1]")
    key = read_fleet_key(args.key_file)
    zopts = ZenohOptions(
        mode=args.mode,
        listen=tuple(args.listen),
        connect=tuple(args.connect),
        multicast=args.multicast,
        shared_memory=args.shm == "on",
        lease_ms=args.lease_ms,
        config_file=args.zenoh_config,
    )
    tiles = None
    if args.tiles_listen or args.tiles_connect:
        tiles = tile_session_options(zopts, args.tiles_listen, args.tiles_connect)
    try:  # fail now, with one line, rather than inside the daemon
        for session in (zopts,) if tiles is None else (zopts, tiles):
            build_config(session)
    except ValueError as exc:
        raise CliError(str(exc)) from None
    try:
        args.state_dir.mkdir(parents=True, exist_ok=True)
        if args.out is not None:
            args.out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise CliError(f"cannot create directory: {exc}") from None
    return AgentOptions(
        robot=robot,
        source=source,
        state_dir=args.state_dir,
        fleet=fleet,
        out_dir=args.out,
        zenoh=zopts,
        key=key,
        frame=frame,
        resolution=args.resolution,
        speed=args.speed,
        link_timeout=args.link_timeout,
        announce_period=args.announce,
        tiles=tiles,
        min_change=args.min_change,
        min_interval=args.min_interval,
        min_agreement=args.min_agreement,
        epoch_change=args.epoch_change,
        forget_after=args.forget_after,
        inbox_bytes=args.inbox_mib << 20,
        outputs=outputs,
        known_poses=tuple(known_poses.items()),
    )


def _require_extras(source_kind: str, outputs: OutputOptions) -> None:
    """The optional dependencies the source and outputs use are installed (else CliError)."""
    if source_kind in ("ros2", "rosbag"):
        require_extra("rosbags", "ros2", f"--source {source_kind}:")
    for option, topic in (("--ros-publish", outputs.publish), ("--ros-links", outputs.links)):
        if topic is not None:
            require_extra("rosbags", "ros2", option)
    if outputs.foxglove is not None:
        require_extra("foxglove", "view", "--foxglove")


def _output_options(args: argparse.Namespace) -> OutputOptions:
    """The ROS 2 and Foxglove options (``ValueError`` with one line if bad)."""
    ros = RosOptions(
        domain=check_domain(args.ros_domain),
        distro=args.ros_distro,
        form=args.ros_keys,
        node=agent_node_name(args.robot),
    )
    for topic in (args.ros_publish, args.ros_links):
        if topic is not None:
            check_topic(topic)
    if args.ros_links is not None and args.ros_links == args.ros_publish:
        raise ValueError(f"--ros-links {args.ros_links} is the map's topic: give it one of its own")
    if not _FRAME_ID.fullmatch(args.ros_frame):
        raise ValueError(f"--ros-frame must be a TF frame id like world, got {args.ros_frame!r}")
    if args.ros_frame == robot_map_frame(args.ros_frame.partition("/")[0]):
        # the agent places every robot's map frame under it: a robot's own would be its own
        # parent, a transform tf2 refuses
        raise ValueError(
            f"--ros-frame {args.ros_frame} is a robot's map frame (<robot>/map); the merged "
            "frame needs a name of its own, such as world"
        )
    foxglove = parse_endpoint(args.foxglove) if args.foxglove else None
    return OutputOptions(
        ros, args.ros_publish, args.ros_frame, args.ros_rate, foxglove, args.ros_links
    )


def run(args: argparse.Namespace) -> int:
    opts = options_from_args(args)
    logging.basicConfig(
        level=logging.WARNING,
        format=f"%(asctime)s {opts.robot} %(levelname)s %(message)s",
        stream=sys.stderr,
    )
    # The agent's decisions (links, global maps, robots joining) are INFO and always logged:
    # journald and a launcher's agent.log read stderr. Its timings are DEBUG, on -v.
    logging.getLogger("pgvd.agent").setLevel(logging.DEBUG if args.verbose else logging.INFO)
    from agent.daemon import Agent

    try:
        agent = Agent(opts)
    except ValueError as exc:
        raise CliError(str(exc)) from None
    stop = threading.Event()

    def on_signal(signum: int, _frame: object) -> None:
        stop.set()

    previous = {sig: signal.signal(sig, on_signal) for sig in (signal.SIGTERM, signal.SIGINT)}
    try:
        agent.run(stop)
    except zenoh.ZError as exc:  # e.g. the listen port is taken: one line, not a traceback
        raise CliError(f"cannot open the Zenoh session: {zenoh_error(exc)}") from None
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    return EXIT_OK
