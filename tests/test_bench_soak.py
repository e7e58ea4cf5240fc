"""bench.soak's steadiness measures: moves between consecutive global maps, anchor changes."""

from __future__ import annotations

import json
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from components import component

from agent.status import component_json
from bench.soak import (
    JOINER,
    _churn_plan,
    _record_placements,
    anchor_changes,
    jumps,
    placement_move,
    robot_ids,
    rss_growth,
    unchanged_moves,
)
from pgvd.grid import Grid, rigid_matrix

ROOT = Path(__file__).resolve().parents[1]
#: Each robot's canvas: the moves are measured over its corners.
SHAPE = (10, 10)


def _map(t: float, x: np.ndarray, links: list) -> dict:
    eye = np.eye(3).tolist()
    return {"t": t, "digest": str(t), "members": ["r1", "r2"], "links": links,
            "transforms": {"r1": eye, "r2": x.tolist()}}  # fmt: skip


def test_placement_move_over_the_canvas_corners() -> None:
    cells, deg = placement_move(np.eye(3).tolist(), rigid_matrix(0.0, 3.0, 4.0).tolist(), (10, 10))
    assert cells == pytest.approx(5.0) and deg == pytest.approx(0.0)
    turn = rigid_matrix(np.radians(0.5), 0.0, 0.0)
    cells, deg = placement_move(np.eye(3).tolist(), turn.tolist(), (101, 101))
    assert deg == pytest.approx(0.5) and cells == pytest.approx(
        np.hypot(100, 100) * np.radians(0.5), rel=1e-3
    )


def test_jumps_split_same_links_from_new_links() -> None:
    x = rigid_matrix(0.2, 50.0, 10.0)
    same = [("r1", "r2", "r1", 1, 1)]
    history = {
        "r1": [
            _map(0.0, x, same),
            _map(1.0, x, same),  # a new version, same link: no move
            _map(2.0, rigid_matrix(0.2, 52.0, 10.0), [("r1", "r2", "r1", 2, 1)]),  # new link
        ]
    }
    out = jumps(history, lambda robot: (10, 10))
    assert out["same_links"] == {"cells": 0.0, "deg": 0.0, "pairs": 1}
    assert out["all"]["pairs"] == 2 and out["all"]["cells"] == pytest.approx(2.0)
    history["r1"][1]["members"] = ["r1", "r2", "r3"]  # membership changed: not compared
    assert jumps(history, lambda robot: (10, 10))["all"]["pairs"] == 0


def merged(anchor: str, placed: dict[str, tuple[int, np.ndarray]], digest: str) -> dict:
    """A merged map as an agent's status shows it: robot -> (version, placement)."""
    grid = Grid(np.zeros(SHAPE, np.float32), 0.1)
    comp = component(
        {r: (v, grid) for r, (v, _) in placed.items()},
        {r: m for r, (_, m) in placed.items()},
        digest,
    )
    return component_json(replace(comp, anchor=anchor))


def poll(history: dict, t: float, own: dict, *others: dict) -> None:
    """What agent r1's status says at second ``t``: its own merged map and the others."""
    _record_placements(history, {"r1": {"robot": "r1", "components": [own, *others]}}, t)


EYE = np.eye(3)
R2 = rigid_matrix(0.0, 20.0, 0.0)
R3 = rigid_matrix(0.0, 0.0, 30.0)


def test_the_anchor_changes_are_told_apart_and_unchanged_robots_moves_measured() -> None:
    """Agent r1's global maps through a run; the warm-up ends at 10 s."""
    history: dict[str, list] = {}
    r5r6 = merged("r5", {"r5": (1, EYE), "r6": (1, R2)}, "56")
    # warm-up: the anchor changes while the merged map forms; not counted
    poll(history, 1.0, merged("r2", {"r1": (1, EYE), "r2": (1, R2)}, "a"))
    poll(history, 2.0, merged("r1", {"r1": (1, EYE), "r2": (1, R2)}, "b"))
    # the lone r3 joins, and r2, its map unchanged, moves 0.5 cells
    members = {"r1": (1, EYE), "r2": (1, R2 @ rigid_matrix(0.0, 0.5, 0.0)), "r3": (1, R3)}
    poll(history, 11.0, merged("r1", members, "c"))
    # r2's map changes and it moves 7 cells: not a robot whose map is unchanged
    members["r2"] = (2, R2 @ rigid_matrix(0.0, 7.0, 0.0))
    poll(history, 12.0, merged("r1", members, "d"))
    poll(history, 12.5, merged("r1", members, "d"), r5r6)  # the merged map r5-r6 forms
    # the frame jumps to r3 although r1 is still held and nobody joined
    moved = {r: (v, np.linalg.inv(R3) @ m) for r, (v, m) in members.items()}
    poll(history, 13.0, merged("r3", moved, "e"), r5r6)
    # the merged map r5-r6 joins it and takes the anchor: two frames became one
    moved |= {"r5": (1, EYE), "r6": (1, R2)}
    poll(history, 14.0, merged("r5", moved, "f"))
    # r5 is forgotten: the anchor left, r6 takes it
    del moved["r5"]
    poll(history, 15.0, merged("r6", moved, "g"))

    changes = anchor_changes(history, since=10.0)
    assert changes == {"jumps": 1, "left": 1, "merged": 1, "jumped": [["r1", 13.0, "r1", "r3"]]}
    assert anchor_changes(history)["jumps"] == 2  # with the warm-up: r2 -> r1 at 2 s too
    moves = unchanged_moves(history, lambda robot: SHAPE, since=10.0)
    # b -> c (r2 moved, a join) and c -> d (r3 still); later pairs changed anchor
    assert moves["all"] == {"cells": 0.5, "deg": 0.0, "pairs": 2}
    assert moves["membership_changed"] == {"cells": 0.5, "deg": 0.0, "pairs": 1}


