"""ROS 2 robots in the fleet, end to end: real agent processes, a ROS 2 node on the wire.

The ROS side is tests/ros2_peer.py, written from rmw_zenoh's documentation (no project code
on the wire). It publishes two segments of the Intel log, each mapped in a random frame of
its own (agent/scenario.py), as latched ``nav_msgs/msg/OccupancyGrid`` on ``/r1/map`` and
``/r2/map`` before any agent runs; agents r1 and r2 follow those topics (``--source ros2:``)
and r1 publishes the merged map on ``/map_merged`` with ``/tf_static``, and the link between the
two maps as RViz markers on ``/map_merged_links``. Then every kind of bad ROS
message is sent to r2's topic. A second fleet replays a rosbag2 written from the Intel log
beside a CARMEN-source peer.
A DDS robot's map reaches an agent through zenoh-bridge-ros2dds's key form (``--ros-keys
bridge``).
"""

from __future__ import annotations

import json
import math
import subprocess
import sys
import threading
import time

import numpy as np
import pytest

pytest.importorskip("rosbags")
import bags
import ros2_peer
import ros2_truth

from agent.evaluate import link_error, true_matrix
from agent.launcher import ROOT, LocalFleet, free_port, wait_for
from agent.scenario import LOG, random_frames, segments
from agent.state import StateDir
from pgvd.carmen import read_carmen
from pgvd.integrate import se2, select_segment
from pgvd.io import read_map

pytestmark = [pytest.mark.fleet, pytest.mark.slow]

TF = "tf2_msgs/msg/TFMessage"
MARKERS = "visualization_msgs/msg/MarkerArray"
LINKS_ARGS = ("--ros-links", "/map_merged_links")
ROBOTS = ("r1", "r2")


def _status_cli(endpoint: str, fleet: str) -> dict:
    """``pgvd status --json`` run as a user would."""
    cmd = [sys.executable, "-m", "agent.cli", "status", "--fleet", fleet, "--connect", endpoint]
    res = subprocess.run([*cmd, "--json"], cwd=ROOT, capture_output=True, text=True, timeout=30)
    assert res.returncode == 0, res.stderr
    return json.loads(res.stdout)


class _Collector:
    """Samples of one key, decoded with rosbags, from Zenoh's callback thread."""

    def __init__(self, msgtype: str) -> None:
        self.msgtype = msgtype
        self.lock = threading.Lock()
        self.got: list = []

    def __call__(self, sample) -> None:
        msg = ros2_peer.TS.deserialize_cdr(sample.payload.to_bytes(), self.msgtype)
        att = sample.attachment
        with self.lock:
            self.got.append((msg, len(sample.payload.to_bytes()), att and att.to_bytes()))

    def last(self):
        with self.lock:
            return self.got[-1] if self.got else None


