"""The merged frame never jumps: each component is anchored at its oldest robot.

Real :class:`FleetNode` cores carry real maps (the Intel lab halves of ``intel_split_gt``)
to each other as Zenoh would; each robot's first epoch travels in its manifests, and every
node builds its global map from what its book holds.
"""

from __future__ import annotations

import itertools
from pathlib import Path

import numpy as np
import pytest

from agent import wire
from agent.actions import PersistMap, Publish, Reply
from agent.evaluate import link_error
from agent.fusecache import LayerCache
from agent.globalmap import Component, build_components
from agent.links import LinkRecord, epoch_of
from agent.node import FleetNode, Instant, NodeOptions
from agent.state import StateDir, StoredMap
from pgvd.fusion import fuse_layers
from pgvd.grid import Grid, relative_matrix, rigid_matrix
from pgvd.io import read_map
from pgvd.posegraph import components, solve
from pgvd.transform import resample
from protocol import ProtocolError, encode_map

KEY = b"the lab's fleet key"
T0 = 1_700_000_000.0  # wall clock at mono 0
COV = np.diag([0.5, 0.5, 1e-5])


def at(t: float) -> Instant:
    return Instant(t, T0 + t)


def shifted(g: Grid, dx: int, dy: int) -> tuple[Grid, np.ndarray]:
    """``g`` in a frame ``(dx, dy)`` cells off, and the copy's pixels -> ``g``'s."""
    lo = np.pad(g.logodds, ((dy, 0), (dx, 0)))
    return Grid(lo, g.resolution, g.origin), rigid_matrix(0.0, -dx, -dy)


