"""The fusion cache: a warm rebuild re-warps only what changed and is bit for bit a cold one."""

from __future__ import annotations

import logging
import re

import numpy as np
import pytest

import agent.fusecache
from agent.book import FleetBook
from agent.fusecache import LayerCache
from agent.globalmap import Component, build_components
from agent.links import EPOCH_SHIFT, LinkRecord
from agent.worker import FusionWorker, Registration
from pgvd.fusion import blur_in_own_frame, fuse_layers, warp_layer
from pgvd.grid import Grid, relative_matrix, rigid_matrix

COV = np.diag([0.2, 0.2, 1e-5])


def link(a: str, b: str, m: np.ndarray) -> LinkRecord:
    return LinkRecord(a, 1, b, 1, True, m, COV, 0.9, a)


def rolled(g: Grid, dx: int, dy: int) -> tuple[Grid, np.ndarray]:
    """A copy of ``g`` shifted by whole cells, and copy px -> ``g`` px."""
    copy = Grid(np.roll(g.logodds, (dy, dx), axis=(0, 1)), g.resolution, g.origin)
    return copy, rigid_matrix(0.0, -dx, -dy)


def same_maps(warm: list[Component], cold: list[Component]) -> bool:
    return [(c.members, c.digest, c.grid.origin, c.grid.logodds.tobytes()) for c in warm] == [
        (c.members, c.digest, c.grid.origin, c.grid.logodds.tobytes()) for c in cold
    ]


def test_a_warm_rebuild_is_a_cold_one_through_every_kind_of_change(halves: tuple) -> None:
    """A version, a placement, a robot joining far out (the canvas grows), a robot leaving:
    each re-warps only the robots it moved, and the global map is the cold build's bytes."""
    a, b, truth = halves
    c, c_to_a = rolled(a, 7, 4)
    d, d_to_b = rolled(b, -6, 3)
    maps = {"r1": (1, a), "r2": (1, b), "r3": (1, c), "r4": (1, d)}
    links = [link("r1", "r2", truth), link("r1", "r3", c_to_a), link("r2", "r4", d_to_b)]
    cache = LayerCache()

    def rebuild() -> tuple[int, Component]:
        warps = cache.warps
        warm = build_components(maps, links, layers=cache)
        assert same_maps(warm, build_components(maps, links))
        (comp,) = (k for k in warm if len(k.members) > 1)
        return cache.warps - warps, comp

    assert rebuild()[0] == 3
    assert rebuild()[0] == 0  # nothing changed

    walls = c.logodds.copy()
    walls[100:110, 50:200] = 3.0
    maps["r3"] = (2, Grid(walls, c.resolution, c.origin))  # r3's next version
    assert rebuild()[0] == 1

    links[2] = link("r2", "r4", rigid_matrix(0.05, 1.5, -2.0) @ d_to_b)  # r4 placed anew
    assert rebuild()[0] == 1

    before = rebuild()[1].grid.shape
    maps["r5"] = (1, b)
    links.append(link("r1", "r5", rigid_matrix(0.6, 250.0, 180.0)))
    warps, comp = rebuild()
    assert warps == 1 and comp.grid.shape[0] > before[0] + 100 and comp.grid.shape[1] > before[1]
    assert cache.robots == {"r2", "r3", "r4", "r5"}  # the anchor needs no layer

    held = cache.held_bytes()
    del maps["r3"]
    warps, comp = rebuild()
    assert warps == 0 and comp.members == ("r1", "r2", "r4", "r5")
    assert cache.robots == {"r2", "r4", "r5"} and cache.held_bytes() < held


def test_a_failing_blur_falls_back_to_the_plain_warp_the_same_everywhere(
    halves: tuple, monkeypatch: pytest.MonkeyPatch
) -> None:
    a, b, truth = halves

    def fragile(grid: Grid, cov: np.ndarray) -> np.ndarray:
        if cov.any():
            raise ZeroDivisionError("float division by zero")
        return blur_in_own_frame(grid, cov)

    monkeypatch.setattr(agent.fusecache, "blur_in_own_frame", fragile)
    cache = LayerCache()
    maps = {"r1": (1, a), "r2": (1, b)}
    for _ in range(2):  # cold, then warm: the fallback is held with the layer
        (comp,) = build_components(maps, [link("r1", "r2", truth)], layers=cache)
        assert comp.unblurred == ("r2",)
        plain = fuse_layers(a, [warp_layer(b, comp.transforms["r2"], np.zeros((3, 3)))])
        assert comp.grid.logodds.tobytes() == plain.logodds.tobytes()
    assert cache.warps == 1 and cache.reuses == 1