def test_a_join_that_moves_an_unchanged_robot_counts_as_a_membership_change() -> None:
    history: dict[str, list] = {}
    poll(history, 1.0, merged("r1", {"r1": (1, EYE), "r2": (1, R2)}, "a"))
    turned = R2 @ rigid_matrix(np.radians(0.2), 0.0, 0.0)
    poll(history, 2.0, merged("r1", {"r1": (1, EYE), "r2": (1, turned), "r0": (1, R3)}, "b"))
    moves = unchanged_moves(history, lambda robot: SHAPE)
    assert moves["membership_changed"]["deg"] == pytest.approx(0.2)
    assert moves["membership_changed"]["cells"] == pytest.approx(
        np.hypot(9, 9) * np.radians(0.2), abs=1e-3
    )
    assert moves["all"] == moves["membership_changed"]


def test_the_joiner_has_the_lowest_id_so_a_lowest_id_anchor_would_jump() -> None:
    ids = robot_ids(16, churn=True)
    assert ids[-1] == JOINER == min(ids) and len(set(ids)) == 17
    plan = _churn_plan(16, 4.0)
    assert [(kind, robot) for _, kind, robot in plan] == [
        ("leave", "r16"),
        ("join", JOINER),
        ("return", "r16"),
    ]
    assert [t for t, _, _ in plan] == [60.0, 120.0, 180.0]


def test_a_late_joiners_memory_grows_from_its_own_warm_up() -> None:
    """Sampled every 5 s: 100 MB at its start, 200 MB from its warm-up on, 210 MB at the end."""
    joiner = [
        (t, 0.0, 100.0 if t < 120 else 210.0 if t >= 300 else 200.0) for t in range(90, 365, 5)
    ]
    assert rss_growth(joiner) == pytest.approx(5.0)


@pytest.mark.fleet
@pytest.mark.slow
def test_a_short_churn_soak_reports_the_merged_frame(tmp_path) -> None:
    """Real agents for one minute: a robot leaves, r0 joins, the first returns; the report
    carries the anchor changes and the moves of unchanged robots beside the rest."""
    cmd = [sys.executable, "-m", "bench", "soak", "--robots", "2", "--churn", "--minutes", "1",
           "--settle", "30", "--out", str(tmp_path)]  # fmt: skip
    done = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-2000:]
    summary = json.loads((tmp_path / "soak-cycle-churn.json").read_text())["summary"]
    assert [(c["event"], c["robot"]) for c in summary["churn"]] == [
        ("leave", "r2"),
        ("join", JOINER),
        ("return", "r2"),
    ]
    assert summary["dead"] == [] and set(summary["rss_end_mb"]) == {"r0", "r1", "r2"}
    assert set(summary["anchor_changes"]) == {"jumps", "left", "merged", "jumped"}
    assert set(summary["unchanged_moves"]) == {"all", "membership_changed"}
    md = (tmp_path / "soak-cycle-churn.md").read_text()
    assert "- anchor changes of an agent's merged map after warm-up:" in md
    assert "- largest move of robots whose map did not change" in md


def test_a_lone_robots_first_merge_is_no_jump_and_a_departed_anchor_is_no_jump() -> None:
    def seen(t: float, anchor: str, members: list[str]) -> dict:
        return {"t": t, "anchor": anchor, "members": members, "others": []}

    history = {
        "r2": [
            seen(1.0, "r1", ["r1", "r2"]),
            seen(2.0, "r1", ["r1", "r2", "r3"]),  # r3 joins: the frame stays
            seen(3.0, "r0", ["r0", "r1", "r2", "r3"]),  # r0 joins and takes the frame: a jump
            seen(4.0, "r1", ["r1", "r2", "r3"]),  # r0 forgotten: the frame follows its departure
        ],
        "r0": [seen(1.0, "r0", ["r0"]), seen(3.0, "r1", ["r0", "r1", "r2", "r3"])],  # lone r0
    }
    assert anchor_changes(history) == {
        "jumps": 1,
        "left": 1,
        "merged": 0,
        "jumped": [["r2", 3.0, "r1", "r0"]],
    }
