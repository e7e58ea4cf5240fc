"""protocol.ros2: rmw_zenoh's keys, tokens and attachment as documented; OccupancyGrid CDR in
and out, and every malformed message refused with its reason.

The expected keys, tokens and attachment bytes below are written from rmw_zenoh's
documentation (ros2/rmw_zenoh ``docs/design.md``, ``attachment_helpers.cpp``) and from
Zenoh's own serializer, not from the module under test.
"""

from __future__ import annotations

import math
import struct
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from refusals import refused

from pgvd.grid import Grid
from pgvd.io import read_map
from protocol import ProtocolError
from protocol.ros2.attachment import Attachment, decode_attachment, encode_attachment
from protocol.ros2.keys import RosNode, data_key
from protocol.ros2.markers import LIFT, LineList, encode_line_lists
from protocol.ros2.occupancy import (
    Placement,
    decode_occupancy_grid,
    encode_occupancy_grid,
    encode_tf,
    transform_stamped,
)
from protocol.ros2.types import MARKER_ARRAY, OCCUPANCY_GRID, TF_MESSAGE, typestore

rosbags = pytest.importorskip("rosbags")
GOLDEN = Path(__file__).resolve().parent / "golden" / "ros2"  # made by real rclpy

# The key of /robot1/map in domain 0 on Jazzy, as `ros2 topic info -v` and rclpy give it.
JAZZY_MAP_KEY = (
    "0/robot1/map/nav_msgs::msg::dds_::OccupancyGrid_/"
    "RIHS01_8d348150c12913a31ee0ec170fbf25089e4745d17035792a1ba94d6f0bc0cfc7"
)


def test_data_keys_have_rmw_zenohs_documented_form() -> None:
    assert data_key("/robot1/map", OCCUPANCY_GRID) == JAZZY_MAP_KEY
    assert data_key("/robot1/map", OCCUPANCY_GRID, distro="kilted") == JAZZY_MAP_KEY
    assert data_key("/map", OCCUPANCY_GRID, domain=7, distro="humble") == (
        "7/map/nav_msgs::msg::dds_::OccupancyGrid_/TypeHashNotSupported"
    )
    assert data_key("/robot1/map", OCCUPANCY_GRID, form="bridge") == "robot1/map"


