"""A second ROS 2 peer from outside the project: zenoh-ros2-sdk, a pure-Python rmw_zenoh client.

tests/ros2_peer.py was written here from rmw_zenoh's documentation; zenoh-ros2-sdk (PyPI) was
written by others, so what both agree on is not one reading of the design twice. Its
publishers put two Intel segments as ``nav_msgs/msg/OccupancyGrid`` on ``/r1/map`` and
``/r2/map`` with its own data key (the type hash computed by the SDK from ``.msg`` texts), its
33-byte attachment and its liveliness tokens; agents r1 and r2 follow those topics
(``--source ros2:``) and r1 publishes ``/map_merged`` and ``/tf_static``, which the SDK's
subscribers decode with its own typestore. The SDK's discovery (its ``ros2 topic info -v``)
reads the agents' liveliness tokens, and its transient-local subscriber finds r1's
publisher by its token and fetches the map from that publisher's cache.

The SDK's CDR is rosbags', as is tests/ros2_peer.py's: the CDR check that owes nothing to
rosbags is tests/test_protocol_ros2.py's rclpy golden files.

Offline: the SDK reads the ``.msg`` texts from a directory laid out from
tests/golden/ros2/msgdefs.json; its git cache (``ZENOH_ROS2_SDK_CACHE``, where it would
clone the ROS 2 interface repositories) names a directory that must never be created.
The SDK's session is an rmw_zenoh node's (its bundled config: a peer that connects to a
router), so the hub is a Zenoh router configured as rmw_zenohd is; the agents connect to it.
"""

from __future__ import annotations

import json
import threading
import time
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("zenoh_ros2_sdk")
import ros2_peer
import ros2_truth
import zenoh
import zenoh_ros2_sdk as sdk
from zenoh_ros2_sdk.qos import QosDurability, QosProfile

from agent.launcher import LocalFleet, free_port, wait_for
from agent.scenario import random_frames, segments
from agent.state import StateDir
from pgvd.io import read_map

pytestmark = [pytest.mark.fleet, pytest.mark.slow]

GRID = ros2_peer.GRID
TF = "tf2_msgs/msg/TFMessage"
ROBOTS = ("r1", "r2")
MSGDEFS = Path(__file__).resolve().parent / "golden" / "ros2" / "msgdefs.json"
#: slam_toolbox's /map and the agent's /map_merged: transient local, depth 1.
LATCHED = QosProfile(durability=QosDurability.TRANSIENT_LOCAL, history_depth=1)


def _lay_out_msgdefs(root: Path) -> Path:
    """The SDK's local message directory, ``<pkg>/msg/<Name>.msg``, from msgdefs.json."""
    for msgtype, text in json.loads(MSGDEFS.read_text()).items():
        path = root / f"{msgtype}.msg"
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)
    return root


def _rmw_zenohd(port: int) -> zenoh.Session:
    """A Zenoh router as rmw_zenohd sets one up: it does not route between two peers."""
    cfg = zenoh.Config()
    settings = {
        "mode": "router",
        "listen/endpoints": [f"tcp/127.0.0.1:{port}"],
        "scouting/multicast/enabled": False,
        "routing/router/peers_failover_brokering": False,
    }
    for path, value in settings.items():
        cfg.insert_json5(path, json.dumps(value))
    return zenoh.open(cfg)


def _grid_fields(ros_map: dict) -> dict:
    """A :func:`ros2_truth.ros_map` map as the fields of the SDK's own OccupancyGrid class."""
    cls = sdk.get_message_class
    stamp = cls("builtin_interfaces/msg/Time")(sec=1, nanosec=0)
    h, w = ros_map["shape"]
    x, y = ros_map["origin"]
    origin = cls("geometry_msgs/msg/Pose")(
        position=cls("geometry_msgs/msg/Point")(x=float(x), y=float(y), z=0.0),
        orientation=cls("geometry_msgs/msg/Quaternion")(x=0.0, y=0.0, z=0.0, w=1.0),
    )
    return {
        "header": cls("std_msgs/msg/Header")(stamp=stamp, frame_id="map"),
        "info": cls("nav_msgs/msg/MapMetaData")(
            map_load_time=stamp,
            resolution=ros2_truth.RESOLUTION,
            width=w,
            height=h,
            origin=origin,
        ),
        "data": ros_map["cells"],
    }


