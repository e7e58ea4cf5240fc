"""The links as RViz markers: lines between the real maps' placed centres, one namespace per
state, and an agent's outputs sending them over a real Zenoh session, decoded by rosbags."""

from __future__ import annotations

import threading

import numpy as np
import pytest
from components import component

from agent import trust
from agent.book import FleetBook
from agent.counters import Counters
from agent.launcher import wait_for
from agent.linkmarks import COLOURS, known_centre, link_line_lists, map_centres
from agent.links import LinkRecord
from agent.outputs import OutputOptions, Outputs
from pgvd.grid import Grid, pixel_to_world, relative_matrix
from pgvd.integrate import se2
from pgvd.io import read_map

MARKERS = "visualization_msgs/msg/MarkerArray"
DRAWN = [trust.ACCEPTED, trust.CONFIRMED, trust.CANDIDATE, trust.WITHDRAWN]


def _maps() -> tuple[Grid, Grid, np.ndarray]:
    """Intel map A, and B (A's cells in a frame of its own) placed at (3, -2, 0.7) in A's."""
    a = read_map("examples/intel_a.yaml")
    b = Grid(a.logodds[::-1, :].copy(), a.resolution, (0.0, 0.0, 0.0))
    placed = Grid(b.logodds, b.resolution, (3.0, -2.0, 0.7))
    return a, b, relative_matrix(a, placed)


def _link(a: str, b: str, state: str, versions: tuple[int, int] = (1, 1)) -> LinkRecord:
    return LinkRecord(
        a, versions[0], b, versions[1], state in trust.IN_MAP, np.eye(3), np.eye(3), 0.5, a,
        state=state,
    )  # fmt: skip


def test_centres_are_the_known_cells_mean_placed_in_the_merged_frame() -> None:
    a, b, b_to_a = _maps()
    comp = component({"a": (1, a), "b": (1, b)}, {"a": np.eye(3), "b": b_to_a})
    centres = map_centres(comp, {"a": (1, a), "b": (1, b)})
    # B's centre in its own frame, moved by B's true pose in A's frame
    own = pixel_to_world(b, known_centre(b))[0]
    truth = se2(3.0, -2.0, 0.7) @ np.append(own, 1.0)
    assert centres["b"] == pytest.approx(tuple(truth[:2]), abs=1e-6)
    assert centres["a"] == pytest.approx(tuple(pixel_to_world(a, known_centre(a))[0]), abs=1e-9)
    # a map that moved on since the component was built is not placed; an empty map has none
    assert list(map_centres(comp, {"a": (1, a), "b": (2, b)})) == ["a"]
    assert map_centres(comp, {"a": (2, a), "b": (1, b)}) == {}
    blank = Grid(np.zeros_like(b.logodds), b.resolution, b.origin)
    assert known_centre(blank) is None
    assert list(map_centres(comp, {"a": (1, a), "b": (1, blank)})) == ["a"]


def test_one_line_list_per_drawn_state_and_rejected_or_unplaced_links_left_out() -> None:
    centres = {"a": (0.0, 0.0), "b": (4.0, 1.0), "c": (-2.0, 3.0), "d": (1.0, 1.0)}
    second = 1 << 31  # the first version of a map's second epoch
    versions = {"a": 1, "b": second, "c": 1, "d": 1, "e": 1}
    records = [
        _link("a", "b", trust.CONFIRMED, (1, second)),
        _link("a", "c", trust.CANDIDATE),
        _link("b", "c", trust.WITHDRAWN, (second, 1)),
        _link("a", "d", trust.REJECTED),
        _link("c", "d", trust.ACCEPTED),
        _link("d", "e", trust.ACCEPTED),  # e is not placed
        _link("b", "d", trust.ACCEPTED, (1, 1)),  # of the first epoch of b's map
    ]
    lists = {ln.ns: ln for ln in link_line_lists(records, versions, centres)}
    assert list(lists) == DRAWN
    assert lists[trust.CONFIRMED].segments == ((centres["a"], centres["b"]),)
    assert lists[trust.CANDIDATE].segments == ((centres["a"], centres["c"]),)
    assert lists[trust.WITHDRAWN].segments == ((centres["b"], centres["c"]),)
    assert lists[trust.ACCEPTED].segments == ((centres["c"], centres["d"]),)
    colours = {ln.rgba for ln in lists.values()}
    assert len(colours) == 4 and lists[trust.ACCEPTED].rgba == (0.0, 150 / 255, 0.0, 1.0)
    # no links, or none placed: every state's list is empty, so its lines go
    for empty in (link_line_lists([], versions, centres), link_line_lists(records, versions, {})):
        assert [(ln.ns, ln.segments) for ln in empty] == [(s, ()) for s in COLOURS]