@pytest.mark.parametrize(
    ("topic", "kwargs", "match"),
    [
        ("robot1/map", {}, "absolute"),
        ("/robot1//map", {}, "absolute"),
        ("/robot1/map*", {}, "absolute"),
        ("/map", {"distro": "rolling"}, "unknown ROS 2 distro"),
        ("/map", {"domain": 233}, "domain id"),
        ("/map", {"form": "dds"}, "unknown ROS key form"),
    ],
)
def test_bad_key_arguments_are_refused_precisely(topic: str, kwargs: dict, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        data_key(topic, OCCUPANCY_GRID, **kwargs)


def test_liveliness_tokens_follow_the_documented_layout() -> None:
    node = RosNode(zid="1f2e3d", name="pgvd_agent", namespace="/robot1", node_id=0, domain=0)
    assert node.token() == "@ros2_lv/0/1f2e3d/0/0/NN/%/%robot1/pgvd_agent"
    token = node.entity_token("MS", 4, "/robot1/map", OCCUPANCY_GRID)
    fields = token.split("/")
    assert fields[:10] == [
        "@ros2_lv",
        "0",
        "1f2e3d",
        "0",
        "4",
        "MS",
        "%",
        "%robot1",
        "pgvd_agent",
        "%robot1%map",
    ]
    assert fields[10:12] == JAZZY_MAP_KEY.split("/")[3:5]
    # Transient local, keep-last 1; reliability and the rest at rmw_zenoh's defaults.
    assert fields[12] == ":1:,1:,:,:,,"
    assert RosNode(zid="a", name="n").token() == "@ros2_lv/0/a/0/0/NN/%/%/n"


int64s = st.integers(-(2**63), 2**63 - 1)


@given(int64s, int64s, st.binary(min_size=16, max_size=16))
def test_attachment_matches_zenohs_serializer(seq: int, stamp: int, gid: bytes) -> None:
    from zenoh.ext import Int64, z_serialize

    raw = encode_attachment(Attachment(seq, stamp, gid))
    assert raw == z_serialize((Int64(seq), Int64(stamp), gid)).to_bytes()
    assert raw == struct.pack("<qqB", seq, stamp, 16) + gid
    assert decode_attachment(raw) == Attachment(seq, stamp, gid)


@given(st.binary(max_size=64))
def test_attachment_decoder_refuses_or_parses(data: bytes) -> None:
    try:
        att = decode_attachment(data)
    except ProtocolError as exc:
        assert exc.reason in ("framing", "value")
    else:
        assert encode_attachment(att) == data


def test_real_map_round_trips_through_occupancy_grid_cdr(shared) -> None:
    grid = read_map(shared / "maps" / "intel" / "intel.yaml")
    cdr = encode_occupancy_grid(grid, "world", 1_700_000_000_123_456_789)
    assert cdr[:4] == b"\x00\x01\x00\x00"
    ros = decode_occupancy_grid(cdr)
    assert ros.frame_id == "world" and ros.stamp_ns == 1_700_000_000_123_456_789
    assert ros.grid.shape == grid.shape and ros.grid.resolution == pytest.approx(grid.resolution)
    assert ros.grid.origin == pytest.approx(grid.origin)
    # Classes survive: occupied, free and unknown cells stay what they were.
    assert np.array_equal(np.sign(ros.grid.logodds), np.sign(grid.logodds))
    # The rows are flipped: data row 0 is the map's lowest row (REP 103).
    msg = typestore().deserialize_cdr(cdr, OCCUPANCY_GRID)
    bottom = msg.data[: grid.shape[1]]
    assert np.array_equal(bottom == -1, grid.logodds[-1] == 0)


def _message(
    width: int = 3,
    height: int = 2,
    resolution: float = 0.05,
    data=None,
    origin=(1.0, 2.0),
    quaternion=(0.0, 0.0, 0.0, 1.0),
):
    ts = typestore()
    t = ts.types
    data = np.array([-1, 0, 100, 50, 1, 2], dtype=np.int8) if data is None else data
    return t[OCCUPANCY_GRID](
        header=t["std_msgs/msg/Header"](
            stamp=t["builtin_interfaces/msg/Time"](sec=3, nanosec=4), frame_id="map"
        ),
        info=t["nav_msgs/msg/MapMetaData"](
            map_load_time=t["builtin_interfaces/msg/Time"](sec=0, nanosec=0),
            resolution=resolution,
            width=width,
            height=height,
            origin=t["geometry_msgs/msg/Pose"](
                position=t["geometry_msgs/msg/Point"](x=origin[0], y=origin[1], z=0.0),
                orientation=t["geometry_msgs/msg/Quaternion"](
                    x=quaternion[0], y=quaternion[1], z=quaternion[2], w=quaternion[3]
                ),
            ),
        ),
        data=np.asarray(data, dtype=np.int8),
    )


def _cdr(**kwargs) -> bytes:
    return bytes(typestore().serialize_cdr(_message(**kwargs), OCCUPANCY_GRID))


def test_cell_values_mean_what_ros_says() -> None:
    grid = decode_occupancy_grid(_cdr()).grid
    top, bottom = grid.logodds  # data row 0 is the bottom row
    assert bottom[0] == 0.0  # -1: unknown
    assert bottom[1] < -2.0 and bottom[2] > 2.0  # free, occupied
    assert top[0] == 0.0  # 50 %: no evidence either way
    assert 0 > top[1] > bottom[1]  # 1 % and 2 %: free, less sure than 0 %


@pytest.mark.parametrize(
    ("kwargs", "reason", "match"),
    [
        ({"width": 4}, "value", "carries 6 cells"),
        ({"resolution": 0.0}, "value", "resolution"),
        ({"resolution": -0.05}, "value", "resolution"),
        ({"resolution": math.nan}, "value", "resolution"),
        ({"origin": (math.nan, 0.0)}, "value", "origin is not finite"),
        ({"quaternion": (0.0, 0.0, 0.0, 0.0)}, "value", "rotation about z"),
        ({"quaternion": (0.7071, 0.0, 0.0, 0.7071)}, "value", "rotation about z"),
        ({"data": [-1, 0, 100, 101, 1, 2]}, "value", "-1..100"),
        ({"data": [-1, -2, 100, 50, 1, 2]}, "value", "-1..100"),
        ({"width": 0, "height": 0, "data": []}, "value", "carries 0 cells"),
    ],
)
def test_bad_grids_are_refused_with_their_reason(kwargs: dict, reason: str, match: str) -> None:
    with refused(reason, match):
        decode_occupancy_grid(_cdr(**kwargs))


def test_truncated_and_foreign_cdr_is_refused() -> None:
    cdr = _cdr()
    with refused("framing", "does not parse"):
        decode_occupancy_grid(cdr[:30])
    with refused("framing", "encapsulation"):
        decode_occupancy_grid(b"\x07" + cdr[1:])
    tf = encode_tf([Placement("world", "r1/map", 1.0, 2.0, 0.5)], 0)
    with pytest.raises(ProtocolError):
        decode_occupancy_grid(tf)


@settings(max_examples=300)
@given(st.binary(max_size=200))
def test_garbage_is_refused_never_crashes(data: bytes) -> None:
    try:
        ros = decode_occupancy_grid(b"\x00\x01\x00\x00" + data)
    except ProtocolError as exc:
        assert exc.reason in ("framing", "value", "limit")
    else:
        assert ros.grid.logodds.size > 0


@settings(max_examples=60)
@given(st.data())
def test_flipped_bytes_of_a_real_message_are_refused_or_decoded(data) -> None:
    cdr = bytearray(_cdr())
    for _ in range(data.draw(st.integers(1, 4))):
        cdr[data.draw(st.integers(4, len(cdr) - 1))] = data.draw(st.integers(0, 255))
    try:
        decode_occupancy_grid(bytes(cdr))
    except ProtocolError as exc:
        assert exc.reason in ("framing", "value", "limit")


@settings(max_examples=40)
@given(
    st.integers(1, 12),
    st.integers(1, 12),
    st.floats(0.01, 1.0),
    st.floats(-1e3, 1e3),
    st.floats(-1e3, 1e3),
    st.floats(-3.1, 3.1),
    st.data(),
)
def test_grid_round_trip_keeps_classes_and_geometry(h, w, res, ox, oy, yaw, data) -> None:
    # Free, unknown, weak evidence either way (published as unknown: trinary), occupied.
    values = data.draw(
        st.lists(st.sampled_from([-3.0, 0.0, -0.3, 0.3, 2.5]), min_size=h * w, max_size=h * w)
    )
    grid = Grid(np.array(values, dtype=np.float32).reshape(h, w), res, (ox, oy, yaw))
    ros = decode_occupancy_grid(encode_occupancy_grid(grid, "world", 0))
    classes = np.sign(grid.logodds) * (np.abs(grid.logodds) > 1.0)
    assert np.array_equal(np.sign(ros.grid.logodds), classes)
    assert ros.grid.resolution == pytest.approx(res, rel=1e-6)  # float32 on the wire
    assert ros.grid.origin[:2] == pytest.approx((ox, oy))
    assert math.remainder(ros.grid.origin[2] - yaw, 2 * math.pi) == pytest.approx(0.0, abs=1e-9)


def test_tf_message_places_each_robot_map() -> None:
    cdr = encode_tf(
        [Placement("world", "r1/map", 0.0, 0.0, 0.0), Placement("world", "r2/map", 3.0, -1.5, 0.5)],
        2_000_000_001,
    )
    msg = typestore().deserialize_cdr(cdr, TF_MESSAGE)
    second = msg.transforms[1]
    assert (second.header.frame_id, second.child_frame_id) == ("world", "r2/map")
    assert (second.header.stamp.sec, second.header.stamp.nanosec) == (2, 1)
    assert (second.transform.translation.x, second.transform.translation.y) == (3.0, -1.5)
    q = second.transform.rotation
    assert 2 * math.atan2(q.z, q.w) == pytest.approx(0.5)


def test_occupancy_grid_bytes_equal_rclpys() -> None:
    golden = (GOLDEN / "occupancy_grid.cdr").read_bytes()
    ros = decode_occupancy_grid(golden)
    assert ros.grid.shape == (5, 7) and ros.frame_id == "world"
    assert ros.grid.origin == pytest.approx((1.5, -2.25, 0.3))
    assert ros.grid.resolution == pytest.approx(0.05)
    # The golden map's lowest row is a wall; its top row is unknown (Grid rows run top-down).
    assert np.all(ros.grid.logodds[-1] > 0) and np.all(ros.grid.logodds[0] == 0)
    assert encode_occupancy_grid(ros.grid, "world", ros.stamp_ns) == golden


def test_transform_bytes_equal_rclpys() -> None:
    golden = (GOLDEN / "transform_stamped.cdr").read_bytes()
    stamp = 1_700_000_000 * 10**9 + 123_456_789
    msg = transform_stamped(Placement("world", "robot2/map", 3.0, -1.5, 0.5), stamp)
    ours = bytes(typestore().serialize_cdr(msg, "geometry_msgs/msg/TransformStamped"))
    # CDR leaves alignment padding undefined, and rclpy's Fast-CDR does not zero it: after
    # child_frame_id ("robot2/map" ends at byte 39) the float64 translation is 8-aligned from
    # byte 4 (after the encapsulation header), so bytes 39..43 are padding. All else is equal.
    padding = slice(39, 44)
    assert len(ours) == len(golden)
    assert ours[: padding.start] == golden[: padding.start]
    assert ours[padding.stop :] == golden[padding.stop :]


# MarkerArray's key on Jazzy: the same RIHS01 hash is listed by two ROS 2 client libraries
# the project did not write (a C type table and an Elixir message module).
JAZZY_LINKS_KEY = (
    "0/map_merged_links/visualization_msgs::msg::dds_::MarkerArray_/"
    "RIHS01_86cb8800b6fb05b5eff1abd7a56f62a5641d3ae9a1c29e78e67e704f1d067dcf"
)


def test_marker_array_keys_carry_its_type_hash_per_distro() -> None:
    assert data_key("/map_merged_links", MARKER_ARRAY) == JAZZY_LINKS_KEY
    assert data_key("/map_merged_links", MARKER_ARRAY, distro="kilted") == JAZZY_LINKS_KEY
    assert data_key("/map_merged_links", MARKER_ARRAY, distro="humble").endswith(
        "/visualization_msgs::msg::dds_::MarkerArray_/TypeHashNotSupported"
    )


@pytest.mark.parametrize("store", ["ROS2_HUMBLE", "ROS2_JAZZY", "ROS2_KILTED"])
def test_line_lists_decode_as_each_distros_marker_array(store: str) -> None:
    """rosbags' own store of each distro reads the bytes: one LINE_LIST per list, added with
    its segments' points or deleted when it has none."""
    from rosbags.typesys import Stores, get_typestore

    lists = [
        LineList("confirmed", (0.1, 0.4, 0.9, 1.0), (((0.0, 0.0), (3.0, -2.0)), ((1, 1), (2, 5)))),
        LineList("candidate", (0.9, 0.5, 0.0, 1.0)),
    ]
    cdr = encode_line_lists(lists, "world", 7 * 10**9 + 5, width=0.3)
    assert cdr[:4] == b"\x00\x01\x00\x00"
    msg = get_typestore(getattr(Stores, store)).deserialize_cdr(cdr, MARKER_ARRAY)
    first, second = msg.markers
    assert (first.ns, first.id, first.type, first.action) == ("confirmed", 0, 5, 0)
    assert (second.ns, second.action, len(second.points)) == ("candidate", 2, 0)
    assert [(p.x, p.y) for p in first.points] == [(0.0, 0.0), (3.0, -2.0), (1.0, 1.0), (2.0, 5.0)]
    assert {p.z for p in first.points} == {LIFT}
    assert first.header.frame_id == "world"
    assert (first.header.stamp.sec, first.header.stamp.nanosec) == (7, 5)
    assert first.scale.x == 0.3 and first.pose.orientation.w == 1.0
    assert (first.color.r, first.color.a) == (pytest.approx(0.1), 1.0)
    assert (first.lifetime.sec, first.lifetime.nanosec) == (0, 0)
    empty = get_typestore(getattr(Stores, store)).deserialize_cdr(
        encode_line_lists([], "world", 0), MARKER_ARRAY
    )
    assert empty.markers == []


@pytest.mark.parametrize(
    ("make", "match"),
    [
        (lambda: LineList("", (0, 0, 0, 1)), "namespace must not be empty"),
        (lambda: LineList("a", (0, 0, 2, 1)), "rgba"),
        (lambda: LineList("a", (0, 0, 0)), "rgba"),
        (lambda: LineList("a", (0, 0, 0, 1), (((0, math.nan), (1, 1)),)), "finite"),
        (lambda: LineList("a", (0, 0, 0, 1), (((0, 0),),)), "two finite"),
        (lambda: encode_line_lists([LineList("a", (0, 0, 0, 1))] * 2, "w", 0), "differ"),
        (lambda: encode_line_lists([], "w", 0, width=0.0), "width"),
    ],
)
def test_bad_line_lists_are_refused_precisely(make, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        make()
