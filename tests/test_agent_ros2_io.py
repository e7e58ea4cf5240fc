"""agent.ros2_io against a ROS 2 peer written from rmw_zenoh's documentation (tests/ros2_peer.py),
over real Zenoh sessions on 127.0.0.1: latched maps reach a late subscriber, bad samples are
counted by reason, and the merged map and TF published by the agent decode with rosbags."""

from __future__ import annotations

import re
import socket
import string
import struct
import time
from collections.abc import Callable, Iterator

import numpy as np
import pytest
from hypothesis import assume, given
from hypothesis import strategies as st

pytest.importorskip("rosbags")
import ros2_peer

from agent.keys import is_name
from agent.ros2_io import (
    RosMapPublisher,
    RosMapSubscription,
    RosOptions,
    agent_node_name,
    declare_node,
)
from pgvd.io import read_map
from protocol.ros2.occupancy import Placement

TF = "tf2_msgs/msg/TFMessage"


def _port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def _wait(what: Callable[[], object], timeout: float = 10.0) -> object:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        value = what()
        if value:
            return value
        time.sleep(0.05)
    raise AssertionError("timed out")


@pytest.fixture
def sessions() -> Iterator[tuple]:
    endpoint = f"tcp/127.0.0.1:{_port()}"
    robot = ros2_peer.session(listen=endpoint)
    agent = ros2_peer.session(connect=endpoint)
    _wait(lambda: list(agent.info.peers_zid()))
    yield robot, agent
    agent.close()
    robot.close()


def _cells() -> tuple[np.ndarray, int, int]:
    """A small real map: a crop of the intel lab, in ROS row order."""
    grid = read_map("examples/intel_a.yaml")
    prob = grid.probability()[200:260, 300:380]
    cells = np.full(prob.shape, -1, dtype=np.int8)
    cells[prob > 0.65], cells[prob < 0.196] = 100, 0
    return np.flipud(cells).ravel(), prob.shape[1], prob.shape[0]


def test_latched_map_reaches_a_late_subscriber_and_updates_follow(sessions) -> None:
    robot, agent = sessions
    cells, w, h = _cells()
    pub = ros2_peer.LatchedPublisher(robot, "/robot1/map")
    pub.put(ros2_peer.grid_cdr(cells, w, h, 0.05, (1.0, -2.0)))
    time.sleep(0.3)  # published before anyone subscribed: only the cache holds it
    drops: list[tuple[str, str]] = []
    sub = RosMapSubscription(agent, "/robot1/map", RosOptions(), lambda r, d: drops.append((r, d)))
    try:
        first = _wait(sub.take)
        assert first.grid.shape == (h, w) and first.grid.origin[:2] == (1.0, -2.0)
        assert np.array_equal(np.flipud(first.grid.logodds).ravel() == 0, cells == -1)
        cells2 = cells.copy()
        cells2[:w] = 100
        pub.put(ros2_peer.grid_cdr(cells2, w, h, 0.05, (1.0, -2.0)))
        second = _wait(sub.take)
        assert np.all(second.grid.logodds[-1] > 0)
        # The subscription's token is what slam_toolbox counts as a subscriber.
        tokens = [str(r.ok.key_expr) for r in robot.liveliness().get("@ros2_lv/**")]
        assert any("/MS/" in t and t.split("/")[9] == "%robot1%map" for t in tokens), tokens
        assert drops == []
    finally:
        sub.close()
        pub.close()