def _bad_inputs(robot_session, topic: str, good: dict, counted) -> dict[str, int]:
    """Every kind of bad OccupancyGrid on ``topic``; returns the drops each should count.

    The publishers stay up until ``counted()`` (the agent's drops) says every message came,
    as a SLAM node's would: an advanced subscriber still querying a new publisher's history
    when it leaves may lose its live samples (seen on a loaded machine: only the first
    publisher's message arrived).
    """
    cells = np.zeros(16, dtype=np.int8)
    wrong_hash = ros2_peer.LatchedPublisher(robot_session, topic, type_hash="RIHS01_" + "0" * 64)
    pub = ros2_peer.LatchedPublisher(robot_session, topic)
    time.sleep(1.0)  # let the agent's subscriber see the new publishers
    wrong_hash.put(ros2_peer.grid_cdr(cells, 4, 4, 0.1, (0.0, 0.0)))
    pub.put(good["cdr"][: len(good["cdr"]) // 3])  # truncated
    pub.put(b"\x00\x01\x00\x00" + bytes(range(256)) * 4)  # garbage after a CDR header
    pub.put(ros2_peer.grid_cdr(cells, 5, 4, 0.1, (0.0, 0.0)))  # width * height != len(data)
    pub.put(ros2_peer.grid_cdr(cells, 4, 4, 0.0, (0.0, 0.0)))  # resolution 0
    pub.put(ros2_peer.grid_cdr(cells, 4, 4, -0.1, (0.0, 0.0)))  # resolution < 0
    pub.put(ros2_peer.grid_cdr(cells, 4, 4, 0.1, (math.nan, 0.0)))  # NaN origin
    pub.put(ros2_peer.grid_cdr(np.full(16, 101, np.int8), 4, 4, 0.1, (0.0, 0.0)))  # > 100
    pub.put(ros2_peer.grid_cdr(np.full(16, -2, np.int8), 4, 4, 0.1, (0.0, 0.0)))  # < -1
    pub.put(ros2_peer.grid_cdr(cells, 4, 4, 0.1, (0.0, 0.0)), with_attachment=False)
    expected = {
        "ros2_type_hash": 1,
        "ros2_cdr": 2,
        "ros2_size": 1,
        "ros2_resolution": 2,
        "ros2_origin": 1,
        "ros2_cells": 2,
        "ros2_attachment": 1,
    }
    # the status is written a few seconds behind the drops on a loaded machine
    wait_for(lambda: counted() == expected, 30)
    wrong_hash.close()
    pub.close()
    return expected


def _r1_component(status: dict | None) -> dict:
    """The component of r1's status that holds r1 (its global map), {} if none yet."""
    comps = (status or {}).get("components", [])
    return next((c for c in comps if "r1" in c["members"]), {})


def _grow(fleet: LocalFleet, publisher, tf: _Collector, merged: _Collector, frame) -> dict:
    """r2's SLAM map grows, as slam_toolbox's does: same map frame, a new origin and size.

    Its segment of the log is extended backwards, so the grid grows on its low side and its
    origin moves. Returns the grown map's truth, the ``/tf_static`` and ``/map_merged`` that r1
    sends once its global map holds the grown version, and that map's component in r1's
    status.
    """
    start, end = segments(2)[1]
    grown = ros2_truth.ros_map((start - 0.15, end), frame)
    held = _r1_component(fleet.agents["r1"].status())["versions"]["r2"]
    publisher.put(grown["cdr"])

    def rebuilt() -> dict:
        status = fleet.agents["r1"].status() or {}
        comp = _r1_component(status) if status.get("settled") else {}
        return comp if comp.get("versions", {}).get("r2", held) > held else {}

    wait_for(rebuilt, 60)
    comp = rebuilt()

    def published() -> bool:
        """A 4 Hz tick has sent a map of the rebuilt component's shape and its TF."""
        m, t = merged.last(), tf.last()
        if not (comp and m and t and t[0].transforms):
            return False
        stamp = t[0].transforms[0].header.stamp
        same_tick = (stamp.sec, stamp.nanosec) == (m[0].header.stamp.sec, m[0].header.stamp.nanosec)
        return same_tick and (m[0].info.height, m[0].info.width) == tuple(comp["shape"])

    wait_for(published, 10)
    return {"map": grown, "component": comp, "tf": tf.last(), "merged_map": merged.last()}


@pytest.fixture(scope="module")
def ros_fleet(tmp_path_factory: pytest.TempPathFactory) -> dict:
    work = tmp_path_factory.mktemp("ros2fleet")
    frames = random_frames(2, seed=12)
    maps = {
        r: ros2_truth.ros_map(seg, fr)
        for r, seg, fr in zip(ROBOTS, segments(2), frames, strict=True)
    }
    out: dict = {"maps": maps}
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    robot = ros2_peer.session(listen=endpoint)
    publishers = [ros2_peer.LatchedPublisher(robot, f"/{r}/map") for r in ROBOTS]
    merged, tf, links = _Collector(ros2_peer.GRID), _Collector(TF), _Collector(MARKERS)
    subs = []
    try:
        # Published before any agent runs: only the publishers' caches hold the maps.
        for r, pub in zip(ROBOTS, publishers, strict=True):
            pub.put(maps[r]["cdr"])
        subs.append(ros2_peer.latched_subscriber(robot, ros2_peer.key("/tf_static", TF), tf))
        subs.append(ros2_peer.latched_subscriber(robot, ros2_peer.key("/map_merged"), merged))
        links_key = ros2_peer.key("/map_merged_links", MARKERS)
        subs.append(ros2_peer.latched_subscriber(robot, links_key, links))
        with LocalFleet("ros", work, ["--connect", endpoint, "--link-timeout", "3"]) as fleet:
            fleet.add(
                "r1",
                "ros2:/r1/map",
                ["--ros-publish", "/map_merged", "--ros-rate", "4", *LINKS_ARGS],
            )
            fleet.add("r2", "ros2:/r2/map")
            out["merged"] = wait_for(
                lambda: ros2_truth.one_global_map(fleet.statuses(), ROBOTS), 120
            )
            out["statuses"] = fleet.statuses()
            digest = out["statuses"]["r1"]["global"]["digest"]
            time.sleep(1.0)  # the next tick at 4 Hz sends the placements of a new global map
            out["tf"], out["merged_map"], out["links"] = tf.last(), merged.last(), links.last()
            out["global"] = read_map(fleet.agents["r1"].out_dir / "global.yaml")
            # A subscriber that comes after the publication still gets the map (transient local).
            late = _Collector(ros2_peer.GRID)
            subs.append(ros2_peer.latched_subscriber(robot, ros2_peer.key("/map_merged"), late))
            wait_for(late.last, 10)
            out["late"] = late.last()

            def drops() -> dict | None:
                return (fleet.agents["r2"].status() or {}).get("drops")

            out["expected_drops"] = _bad_inputs(robot, "/r2/map", maps["r2"], drops)
            out["status_cli"] = _status_cli(fleet.agents["r2"].endpoint, "ros")
            out["alive"] = [r for r, a in fleet.agents.items() if a.alive()]
            out["digest_after"] = fleet.agents["r1"].status()["global"]["digest"]
            out["digest_before"] = digest
            out["grown"] = _grow(fleet, publishers[1], tf, merged, frames[1])
    finally:
        for sub in subs:
            sub.undeclare()
        for pub in publishers:
            pub.close()
        robot.close()
    return out


def test_two_ros_robots_merge_and_the_merged_map_reaches_ros(ros_fleet: dict) -> None:
    assert ros_fleet["merged"], ros_fleet["statuses"]
    got = ros_fleet["merged_map"]
    assert got is not None
    msg, size, att = got
    glob = ros_fleet["global"]
    assert msg.header.frame_id == "world"
    assert (msg.info.height, msg.info.width) == glob.shape
    assert np.allclose(
        [msg.info.origin.position.x, msg.info.origin.position.y], glob.origin[:2], atol=1e-3
    )
    assert set(np.unique(msg.data)) == {-1, 0, 100}
    assert len(att) == 33  # rmw_zenoh's attachment: an unmodified ROS 2 subscriber takes it
    counts = ros_fleet["status_cli"]["r1"]["counts"]  # after the last publication
    assert counts["ros_maps_published"] >= 1 and counts["ros_map_bytes"] >= size


def test_the_link_between_the_maps_reaches_rviz_as_a_line_between_their_centres(
    ros_fleet: dict,
) -> None:
    """The MarkerArray r1 sends: the pair's line in the namespace of its state, in ``world``,
    ending at each map's centre as r1's own TF places it; the other states' lines deleted."""
    msg, _, att = ros_fleet["links"]
    state = ros_fleet["statuses"]["r1"]["link_states"]
    drawn = {s: pairs for s, pairs in state.items() if s != "rejected"}
    assert [p for pairs in drawn.values() for p in pairs] == ["r1/r2"], state
    by_ns = {m.ns: m for m in msg.markers}
    assert sorted(by_ns) == sorted(drawn)
    (ns,) = [s for s, pairs in drawn.items() if pairs]
    line = by_ns[ns]
    assert (line.type, line.action, line.header.frame_id, len(line.points)) == (5, 0, "world", 2)
    assert all(by_ns[s].action == 2 for s in drawn if s != ns)  # DELETE: no line of that state
    # r2's end: the centre of r2's known cells in its own frame, placed by r1's TF
    placed = {t.child_frame_id: t.transform for t in ros_fleet["tf"][0].transforms}["r2/map"]
    r2 = ros_fleet["maps"]["r2"]
    rows, cols = np.nonzero(r2["cells"].reshape(r2["shape"]) != -1)  # ROS rows: lowest first
    ox, oy = r2["origin"][:2]  # an unrotated OccupancyGrid origin
    res = ros2_truth.RESOLUTION
    own = (ox + (cols.mean() + 0.5) * res, oy + (rows.mean() + 0.5) * res)
    yaw = 2 * math.atan2(placed.rotation.z, placed.rotation.w)
    end = se2(placed.translation.x, placed.translation.y, yaw) @ np.append(own, 1.0)
    assert (line.points[1].x, line.points[1].y) == pytest.approx(tuple(end[:2]), abs=1e-3)
    assert len(att) == 33


def test_tf_places_each_robot_map_within_2_cells_and_half_a_degree(ros_fleet: dict) -> None:
    # the merged frame is the anchor's map frame: the robot whose first map came first
    anchor = ros_fleet["statuses"]["r1"]["global"]["anchor"]
    ros2_truth.assert_tf_places_maps(ros_fleet["tf"][0], ros_fleet["maps"], anchor=anchor)


def test_a_late_ros_subscriber_still_gets_the_merged_map(ros_fleet: dict) -> None:
    late = ros_fleet["late"]
    assert late is not None
    assert (late[0].info.height, late[0].info.width) == ros_fleet["global"].shape


def test_each_bad_ros_message_is_dropped_and_counted_by_reason(ros_fleet: dict) -> None:
    assert ros_fleet["alive"] == list(ROBOTS)
    drops = ros_fleet["status_cli"]["r2"]["drops"]
    assert drops == ros_fleet["expected_drops"]
    assert ros_fleet["digest_after"] == ros_fleet["digest_before"]  # nothing bad got in


@pytest.fixture(scope="module")
def bag_fleet(tmp_path_factory: pytest.TempPathFactory) -> dict:
    work = tmp_path_factory.mktemp("bagfleet")
    seg_bag, seg_log = segments(2)
    bag = work / "intel_bag"
    bags.write_scan_bag(bag, select_segment(read_carmen(LOG), seg_bag))
    fb, fc = random_frames(2, seed=7)
    with LocalFleet("bags", work, ["--speed", "200", "--link-timeout", "3"]) as fleet:
        fleet.add("rb", f"rosbag:{bag}:/scan", [f"--frame={fb[0]},{fb[1]},{fb[2]}"])
        fleet.add(
            "rc", f"carmen:{LOG}@{seg_log[0]}-{seg_log[1]}", [f"--frame={fc[0]},{fc[1]},{fc[2]}"]
        )

        def merged() -> bool:
            st = fleet.statuses()
            return all(
                s
                and s["source"]["done"]
                and s["global"]
                and s["global"]["members"] == ["rb", "rc"]
                and s["settled"]
                for s in st.values()
            )

        ok = wait_for(merged, 120)
        shapes = {
            r: StateDir(a.state_dir).load_maps()[0][r].grid.shape for r, a in fleet.agents.items()
        }
        return {"merged": ok, "statuses": fleet.statuses(), "shapes": shapes}


def test_a_replayed_rosbag_merges_with_a_carmen_peer(bag_fleet: dict) -> None:
    assert bag_fleet["merged"], bag_fleet["statuses"]
    st = bag_fleet["statuses"]
    assert st["rb"]["source"]["kind"] == "rosbag"
    w2p = {r: np.array(s["source"]["world_to_pixel"]) for r, s in st.items()}
    links = [ln for ln in st["rb"]["links"] if ln["current"] and ln["accepted"]]
    assert len(links) == 1
    ln = links[0]
    truth = true_matrix(w2p[ln["a"]], w2p[ln["b"]])
    deg, cells = link_error(ln["matrix"], truth, bag_fleet["shapes"][ln["b"]])
    assert deg <= 2.0 and cells <= 3.0, (deg, cells)


def test_a_dds_robot_behind_zenoh_bridge_ros2dds_is_followed(tmp_path) -> None:
    """An Intel map latched on ``/robot1/map`` as the bridge routes it, before the agent runs."""
    grid = read_map(ROOT / "examples" / "intel_a.yaml")
    prob = grid.probability()
    cells = np.full(prob.shape, -1, dtype=np.int8)
    cells[prob > 0.65], cells[prob < 0.196] = 100, 0
    h, w = prob.shape
    cdr = ros2_peer.grid_cdr(
        np.flipud(cells).ravel(), w, h, grid.resolution, grid.origin[:2], frame_id="robot1/map"
    )
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    dds_side = ros2_peer.session(listen=endpoint)
    route = ros2_peer.BridgeRoute(dds_side, "/robot1/map")
    try:
        route.put(cdr)  # only the route's cache holds it when the agent starts
        with LocalFleet("bridge", tmp_path, ["--connect", endpoint]) as fleet:
            agent = fleet.add("robot1", "ros2:/robot1/map", ["--ros-keys", "bridge"])
            assert wait_for(lambda: (agent.status() or {}).get("own_version") is not None, 60)
            status = agent.status()
            stored = StateDir(agent.state_dir).load_maps()[0]["robot1"].grid
    finally:
        route.close()
        dds_side.close()
    assert status["source"]["frame_id"] == "robot1/map" and status["drops"] == {}
    assert stored.shape == (h, w)
    assert stored.resolution == pytest.approx(grid.resolution, rel=1e-7)  # float32 on the wire
    np.testing.assert_allclose(stored.origin[:2], grid.origin[:2], atol=1e-9)
    p = stored.probability()
    np.testing.assert_array_equal(p > 0.5, cells == 100)
    np.testing.assert_array_equal(p < 0.5, cells == 0)


def test_a_growing_slam_map_is_followed_and_placed_again(ros_fleet: dict) -> None:
    """slam_toolbox's /map grows (m-explore-ros2 #10): the merged map and TF follow it."""
    grown = ros_fleet["grown"]
    comp = grown["component"]
    assert comp, "r1 never rebuilt its global map with r2's grown map"
    assert grown["map"]["shape"] != ros_fleet["maps"]["r2"]["shape"]
    assert comp["members"] == list(ROBOTS)
    msg = grown["merged_map"][0]
    assert (msg.info.height, msg.info.width) == tuple(comp["shape"])
    maps = {"r1": ros_fleet["maps"]["r1"], "r2": grown["map"]}
    ros2_truth.assert_tf_places_maps(grown["tf"][0], maps, anchor=comp["anchor"])
