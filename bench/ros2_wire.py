"""Bytes on the wire: pgvd map updates against the ROS 2 ``OccupancyGrid`` of the same map.

The plain ``nav_msgs/msg/OccupancyGrid`` a ROS 2 node publishes is CDR plus rmw_zenoh's
33-byte attachment.

The map is the Intel Research Lab log replayed at ROS's usual 0.05 m cells, as slam_toolbox would
grow it: after ``--first`` scans it is sent whole (pgvd: every tile and the manifest), then every
``--every`` scans again (ROS: the whole OccupancyGrid each time; pgvd: the changed tiles and the
manifest, :class:`agent.wire.Outbound`). Both sides are the agent's own encoders, and the
OccupancyGrid bytes are rosbags' serializer (equal to rclpy's, tests/test_protocol_ros2.py).

Usage::

    python3 -m bench ros2_wire [--first 300] [--every 20] [--out bench/results/ros2_wire.md]
"""

from __future__ import annotations

import argparse
from pathlib import Path

from agent.scenario import LOG
from agent.wire import Outbound, on_the_wire
from pgvd.carmen import read_carmen
from pgvd.integrate import frame_for, integrate_scan
from protocol.ros2.attachment import SIZE as ATTACHMENT
from protocol.ros2.occupancy import encode_occupancy_grid


def _pgvd_bytes(published: tuple[list[bytes], bytes]) -> int:
    tiles, manifest = published
    return sum(map(len, tiles)) + len(manifest)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--first", type=int, default=300, help="scans in the first (whole) map")
    ap.add_argument("--every", type=int, default=20, help="scans between two updates")
    ap.add_argument("--out", type=Path, help="also write the table here (Markdown)")
    args = ap.parse_args()
    scans = read_carmen(LOG)
    frame = frame_for(scans, 0.05)  # the whole log's canvas: slam_toolbox's grows, ours is fixed
    logodds = frame.empty()
    out = Outbound("bench", "r1", None)
    held = None
    rows, ros_total, pgvd_total = [], 0, 0
    stops = list(range(args.first, len(scans), args.every))
    done = 0
    for version, stop in enumerate(stops, start=1):
        for scan in scans[done:stop]:
            integrate_scan(logodds, scan, frame)
        done = stop
        grid = on_the_wire(frame.grid(logodds.copy()))
        ros = len(encode_occupancy_grid(grid, "map", 0)) + ATTACHMENT
        pgvd = _pgvd_bytes(out.prepare(version, grid, held))
        held = (version, grid)
        ros_total, pgvd_total = ros_total + ros, pgvd_total + pgvd
        if version in (1, 2, len(stops)):
            rows.append(f"| {version} | {stop} | {ros:,} | {pgvd:,} | {pgvd / ros:.2%} |")
    h, w = frame.shape
    header = (
        "| update | scans | OccupancyGrid + attachment (B) | pgvd tiles + manifest (B) | ratio |"
    )
    ratio = pgvd_total / ros_total
    total = f"| all {len(stops)} | | {ros_total:,} | {pgvd_total:,} | {ratio:.2%} |"
    text = "\n".join(
        [
            "# ROS 2 OccupancyGrid against pgvd map updates",
            "",
            f"`python3 -m bench ros2_wire --first {args.first} --every {args.every}`",
            "",
            f"Intel log at 0.05 m: {w}x{h} cells; first map after {args.first} scans, "
            f"then an update every {args.every} scans ({len(stops)} updates).",
            "",
            header,
            "|---|---|---|---|---|",
            *rows,
            total,
        ]
    )
    print(text)
    if args.out is not None:
        args.out.write_text(text + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