def test_a_humble_robots_map_is_followed_with_ros_distro_humble(sessions) -> None:
    """Humble's rmw_zenoh writes ``TypeHashNotSupported`` where the hash goes; a Jazzy key on
    the same topic is then another type's, dropped and counted."""
    robot, agent = sessions
    cells, w, h = _cells()
    humble = ros2_peer.LatchedPublisher(robot, "/robot1/map", type_hash="TypeHashNotSupported")
    humble.put(ros2_peer.grid_cdr(cells, w, h, 0.05, (0.0, 0.0)))
    drops: list[tuple[str, str]] = []
    sub = RosMapSubscription(
        agent, "/robot1/map", RosOptions(distro="humble"), lambda r, d: drops.append((r, d))
    )
    jazzy = ros2_peer.LatchedPublisher(robot, "/robot1/map")
    try:
        assert _wait(sub.take).grid.shape == (h, w)
        time.sleep(0.3)  # let the subscription see the Jazzy publisher
        jazzy.put(ros2_peer.grid_cdr(cells, w, h, 0.05, (0.0, 0.0)))
        _wait(lambda: drops)
        assert [r for r, _ in drops] == ["type_hash"] and sub.take() is None
    finally:
        sub.close()
        jazzy.close()
        humble.close()


def test_only_the_agents_ros_domain_is_followed(sessions) -> None:
    """ROS_DOMAIN_ID is the first chunk of every rmw_zenoh key: a robot on domain 0 is another
    network for an agent started with ``--ros-domain 7``."""
    robot, agent = sessions
    cells, w, h = _cells()
    other = ros2_peer.LatchedPublisher(robot, "/robot1/map")
    other.put(ros2_peer.grid_cdr(cells, w, h, 0.05, (0.0, 0.0)))
    drops: list[tuple[str, str]] = []
    sub = RosMapSubscription(
        agent, "/robot1/map", RosOptions(domain=7), lambda r, d: drops.append((r, d))
    )
    ours = ros2_peer.LatchedPublisher(robot, "/robot1/map", domain=7)
    try:
        time.sleep(0.5)  # domain 0's cached map would have arrived by now
        assert sub.take() is None
        ours.put(ros2_peer.grid_cdr(cells, w, h, 0.1, (1.0, 2.0)))
        got = _wait(sub.take)
        # MapMetaData.resolution is a float32
        assert got.grid.shape == (h, w) and got.grid.resolution == pytest.approx(0.1) and not drops
    finally:
        sub.close()
        ours.close()
        other.close()