def test_an_agents_link_markers_reach_a_ros_subscriber_and_a_late_one() -> None:
    """Outputs with ``--ros-links``: a MarkerArray on rmw_zenoh's key, with its attachment and
    publisher token, decoded by rosbags; a late transient-local subscriber gets the last."""
    pytest.importorskip("rosbags")
    import ros2_peer

    a, b, b_to_a = _maps()
    book = FleetBook()
    book.put_map("a", 1, a)
    book.put_map("b", 1, b)
    comp = component({"a": (1, a), "b": (1, b)}, {"a": np.eye(3), "b": b_to_a})
    session = ros2_peer.session()
    key = ros2_peer.key("/map_merged_links", MARKERS)
    lock, got, late = threading.Lock(), [], []

    def collect(into: list):
        def callback(sample) -> None:
            msg = ros2_peer.TS.deserialize_cdr(sample.payload.to_bytes(), MARKERS)
            with lock:
                into.append((msg, sample.attachment.to_bytes()))

        return callback

    sub = session.declare_subscriber(key, collect(got))
    counters = Counters()
    out = Outputs(OutputOptions(links="/map_merged_links", rate=1.0), session, counters)
    try:
        out.tick(0.0, comp, book)  # no links yet: every namespace deleted
        assert wait_for(lambda: got, 5)
        book.add_link(_link("a", "b", trust.CANDIDATE))
        out.tick(1.0, comp, book)
        assert wait_for(lambda: len(got) >= 2, 5)
        tokens = [str(r.ok.key_expr) for r in session.liveliness().get("@ros2_lv/**")]
        listener = ros2_peer.latched_subscriber(session, key, collect(late))
        assert wait_for(lambda: late, 10)
        listener.undeclare()
    finally:
        out.close()
        sub.undeclare()
        session.close()
    (empty, _), (msg, att) = got[0], got[1]
    assert [(m.ns, m.action) for m in empty.markers] == [(s, 2) for s in DRAWN]  # DELETE
    by_ns = {m.ns: m for m in msg.markers}
    line = by_ns[trust.CANDIDATE]
    assert (line.type, line.action, line.header.frame_id) == (5, 0, "world")  # LINE_LIST, ADD
    centres = map_centres(comp, {"a": (1, a), "b": (1, b)})
    ends = [c for p in line.points for c in (p.x, p.y)]
    assert ends == pytest.approx([*centres["a"], *centres["b"]])
    assert line.scale.x > 0 and line.color.a == 1.0 and line.pose.orientation.w == 1.0
    assert all(by_ns[s].action == 2 for s in DRAWN if s != trust.CANDIDATE)
    assert len(att) == 33
    assert any("/MP/" in t and "visualization_msgs::msg::dds_::MarkerArray_/RIHS01_" in t
               for t in tokens), tokens  # fmt: skip
    assert [m.ns for m in late[-1][0].markers] == DRAWN
    assert late[-1][0].markers[2].points  # the last sent, not the first
    assert counters.snapshot()["counts"]["ros_links_bytes"] > 0