def test_the_worker_keeps_its_layers_from_one_rebuild_to_the_next(
    halves: tuple, caplog: pytest.LogCaptureFixture
) -> None:
    """A worker's rebuilds with real fusion: r2's next minor versions (its links hold)
    re-warp r2 alone, and the global map is the one a cold build of the same book gives."""
    a, b, _ = halves
    ox, oy, yaw = a.origin
    c = Grid(a.logodds, a.resolution, (ox + 1.0, oy - 0.5, yaw))  # r3: A's map, placed apart
    book, globals_ = FleetBook(), []

    def register(first: Grid, second: Grid) -> Registration:
        return Registration(True, relative_matrix(first, second), COV, 0.9)  # one world frame

    worker = FusionWorker("r1", book, register, book.add_link, globals_.append)
    epoch = 1 << EPOCH_SHIFT
    for robot, grid in (("r1", a), ("r2", b), ("r3", c)):
        book.put_map(robot, epoch, grid)
    caplog.set_level(logging.DEBUG, logger="pgvd.agent")

    def settle(now: float) -> tuple[float, list[int]]:
        """Steps over 40 s (every pair's turn comes); how many maps each rebuild warped."""
        caplog.clear()
        for _ in range(40):
            worker.step(now)
            now += 1.0
        return now, [int(n) for n in re.findall(r"components, (\d+) maps warped", caplog.text)]

    now, _ = settle(0.0)
    assert len(book.snapshot().links) == 3 and globals_[-1].settled
    for minor in (1, 2):
        walls = b.logodds.copy()
        walls[100 + 20 * minor, 40:120] = 3.0
        book.put_map("r2", epoch | minor, Grid(walls, b.resolution, b.origin))
        now, warped = settle(now)
        assert warped == [1]  # one rebuild, of r2's layer alone
    snap = book.snapshot()
    (last,) = globals_[-1].components
    assert last.versions == {"r1": epoch, "r2": epoch | 2, "r3": epoch}
    assert same_maps([last], build_components(snap.maps, snap.links))


def test_a_re_solve_that_moves_placements_by_less_than_a_step_re_warps_nobody(
    halves: tuple,
) -> None:
    """Three robots on a cycle: a link changed by a hair re-solves the cycle and moves
    every placement by a rounding error, which the snapped placements absorb; a link
    moved by a pixel re-warps the robots it moved, and warm stays cold throughout."""
    a, b, truth = halves
    c, c_to_a = rolled(a, 7, 4)
    maps = {"r1": (1, a), "r2": (1, b), "r3": (1, c)}
    c_to_b = np.linalg.inv(truth) @ c_to_a
    links = [link("r1", "r2", truth), link("r1", "r3", c_to_a), link("r2", "r3", c_to_b)]
    cache = LayerCache()

    def rebuild() -> tuple[int, Component]:
        warps = cache.warps
        (warm,) = build_components(maps, links, layers=cache)
        assert same_maps([warm], build_components(maps, links))
        return cache.warps - warps, warm

    assert rebuild()[0] == 2
    raw = build_components(maps, links)  # the solve's own placements, for the next check
    links[2] = link("r2", "r3", rigid_matrix(1e-9, 1e-7, -1e-7) @ c_to_b)
    warps, comp = rebuild()
    assert warps == 0
    assert all(np.array_equal(comp.transforms[r], raw[0].transforms[r]) for r in maps)

    links[2] = link("r2", "r3", rigid_matrix(0.0, 1.5, 0.0) @ c_to_b)
    warps, comp = rebuild()
    assert warps == 2 and not np.array_equal(comp.transforms["r2"], raw[0].transforms["r2"])


def test_each_blur_is_counted_with_its_cause(halves: tuple) -> None:
    """A robot's first map, its covariance on another lattice point, its next version."""
    _, b, truth = halves
    cache = LayerCache()
    cache.layer("r2", 1, b, truth, COV)
    cache.layer("r2", 1, b, truth, COV)  # held: no blur
    cache.layer("r2", 1, b, truth, COV * 2.0)
    cache.layer("r2", 2, b, truth, COV * 2.0)
    assert cache.blur_causes == {"first": 1, "covariance": 1, "version": 1}
    assert cache.blurs == 3
