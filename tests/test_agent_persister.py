"""agent.persister: own versions durable and reported in order, peers' maps newest only."""

from __future__ import annotations

import threading
from pathlib import Path

import numpy as np
import pytest

from agent.counters import Counters
from agent.links import LinkRecord
from agent.persister import Persister
from agent.state import StateDir, StoredMap
from pgvd.grid import Grid, rigid_matrix
from pgvd.io import read_map


@pytest.fixture(scope="module")
def grid(shared: Path) -> Grid:
    """A real map: the Intel lab's first half."""
    return read_map(shared / "maps" / "intel_split_gt" / "intel_partA.yaml")


def test_own_versions_are_on_disk_when_reported_and_reported_in_order(tmp_path, grid) -> None:
    state = StateDir(tmp_path)
    on_disk: list[tuple[int, int]] = []

    def saved(robot: str, version: int) -> None:
        on_disk.append((version, state.load_maps()[0][robot].version))

    writer = Persister(state, "r1", saved, Counters())
    for version in (1, 2, 3):
        writer.save_map("r1", StoredMap(version, grid, {"scan": version}))
    writer.start()
    assert writer.close()
    # each report came once its own version was the file on disk: none coalesced away
    assert on_disk == [(1, 1), (2, 2), (3, 3)]
    assert state.load_maps()[0]["r1"].extra == {"scan": 3}


def test_only_the_newest_pending_version_of_a_peer_is_written(tmp_path, grid) -> None:
    state, counters = StateDir(tmp_path), Counters()
    reported: list[tuple[str, int]] = []
    writer = Persister(state, "r1", lambda r, v: reported.append((r, v)), counters)
    for version in (4, 5, 6):
        writer.save_map("r2", StoredMap(version, grid))
    writer.save_map("r3", StoredMap(9, grid))
    writer.start()
    assert writer.close()
    maps, errors = state.load_maps()
    assert errors == [] and {r: m.version for r, m in maps.items()} == {"r2": 6, "r3": 9}
    assert counters.get("writes_coalesced") == 2
    assert reported == []  # only own versions gate anything


def test_forgetting_a_robot_cancels_its_pending_write(tmp_path, grid) -> None:
    state = StateDir(tmp_path)
    state.save_map("r2", StoredMap(1, grid))
    writer = Persister(state, "r1", lambda r, v: None, Counters())
    writer.save_map("r2", StoredMap(2, grid))
    writer.forget_map("r2")
    writer.start()
    assert writer.close()
    assert state.load_maps() == ({}, [])


def test_a_slow_disk_holds_back_no_caller_and_close_writes_what_is_pending(tmp_path, grid) -> None:
    """While one write is stuck (a disk that stalls), the core's thread still queues more
    and returns at once; closing writes everything queued meanwhile, the last links only."""
    state = StateDir(tmp_path)
    stuck, release = threading.Event(), threading.Event()
    save_map = state.save_map

    def stalling(robot: str, stored: StoredMap, *args: object, **kwargs: object) -> None:
        if stored.version == 1:
            stuck.set()
            release.wait(30)
        save_map(robot, stored, *args, **kwargs)

    state.save_map = stalling  # type: ignore[method-assign]
    writer = Persister(state, "r1", lambda r, v: None, Counters())
    writer.start()
    writer.save_map("r2", StoredMap(1, grid))
    assert stuck.wait(30)
    cov = np.diag([4.0, 4.0, 1e-4])
    link = LinkRecord("r1", 1, "r2", 1, True, rigid_matrix(0.1, 2.0, 3.0), cov, 0.9, "r1")
    for records in ((), (link,)):
        writer.save_links(records)
    writer.save_map("r3", StoredMap(2, grid))
    release.set()
    assert writer.close()
    assert {r: m.version for r, m in state.load_maps()[0].items()} == {"r2": 1, "r3": 2}
    assert [ln.pair for ln in state.load_links()[0]] == [("r1", "r2")]
