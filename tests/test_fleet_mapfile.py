"""Two agents follow map_server files that an "external SLAM" (this test) keeps rewriting."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from agent.evaluate import link_error
from agent.launcher import LocalFleet, agreement, wait_for
from pgvd.grid import Grid, relative_matrix
from pgvd.io import read_map, write_map
from pgvd.transform import resample

pytestmark = [pytest.mark.fleet, pytest.mark.slow]


def test_agents_follow_rewritten_map_files_and_link_them(shared: Path, tmp_path: Path) -> None:
    d = shared / "maps" / "intel_split_gt"
    a = resample(read_map(d / "intel_partA.yaml"), 0.1)
    b = resample(read_map(d / "intel_partB.yaml"), 0.1)
    truth = relative_matrix(a, b)  # the *_split_gt halves are rendered in one world frame
    files = {"m1": tmp_path / "slam1" / "map.yaml", "m2": tmp_path / "slam2" / "map.yaml"}
    # The first map of m2 is its top half only: the SLAM has not explored the rest yet.
    partial = b.logodds.copy()
    partial[partial.shape[0] // 2 :] = 0.0
    write_map(files["m1"], a)
    write_map(files["m2"], Grid(partial, b.resolution, b.origin))

    with LocalFleet("maps", tmp_path / "fleet") as fleet:
        for robot, path in files.items():
            fleet.add(robot, f"map:{path}")

        def both_hold(version_of_m2: int | None = None) -> bool:
            st = fleet.statuses()
            held = [s and s["robots"].get("m2", {}).get("version") for s in st.values()]
            return (
                agreement(st)
                and all(held)
                and (version_of_m2 is None or all(v > version_of_m2 for v in held))
            )

        assert wait_for(both_hold, 60)
        first = fleet.agents["m1"].status()["robots"]["m2"]["version"]
        write_map(files["m2"], b)  # the SLAM rewrites its map
        assert wait_for(lambda: both_hold(first), 60)
        statuses = fleet.statuses()

    for s in statuses.values():
        (link,) = [ln for ln in s["links"] if ln["current"]]
        assert link["accepted"]
        deg, cells = link_error(np.array(link["matrix"]), truth, b.shape)
        assert deg <= 2.0 and cells <= 3.0
        assert s["global"]["members"] == ["m1", "m2"] and s["source"]["read_errors"] == 0
    assert statuses["m1"]["global"]["digest"] == statuses["m2"]["global"]["digest"]