@pytest.mark.parametrize(
    ("kind", "reason"),
    [
        ("hash", "type_hash"),
        ("attachment", "attachment"),
        ("truncated", "cdr"),
        ("size", "size"),
        ("cells", "cells"),
    ],
)
def test_bad_samples_are_dropped_and_counted(sessions, kind: str, reason: str) -> None:
    robot, agent = sessions
    cells, w, h = _cells()
    drops: list[tuple[str, str]] = []
    sub = RosMapSubscription(agent, "/robot1/map", RosOptions(), lambda r, d: drops.append((r, d)))
    pub = ros2_peer.LatchedPublisher(
        robot, "/robot1/map", type_hash="RIHS01_" + "0" * 64 if kind == "hash" else None
    )
    try:
        time.sleep(0.3)
        cdr = ros2_peer.grid_cdr(cells, w, h, 0.05, (0.0, 0.0))
        if kind == "truncated":
            cdr = cdr[: len(cdr) // 2]
        elif kind == "size":
            cdr = ros2_peer.grid_cdr(cells, w + 1, h, 0.05, (0.0, 0.0))
        elif kind == "cells":
            bad = cells.copy()
            bad[0] = 101
            cdr = ros2_peer.grid_cdr(bad, w, h, 0.05, (0.0, 0.0))
        pub.put(cdr, with_attachment=kind != "attachment")
        _wait(lambda: drops)
        assert [r for r, _ in drops] == [reason], drops
        assert sub.take() is None
    finally:
        sub.close()
        pub.close()


def test_merged_map_and_tf_reach_a_ros_subscriber_late_too(sessions) -> None:
    robot, agent = sessions
    grid = read_map("examples/intel_a.yaml")
    out = RosMapPublisher(agent, "/map_merged", "world", RosOptions())
    got: list[tuple[str, bytes, bytes | None]] = []

    def on_sample(sample) -> None:
        att = sample.attachment.to_bytes() if sample.attachment is not None else None
        got.append((str(sample.key_expr), sample.payload.to_bytes(), att))

    try:
        time.sleep(0.3)
        size = out.publish(grid, [Placement("world", "r2/map", 3.0, -1.5, 0.5)], 7 * 10**9)
        # Subscribers that arrive after the publication still get the map and the static
        # transforms, as ROS 2's transient-local subscribers (and tf2's /tf_static listener)
        # do: an advanced subscriber's history query.
        late = [
            ros2_peer.latched_subscriber(robot, ros2_peer.key(topic, msgtype), on_sample)
            for topic, msgtype in (("/map_merged", ros2_peer.GRID), ("/tf_static", TF))
        ]
        _wait(lambda: len(got) >= 2)
        for sub in late:
            sub.undeclare()
    finally:
        out.close()
    by_key = {k: (p, a) for k, p, a in got}
    payload, att = by_key[ros2_peer.key("/map_merged")]
    assert len(payload) == size
    msg = ros2_peer.TS.deserialize_cdr(payload, ros2_peer.GRID)
    assert (msg.info.width, msg.info.height) == (grid.shape[1], grid.shape[0])
    assert msg.header.frame_id == "world"
    seq, stamp, gid_len = struct.unpack_from("<qqB", att)
    assert (seq, stamp, gid_len, len(att)) == (1, 7 * 10**9, 16, 33)
    payload, att = by_key[ros2_peer.key("/tf_static", TF)]
    tf = ros2_peer.TS.deserialize_cdr(payload, TF)
    assert tf.transforms[0].child_frame_id == "r2/map" and len(att) == 33
    # each publisher has a GID of its own, as in rmw_zenoh
    assert by_key[ros2_peer.key("/map_merged")][1][17:] != att[17:]


def test_a_restarted_publisher_numbers_from_1_under_a_new_gid(sessions) -> None:
    # Under the old GID, numbering from 1 again would read to rmw_zenoh's lost-message
    # tracking as every message since the last one lost.
    robot, agent = sessions
    got: list[bytes] = []
    sub = robot.declare_subscriber(
        ros2_peer.key("/tf_static", TF),
        lambda sample: got.append(sample.attachment.to_bytes()),
    )
    try:
        for run in (1, 2):
            out = RosMapPublisher(agent, "/map_merged", "world", RosOptions())
            try:
                time.sleep(0.3)
                out.publish_tf([Placement("world", "r2/map", 0.0, 0.0, 0.0)], 10**9)
                _wait(lambda run=run: len(got) == run)
            finally:
                out.close()
    finally:
        sub.undeclare()
    assert [struct.unpack_from("<qqB", att)[0] for att in got] == [1, 1]
    assert got[0][17:] != got[1][17:]


def test_the_node_token_goes_after_its_publishers_tokens(sessions) -> None:
    # rmw_zenoh's graph cache warns on every ROS node of a node removed before its entities
    robot, agent = sessions
    events: list[tuple[str, str]] = []
    watch = robot.liveliness().declare_subscriber(
        "@ros2_lv/**", lambda s: events.append((str(s.kind), str(s.key_expr).split("/")[5]))
    )
    try:
        node = declare_node(agent, RosOptions())
        out = RosMapPublisher(agent, "/map_merged", "world", RosOptions())
        _wait(lambda: len(events) >= 3)
        out.close()
        node.undeclare()
        _wait(lambda: len(events) >= 6)
    finally:
        watch.undeclare()
    gone = [entity for kind, entity in events if "DELETE" in kind]
    assert gone == ["MP", "MP", "NN"], events
    assert declare_node(agent, RosOptions(form="bridge")) is None


@given(st.text(alphabet=string.ascii_letters + string.digits + "_-", min_size=1, max_size=64))
def test_each_robots_agent_is_a_ros_node_of_its_own_name(robot: str) -> None:
    assume(is_name(robot))
    name = agent_node_name(robot)
    # a ROS 2 node name: letters, digits and underscores, not starting with a digit
    assert re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*", name), name
    assert agent_node_name(robot + "x") != name