def turned(g: Grid) -> tuple[Grid, np.ndarray]:
    """``g`` in a frame turned by 90 degrees, and the copy's pixels -> ``g``'s."""
    w = g.shape[1]
    back = np.array([[0.0, -1.0, w - 1.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    return Grid(np.rot90(g.logodds).copy(), g.resolution, g.origin), back


@pytest.fixture(scope="module")
def lab(shared: Path) -> tuple[dict[str, Grid], dict[str, np.ndarray]]:
    """Three real maps at 0.1 m, each in a frame of its own, and each one's pixels -> r2's
    pixels (the truth).

    r2 and r1 are the two halves of intel_split_gt, r1's turned by 90 degrees; r3 is r2's
    half seen by a robot whose map frame is (60, 40) cells off (a second robot in the same
    rooms).
    """
    d = shared / "maps" / "intel_split_gt"
    a = resample(read_map(d / "intel_partA.yaml"), 0.1)
    b = resample(read_map(d / "intel_partB.yaml"), 0.1)
    c, c_to_a = shifted(a, 60, 40)
    e, e_to_b = turned(b)
    grids = {"r2": a, "r1": e, "r3": c}
    return grids, {"r2": np.eye(3), "r1": relative_matrix(a, b) @ e_to_b, "r3": c_to_a}


def start(robot: str, grid: Grid, t: float) -> tuple[FleetNode, list[Publish]]:
    """A robot's agent, started at ``t`` with ``grid`` as its first version, and what it
    published (persisted first, as the daemon does)."""
    node = FleetNode(NodeOptions(robot, "lab", KEY), at(t))
    (persist,) = node.on_source(grid, at(t), final=True)
    assert isinstance(persist, PersistMap)
    sent = node.on_persisted(robot, persist.stored.version, at(t))
    return node, [a for a in sent if isinstance(a, Publish)]


def deliver(to: FleetNode, sent: list[Publish] | list[Reply], t: float) -> None:
    for msg in sent:
        to.on_message(msg.key, msg.payload, at(t))


def link(
    nodes: dict[str, FleetNode], a: str, b: str, matrix: np.ndarray, noise: tuple = (0, 0, 0)
) -> None:
    """Every node of ``nodes`` caches the same accepted link ``b px -> a px`` of the held
    versions, ``noise`` ``(deg, x px, y px)`` off ``matrix`` as a registration's would be."""
    versions = nodes[a].book.versions()
    off = rigid_matrix(np.radians(noise[0]), noise[1], noise[2])
    rec = LinkRecord(a, versions[a], b, versions[b], True, off @ matrix, COV, 0.9, a)
    for node in nodes.values():
        assert node.book.add_link(rec)


def truth(to_r2: dict[str, np.ndarray], a: str, b: str) -> np.ndarray:
    return np.linalg.inv(to_r2[a]) @ to_r2[b]


def global_map(node: FleetNode, oldest: bool = True) -> list[Component]:
    """The global maps ``node`` builds from its book: anchored at the oldest robot, or
    (``oldest=False``) at the lowest robot id as before."""
    snap = node.book.snapshot()
    return build_components(snap.maps, snap.links, firsts=snap.firsts if oldest else None)


def moved(before: Component, after: Component, shapes: dict[str, tuple]) -> dict[str, tuple]:
    """``{robot: (deg, cells)}`` each placement of ``before`` moved by in ``after``."""
    return {r: link_error(after.transforms[r], m, shapes[r]) for r, m in before.transforms.items()}


def test_a_robot_with_a_lower_id_joining_moves_no_frame(lab) -> None:
    grids, to_r2 = lab
    shapes = {r: g.shape for r, g in grids.items()}
    r2, sent2 = start("r2", grids["r2"], 0.0)
    r3, sent3 = start("r3", grids["r3"], 5.0)
    deliver(r3, sent2, 5.1)
    deliver(r2, sent3, 5.1)
    running = {"r2": r2, "r3": r3}
    link(running, "r2", "r3", truth(to_r2, "r2", "r3"), (0.02, 0.3, -0.2))
    (before,) = global_map(r3)
    assert before.anchor == "r2" and before.members == ("r2", "r3")

    # r1 joins a minute later: it fetches the others' latest maps and links (the queryables'
    # replies), they hear its first map
    r1, sent1 = start("r1", grids["r1"], 60.0)
    for node in running.values():
        deliver(node, sent1, 60.1)
        deliver(r1, [*node.answer_latest(None, None), *node.answer_links()], 60.1)
    fleet = {"r1": r1, **running}
    link(fleet, "r1", "r2", truth(to_r2, "r1", "r2"), (-0.03, 0.4, 0.3))
    link(fleet, "r1", "r3", truth(to_r2, "r1", "r3"), (0.01, -0.3, 0.4))
    built = {robot: global_map(node) for robot, node in fleet.items()}
    (after,) = built["r3"]
    assert after.anchor == "r2" and after.members == ("r1", "r2", "r3")
    # fleet invariant 2: the same maps, first epochs and links give the same map everywhere
    assert {tuple(c.digest for c in comps) for comps in built.values()} == {(after.digest,)}
    for robot, (deg, cells) in moved(before, after, shapes).items():
        assert deg <= 0.1 and cells <= 1.0, (robot, deg, cells)
    # the newcomer is placed right in the old frame
    deg, cells = link_error(after.transforms["r1"], to_r2["r1"], shapes["r1"])
    assert deg < 0.1 and cells < 1.5
    # under the former rule the frame would have jumped to the newcomer's
    (lowest,) = global_map(r3, oldest=False)
    assert lowest.anchor == "r1"
    deg, cells = moved(before, lowest, shapes)["r3"]
    assert deg > 45.0 and cells > 100.0


def test_when_two_components_join_the_older_anchor_wins(lab) -> None:
    grids, placed = lab
    # {r2, r3} began first; {r1, r4} has the lower ids but began later
    maps = {"r2": (1, grids["r2"]), "r3": (1, grids["r3"]), "r1": (1, grids["r1"])}
    r4, r4_to_r1 = shifted(grids["r1"], 3, 30)
    maps["r4"] = (1, r4)
    to_r2 = {**placed, "r4": placed["r1"] @ r4_to_r1}
    firsts = {"r2": 100, "r3": 130, "r1": 200, "r4": 150}

    def rec(a: str, b: str) -> LinkRecord:
        return LinkRecord(a, 1, b, 1, True, truth(to_r2, a, b), COV, 0.9, a)

    apart = build_components(maps, [rec("r2", "r3"), rec("r1", "r4")], firsts=firsts)
    assert [(c.anchor, c.members) for c in apart] == [("r2", ("r2", "r3")), ("r4", ("r1", "r4"))]
    joined = build_components(
        maps, [rec("r2", "r3"), rec("r1", "r4"), rec("r3", "r4")], firsts=firsts
    )
    assert [(c.anchor, c.members) for c in joined] == [("r2", ("r1", "r2", "r3", "r4"))]
    shapes = {r: g.shape for r, (_, g) in maps.items()}
    for robot, (deg, cells) in moved(apart[0], joined[0], shapes).items():
        assert deg <= 0.1 and cells <= 1.0, robot
    # ties by robot id: r1 and r4 began in the same second
    tied = build_components(maps, [rec("r1", "r4")], firsts={"r1": 150, "r4": 150})
    assert [c.anchor for c in tied if len(c.members) == 2] == ["r1"]


def test_the_rank_only_picks_the_anchor_and_defaults_to_the_lowest_id() -> None:
    nodes, edges = ["a", "b", "c", "d", "e"], [("a", "b"), ("c", "b"), ("d", "e")]
    assert components(nodes, edges) == [("a", "b", "c"), ("d", "e")]
    age = {"c": 1, "e": 2}.get
    assert components(nodes, edges, lambda n: age(n, 9)) == [("c", "a", "b"), ("e", "d")]
    ab, bc = rigid_matrix(0.3, 10.0, -4.0), rigid_matrix(-0.1, 2.0, 7.0)
    links = [
        LinkRecord("a", 1, "b", 1, True, ab, COV, 0.9, "a"),
        LinkRecord("b", 1, "c", 1, True, bc, COV, 0.9, "b"),
    ]
    sol = solve(nodes[:3], links, rank=lambda n: {"c": 0}.get(n, 1))
    assert sol.components == (("c", "a", "b"),)
    np.testing.assert_allclose(sol.transforms["c"], np.eye(3))
    np.testing.assert_allclose(sol.transforms["a"], np.linalg.inv(ab @ bc), atol=1e-9)
    assert not sol.covariances["c"].any() and sol.covariances["a"].any()


def test_a_restarted_robot_keeps_its_first_epoch_and_a_lost_state_makes_a_new_robot(
    lab, tmp_path: Path
) -> None:
    grids, _ = lab
    first, _ = start("r1", grids["r1"], 0.0)
    own = first.book.map_of("r1")
    assert own is not None and first.book.snapshot().firsts == {"r1": epoch_of(own[0])}
    state = StateDir(tmp_path)
    state.save_map("r1", StoredMap(own[0], own[1], first_epoch=epoch_of(own[0])))
    maps, errors = StateDir(tmp_path).load_maps()
    assert errors == [] and maps["r1"].first_epoch == int(T0)
    # a day later, with newer epochs, its manifests still say it began at T0
    again = FleetNode(NodeOptions("r1", "lab", KEY), at(86_400.0))
    again.restore(maps, [], at(86_400.0))
    (persist,) = again.on_source(grids["r2"], at(86_401.0), final=True)
    assert epoch_of(persist.stored.version) > int(T0) and persist.stored.first_epoch == int(T0)
    sent = again.on_persisted("r1", persist.stored.version, at(86_401.0))
    peer = FleetNode(NodeOptions("r2", "lab", KEY), at(86_401.0))
    deliver(peer, [a for a in sent if isinstance(a, Publish)], 86_401.1)
    assert peer.book.snapshot().firsts == {"r1": int(T0)}
    # the same id with its state directory lost is a new robot: a new first epoch
    _, sent = start("r1", grids["r1"], 90_000.0)
    deliver(peer, sent, 90_000.1)
    assert peer.book.snapshot().firsts == {"r1": int(T0) + 90_000}


def test_maps_persisted_without_a_first_epoch(lab) -> None:
    """Files of an older agent: the own map's first epoch is its version's epoch, the oldest
    this robot can vouch for; a peer's map is left to be fetched again, since every agent
    must read the same first epoch with a version."""
    grids, _ = lab
    version = (int(T0) + 7) << 31 | 3
    node = FleetNode(NodeOptions("r1", "lab", KEY), at(0.0))
    node.restore({"r1": StoredMap(version, grids["r1"]), "r2": StoredMap(version, grids["r2"])},
                 [], at(0.0))  # fmt: skip
    assert node.book.versions() == {"r1": version}
    assert node.book.snapshot().firsts == {"r1": int(T0) + 7}
    manifest = node.answer_latest(None, None)[-1]
    assert wire.Inbound("lab", KEY).decode(manifest.payload).first_epoch == int(T0) + 7


def test_a_first_epoch_newer_than_its_version_is_dropped(lab) -> None:
    grids, _ = lab
    version = 5 << 31
    tiles, manifest = encode_map("lab", "r2", version, grids["r2"], KEY, first_epoch=6)
    inbound = wire.Inbound("lab", KEY)
    with pytest.raises(ProtocolError, match="first epoch 6 is newer than version"):
        inbound.feed(inbound.decode(manifest))
    _, manifest = encode_map("lab", "r2", version, grids["r2"], KEY, first_epoch=5)
    done = [inbound.feed(inbound.decode(m)) for m in [*tiles, manifest]]
    assert done[-1] is not None and done[-1][0] == version and done[-1][2] == 5


def test_fusion_takes_the_anchor_as_base_then_the_others_by_id(lab) -> None:
    grids, to_r2 = lab
    maps = {r: (1, g) for r, g in grids.items()}
    links = [
        LinkRecord(a, 1, b, 1, True, truth(to_r2, a, b), COV, 0.9, a)
        for a, b in itertools.combinations(sorted(grids), 2)
    ]
    (comp,) = build_components(maps, links, firsts={"r3": 1, "r1": 2, "r2": 2})
    assert comp.anchor == "r3" and comp.members == ("r1", "r2", "r3")
    mats, covs = comp.transforms, comp.covariances
    r1, r2 = (LayerCache().layer(r, 1, grids[r], mats[r], covs[r])[0] for r in ("r1", "r2"))
    in_order = fuse_layers(grids["r3"], [r1, r2])
    assert comp.grid.origin == in_order.origin
    np.testing.assert_array_equal(comp.grid.logodds, in_order.logodds)
    # the entropy filter (37) makes the order tell
    assert not np.array_equal(comp.grid.logodds, fuse_layers(grids["r3"], [r2, r1]).logodds)


def test_a_damaged_first_epoch_is_one_error_line_not_a_crash(lab, tmp_path: Path) -> None:
    grids, _ = lab
    state = StateDir(tmp_path)
    state.save_map("r1", StoredMap(5 << 31, grids["r1"], first_epoch=5))
    path = tmp_path / "maps" / "r1.npz"
    with np.load(path) as z:
        arrays = {k: z[k] for k in z.files}
    np.savez(path, **{**arrays, "first_epoch": np.int64(-1)})
    maps, errors = state.load_maps()
    assert maps == {} and errors == ["r1.npz: corrupt map arrays: first_epoch"]
