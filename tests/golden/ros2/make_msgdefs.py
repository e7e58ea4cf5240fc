"""Write msgdefs.json, the .msg texts zenoh-ros2-sdk needs offline (run by hand after a change).

    .venv/bin/python tests/golden/ros2/make_msgdefs.py

zenoh-ros2-sdk reads a message type's ``.msg`` file at run time, from a local directory first
and else from a git clone of the ROS 2 interface repositories; it computes the type hash of
the data key from those texts. tests/test_fleet_ros2_sdk.py lays this file out as that local
directory, so the SDK runs with no network.

The texts come from rosbags' Jazzy typestore, which holds the ROS 2 message definitions as
fields and constants: comments and field defaults (Quaternion's ``w 1``) are absent, neither
of which enters a RIHS01 type hash or the CDR. One entry per type that an OccupancyGrid or a
TFMessage holds, each naming its nested types ``pkg/Name`` as a ``.msg`` file does.
"""

from __future__ import annotations

import json
from pathlib import Path

from rosbags.typesys import Stores, get_typestore

OUT = Path(__file__).resolve().parent / "msgdefs.json"
ROOTS = ("nav_msgs/msg/OccupancyGrid", "tf2_msgs/msg/TFMessage")
# generate_msgdef joins a type and its dependencies the ROS 1 way: this line, then "MSG: pkg/Name"
SEPARATOR = "=" * 80 + "\n"


def msg_texts(root: str) -> dict[str, str]:
    """``root`` and every type it nests -> its ``.msg`` text."""
    joined, _ = get_typestore(Stores.ROS2_JAZZY).generate_msgdef(root, ros_version=2)
    first, *nested = joined.split(SEPARATOR)
    texts = {root: first}
    for part in nested:
        head, text = part.split("\n", 1)
        pkg, name = head.removeprefix("MSG: ").split("/")
        texts[f"{pkg}/msg/{name}"] = text
    return texts


def main() -> None:
    texts: dict[str, str] = {}
    for root in ROOTS:
        texts |= msg_texts(root)
    OUT.write_text(json.dumps(dict(sorted(texts.items())), indent=1) + "\n")


if __name__ == "__main__":
    main()
