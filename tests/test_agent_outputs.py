"""The global map's placements in the merged frame, from real maps in known frames, and the
TF an agent publishes from them as its global map changes."""

from __future__ import annotations

import math
import threading

import numpy as np
import pytest
from components import component

from agent.book import FleetBook
from agent.counters import Counters
from agent.launcher import wait_for
from agent.outputs import OutputOptions, Outputs, map_placements
from pgvd.grid import Grid, relative_matrix
from pgvd.integrate import se2
from pgvd.io import read_map

TF = "tf2_msgs/msg/TFMessage"


def _b_in_a(a: Grid, x: float, y: float, yaw: float) -> np.ndarray:
    """B px -> A px when B's metric frame is A's moved by (x, y, yaw) (B: A's cells, flipped)."""
    return relative_matrix(a, Grid(a.logodds[::-1, :].copy(), a.resolution, (x, y, yaw)))


@pytest.mark.parametrize("yaw_b", [0.0, 0.7, -2.5])
def test_placements_are_the_true_frames_of_each_map(yaw_b: float) -> None:
    """Two real maps whose metric frames are known: the placement is the true transform."""
    a = read_map("examples/intel_a.yaml")
    # B's metric frame is A's turned by yaw_b and moved by (3, -2): B's origin in its own frame
    # is where A's metric frame puts its lower-left corner, so the true B px -> A px matrix is
    # relative_matrix of the two grids expressed in A's frame.
    b_to_a = se2(3.0, -2.0, yaw_b)
    b_own = Grid(a.logodds[::-1, :].copy(), a.resolution, (0.0, 0.0, 0.0))
    px = _b_in_a(a, 3.0, -2.0, yaw_b)  # b_own and B placed in A's frame share pixels
    comp = component({"a": (1, a), "b": (4, b_own)}, {"a": np.eye(3), "b": px})
    placed = {p.child: p for p in map_placements(comp, {"a": (1, a), "b": (4, b_own)}, "world")}
    assert placed["a/map"].x == pytest.approx(0.0, abs=1e-9)
    assert placed["a/map"].yaw == pytest.approx(0.0, abs=1e-9)
    got = placed["b/map"]
    assert got.parent == "world"
    assert (got.x, got.y) == pytest.approx((b_to_a[0, 2], b_to_a[1, 2]), abs=1e-6)
    assert math.remainder(got.yaw - yaw_b, 2 * math.pi) == pytest.approx(0.0, abs=1e-9)


def test_a_map_newer_than_the_component_is_not_placed() -> None:
    a = read_map("examples/intel_a.yaml")
    comp = component({"a": (1, a), "b": (4, a)}, {"a": np.eye(3), "b": np.eye(3)})
    placed = map_placements(comp, {"a": (1, a), "b": (5, a)}, "world")
    assert [p.child for p in placed] == ["a/map"]
    assert map_placements(comp, {"a": (2, a), "b": (4, a)}, "world") == []


def test_tf_follows_the_global_map_as_it_changes() -> None:
    """Each new global map re-places the robots on /tf_static, and only a change is sent;
    while a member's map has moved on since the rebuild, the last placements stand in rather
    than dropping it from TF, and a late tf2 listener gets them from the publisher's cache."""
    pytest.importorskip("rosbags")
    import ros2_peer

    a = read_map("examples/intel_a.yaml")
    b = Grid(a.logodds[::-1, :].copy(), a.resolution, (0.0, 0.0, 0.0))
    book = FleetBook()
    book.put_map("a", 1, a)
    book.put_map("b", 4, b)
    session = ros2_peer.session()
    lock, got, late = threading.Lock(), [], []
    key = ros2_peer.key("/tf_static", TF)

    def on_tf(into: list):
        def callback(sample) -> None:
            msg = ros2_peer.TS.deserialize_cdr(sample.payload.to_bytes(), TF)
            with lock:
                into.append({t.child_frame_id: t.transform for t in msg.transforms})

        return callback

    def sent_after(tick) -> dict | None:
        with lock:
            seen = len(got)
        tick()
        if not wait_for(lambda: len(got) > seen, 3):
            return None
        with lock:
            return got[-1]

    sub = session.declare_subscriber(key, on_tf(got))
    out = Outputs(OutputOptions(publish="/map_merged", rate=1.0), session, Counters())
    try:
        first = component(
            {"a": (1, a), "b": (4, b)}, {"a": np.eye(3), "b": _b_in_a(a, 3.0, -2.0, 0.7)}
        )
        tf = sent_after(lambda: out.tick(0.0, first, book))
        assert (tf["b/map"].translation.x, tf["b/map"].translation.y) == pytest.approx(
            (3.0, -2.0), abs=1e-6
        )
        # the same global map again: static transforms are not sent again
        assert sent_after(lambda: out.tick(1.0, first, book)) is None
        # The merge refines B's link: a new global map, and B's transform moves with it.
        refined = component(
            {"a": (1, a), "b": (4, b)},
            {"a": np.eye(3), "b": _b_in_a(a, 3.5, -1.0, 0.7)},
            digest="d2",
        )
        tf = sent_after(lambda: out.tick(2.0, refined, book))
        assert (tf["b/map"].translation.x, tf["b/map"].translation.y) == pytest.approx(
            (3.5, -1.0), abs=1e-6
        )
        q = tf["b/map"].rotation
        assert 2 * math.atan2(q.z, q.w) == pytest.approx(0.7, abs=1e-9)
        # B's map moves on before the next rebuild: its placement cannot be computed from
        # this global map, so the refined placements stand in, not sent again.
        book.put_map("b", 5, b)
        stale = component(
            {"a": (1, a), "b": (4, b)},
            {"a": np.eye(3), "b": _b_in_a(a, 9.0, 9.0, 0.0)},
            digest="d3",
        )
        assert sent_after(lambda: out.tick(3.0, stale, book)) is None
        # a listener that starts now gets them, as tf2's transient-local listener does
        listener = ros2_peer.latched_subscriber(session, key, on_tf(late))
        assert wait_for(lambda: late, 10)
        listener.undeclare()
        assert sorted(late[-1]) == ["a/map", "b/map"]
        assert late[-1]["b/map"].translation.x == pytest.approx(3.5, abs=1e-6)
    finally:
        out.close()
        sub.undeclare()
        session.close()