class _Inbox:
    """The messages an SDK subscriber hands its callback, from Zenoh's callback thread."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.got: list = []

    def __call__(self, msg) -> None:
        with self.lock:
            self.got.append(msg)

    def last(self):
        with self.lock:
            return self.got[-1] if self.got else None


def _publish_until_held(fleet: LocalFleet, pubs: dict, maps: dict) -> bool:
    """Publish each robot's map once a second until its agent holds it.

    The SDK's publisher is a plain Zenoh one with no cache (a late subscriber gets nothing),
    so, as a SLAM node republishes its map, it publishes again until the agents have theirs.
    """

    def held() -> bool:
        for robot, pub in pubs.items():
            pub.publish(**_grid_fields(maps[robot]))
        return all((fleet.agents[r].status() or {}).get("own_version") is not None for r in ROBOTS)

    return wait_for(held, 60, period=1.0)


def _topic_info(topic: str, publishers: int, subscriptions: int):
    """The SDK's ``ros2 topic info -v`` of ``topic``, asked again until it counts as expected.

    Each ask is one Zenoh liveliness query, which may miss a token (see
    :func:`_late_subscriber`); asking again is what a user of ``ros2 topic info`` does.
    """
    last = None

    def counted() -> bool:
        nonlocal last
        last = sdk.get_topic_info(topic, timeout=1.0, verbose=True)
        return last is not None and (last.publisher_count, last.subscriber_count) == (
            publishers,
            subscriptions,
        )

    wait_for(counted, 10, period=0.5)
    return last


def _late_subscriber(port: int, tries: int = 5) -> tuple[object, int]:
    """The map a transient-local SDK subscriber gets on creation, and the tries it took.

    Its constructor finds publishers with one liveliness query for their ``MP`` tokens and
    queries each one's cache (``<key>/@adv/pub/<zid>/**?_anyke``). Across peers on Zenoh
    1.10 that one query now and then misses a token that is there (measured on this fleet:
    the first subscriber got nothing in 3 of 5 runs, a second one never; 2 of 40 subscribers
    made one after another got nothing), so a subscriber that got nothing is closed and made
    again, as a node would be restarted.
    """
    for attempt in range(1, tries + 1):
        late = _Inbox()
        sub = sdk.ROS2Subscriber("/map_merged", GRID, late, router_port=port, qos=LATCHED)
        sub.close()
        if late.last() is not None:
            return late.last(), attempt
        time.sleep(0.5)
    return None, tries


@pytest.fixture(scope="module")
def sdk_fleet(tmp_path_factory: pytest.TempPathFactory) -> dict:
    work = tmp_path_factory.mktemp("sdkfleet")
    maps = {
        r: ros2_truth.ros_map(seg, fr)
        for r, seg, fr in zip(ROBOTS, segments(2), random_frames(2, seed=12), strict=True)
    }
    out: dict = {"maps": maps}
    port = free_port()
    git_cache = work / "sdk-git-cache"
    with pytest.MonkeyPatch.context() as env:
        env.setenv("ZENOH_ROS2_SDK_CACHE", str(git_cache))
        msg_dir = _lay_out_msgdefs(work / "msgs")
        assert sdk.get_registry(str(msg_dir)).messages_dir == msg_dir, "registry made earlier"
        router = _rmw_zenohd(port)
        merged, tf = _Inbox(), _Inbox()
        nodes: list = []
        try:
            pubs = {
                r: sdk.ROS2Publisher(
                    f"/{r}/map",
                    GRID,
                    node_name="slam_toolbox",
                    namespace=f"/{r}",
                    router_port=port,
                    qos=LATCHED,
                )
                for r in ROBOTS
            }
            nodes += pubs.values()
            out["keys"] = {r: p.keyexpr for r, p in pubs.items()}
            nodes.append(sdk.ROS2Subscriber("/map_merged", GRID, merged, router_port=port))
            nodes.append(sdk.ROS2Subscriber("/tf_static", TF, tf, router_port=port, qos=LATCHED))
            common = ["--connect", f"tcp/127.0.0.1:{port}", "--link-timeout", "3"]
            with LocalFleet("sdk", work, common) as fleet:
                fleet.add("r1", "ros2:/r1/map", ["--ros-publish", "/map_merged", "--ros-rate", "4"])
                fleet.add("r2", "ros2:/r2/map")
                out["held"] = _publish_until_held(fleet, pubs, maps)
                out["merged"] = wait_for(
                    lambda: ros2_truth.one_global_map(fleet.statuses(), ROBOTS), 120
                )
                out["statuses"] = fleet.statuses()
                time.sleep(1.0)  # the next tick at 4 Hz sends the placements of a new global map
                out["tf"], out["merged_map"] = tf.last(), merged.last()
                out["global"] = read_map(fleet.agents["r1"].out_dir / "global.yaml")
                out["stored"] = {
                    r: StateDir(a.state_dir).load_maps()[0][r].grid for r, a in fleet.agents.items()
                }
                # publishers and subscriptions of each topic, as ROS 2 nodes are now
                graph = {"/map_merged": (1, 1), "/tf_static": (1, 1), "/r1/map": (1, 1)}
                out["info"] = {t: _topic_info(t, *n) for t, n in graph.items()}
                out["late"], out["late_tries"] = _late_subscriber(port)
                out["drops"] = {r: a.status()["drops"] for r, a in fleet.agents.items()}
        finally:
            for node in nodes:
                node.close()
            sdk.ZenohSession.get_instance(router_port=port).close()
            router.close()
    out["git_cache_made"] = git_cache.exists()
    return out


def test_the_sdk_computes_the_same_data_key_and_never_reaches_for_the_network(
    sdk_fleet: dict,
) -> None:
    for robot, key in sdk_fleet["keys"].items():
        assert key == ros2_peer.key(f"/{robot}/map")  # type hash from the .msg texts: RIHS01
    assert not sdk_fleet["git_cache_made"]


def test_the_sdk_publishers_maps_reach_the_agents_whole(sdk_fleet: dict) -> None:
    assert sdk_fleet["held"], sdk_fleet["statuses"]
    assert sdk_fleet["drops"] == {"r1": {}, "r2": {}}  # its attachment and CDR were taken
    for robot, sent in sdk_fleet["maps"].items():
        stored = sdk_fleet["stored"][robot]
        assert stored.shape == sent["shape"]
        assert stored.resolution == pytest.approx(ros2_truth.RESOLUTION, rel=1e-7)  # float32
        np.testing.assert_allclose(stored.origin[:2], sent["origin"], atol=1e-9)
        cells = np.flipud(sent["cells"].reshape(sent["shape"]))  # back to Grid's row order
        p = stored.probability()
        np.testing.assert_array_equal(p > 0.5, cells == 100)
        np.testing.assert_array_equal(p < 0.5, cells == 0)


def test_the_merged_map_reaches_the_sdk_subscriber(sdk_fleet: dict) -> None:
    assert sdk_fleet["merged"], sdk_fleet["statuses"]
    msg, glob = sdk_fleet["merged_map"], sdk_fleet["global"]
    assert msg is not None
    assert msg.header.frame_id == "world"
    assert (msg.info.height, msg.info.width) == glob.shape
    assert msg.info.resolution == pytest.approx(glob.resolution, rel=1e-7)
    assert np.allclose(
        [msg.info.origin.position.x, msg.info.origin.position.y], glob.origin[:2], atol=1e-3
    )
    assert set(np.unique(msg.data)) == {-1, 0, 100}


def test_tf_decoded_by_the_sdk_places_each_map_within_2_cells_and_half_a_degree(
    sdk_fleet: dict,
) -> None:
    assert sdk_fleet["tf"] is not None
    anchor = sdk_fleet["statuses"]["r1"]["global"]["anchor"]
    ros2_truth.assert_tf_places_maps(sdk_fleet["tf"], sdk_fleet["maps"], anchor=anchor)


def test_a_late_transient_local_sdk_subscriber_gets_the_map_from_the_cache(
    sdk_fleet: dict,
) -> None:
    late = sdk_fleet["late"]
    assert late is not None
    assert (late.info.height, late.info.width) == sdk_fleet["global"].shape


def test_the_sdk_discovery_reads_the_agents_liveliness_tokens(sdk_fleet: dict) -> None:
    info = sdk_fleet["info"]
    merged = info["/map_merged"]
    assert merged.topic_types == [GRID]
    [agent] = merged.publishers
    # one node name per agent: r1's publishes the merged map
    assert (agent.node_name, agent.node_namespace) == ("pgvd_agent_r1", "/")
    assert agent.type_hash == ros2_peer.TS.hash_rihs01(GRID)
    qos = QosProfile.decode(agent.qos)
    assert (qos.durability, qos.history_depth) == (QosDurability.TRANSIENT_LOCAL, 1)
    assert merged.subscriber_count == 1  # the SDK's own volatile one
    assert info["/tf_static"].topic_types == [TF]
    [static] = info["/tf_static"].publishers
    assert static.node_name == "pgvd_agent_r1"
    # tf2's StaticTransformBroadcaster profile: a late listener gets the placements
    qos = QosProfile.decode(static.qos)
    assert (qos.durability, qos.history_depth) == (QosDurability.TRANSIENT_LOCAL, 1)
    follow = info["/r1/map"]  # the SDK's publisher and agent r1's subscription
    assert (follow.publisher_count, follow.subscriber_count) == (1, 1)
    assert [s.node_name for s in follow.subscribers] == ["pgvd_agent_r1"]
