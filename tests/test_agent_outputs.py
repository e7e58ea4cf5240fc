"""The global map's placements in the merged frame, from real maps in known frames."""

from __future__ import annotations

import math

import numpy as np
import pytest

from agent.globalmap import Component
from agent.outputs import map_placements
from pgvd.grid import Grid, relative_matrix
from pgvd.integrate import se2
from pgvd.io import read_map


def _component(maps: dict[str, tuple[int, Grid]], transforms: dict[str, np.ndarray]) -> Component:
    members = tuple(sorted(maps))
    return Component(
        anchor=members[0], members=members, versions={r: v for r, (v, _) in maps.items()},
        transforms=transforms, covariances={r: np.zeros((3, 3)) for r in members},
        used=(), rejected=(), grid=maps[members[0]][1], digest="d",
    )


@pytest.mark.parametrize("yaw_b", [0.0, 0.7, -2.5])
def test_placements_are_the_true_frames_of_each_map(yaw_b: float) -> None:
    """Two real maps whose metric frames are known: the placement is the true transform."""
    a = read_map("examples/intel_a.yaml")
    # B's metric frame is A's turned by yaw_b and moved by (3, -2): B's origin in its own frame
    # is where A's metric frame puts its lower-left corner, so the true B px -> A px matrix is
    # relative_matrix of the two grids expressed in A's frame.
    b_to_a = se2(3.0, -2.0, yaw_b)
    b_in_a = Grid(a.logodds[::-1, :].copy(), a.resolution, (3.0, -2.0, yaw_b))
    b_own = Grid(b_in_a.logodds, a.resolution, (0.0, 0.0, 0.0))
    px = relative_matrix(a, b_in_a)  # b_own and b_in_a share pixels
    comp = _component({"a": (1, a), "b": (4, b_own)}, {"a": np.eye(3), "b": px})
    placed = {p.child: p for p in map_placements(comp, {"a": (1, a), "b": (4, b_own)}, "world")}
    assert placed["a/map"].x == pytest.approx(0.0, abs=1e-9)
    assert placed["a/map"].yaw == pytest.approx(0.0, abs=1e-9)
    got = placed["b/map"]
    assert got.parent == "world"
    assert (got.x, got.y) == pytest.approx((b_to_a[0, 2], b_to_a[1, 2]), abs=1e-6)
    assert math.remainder(got.yaw - yaw_b, 2 * math.pi) == pytest.approx(0.0, abs=1e-9)


def test_a_map_newer_than_the_component_is_not_placed() -> None:
    a = read_map("examples/intel_a.yaml")
    comp = _component({"a": (1, a), "b": (4, a)}, {"a": np.eye(3), "b": np.eye(3)})
    placed = map_placements(comp, {"a": (1, a), "b": (5, a)}, "world")
    assert [p.child for p in placed] == ["a/map"]
    assert map_placements(comp, {"a": (2, a), "b": (4, a)}, "world") == []
