"""bench.fleet_accuracy: placement errors and delays on built histories, one real fleet run."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from agent.evaluate import true_matrix
from agent.launcher import ROOT
from bench import fleet_history as fh
from pgvd.grid import Grid
from pgvd.integrate import se2
from pgvd.io import write_map

TOL = fh.Tolerance(2.0, 3.0)
#: r1's frame is the world's (10 px per metre); r2's is turned 30 degrees and shifted.
TRUTH = fh.Truth(
    {
        "r1": np.diag([10.0, 10.0, 1.0]),
        "r2": np.diag([10.0, 10.0, 1.0]) @ se2(4.0, -2.0, np.radians(30.0)),
    },
    {"r1": (100, 100), "r2": (100, 100)},
)
RIGHT_T = true_matrix(TRUTH.world_to_pixel["r1"], TRUTH.world_to_pixel["r2"])
WRONG_T = RIGHT_T + np.array([[0, 0, 10.0], [0, 0, 0], [0, 0, 0]])  # 10 cells off


def comp(t2: np.ndarray | None) -> list[dict]:
    """A global map: r1 and r2 together with r2 at ``t2``, or each alone if None."""
    if t2 is None:
        return [
            {"anchor": r, "members": [r], "transforms": {r: np.eye(3).tolist()}}
            for r in ("r1", "r2")
        ]
    transforms = {"r1": np.eye(3).tolist(), "r2": t2.tolist()}
    return [{"anchor": "r1", "members": ["r1", "r2"], "transforms": transforms}]


def shown(t: float, agent: str, t2: np.ndarray | None) -> dict:
    return {"t": t, "agent": agent, "components": comp(t2)}


def test_relative_error_is_zero_at_the_truth_and_counts_corner_cells_off_it() -> None:
    transforms = comp(RIGHT_T)[0]["transforms"]
    deg, cells = fh.relative_error(transforms, "r1", "r2", TRUTH)
    assert deg == pytest.approx(0, abs=1e-9) and cells == pytest.approx(0, abs=1e-9)
    deg, cells = fh.relative_error(comp(WRONG_T)[0]["transforms"], "r1", "r2", TRUTH)
    assert deg == pytest.approx(0, abs=1e-9) and cells == pytest.approx(10.0)
    # seen from r2, r1 is as far off: the same error, measured on r1's canvas
    deg, cells = fh.relative_error(comp(WRONG_T)[0]["transforms"], "r2", "r1", TRUTH)
    assert cells == pytest.approx(10.0)


def test_placements_alone_right_and_wrong() -> None:
    assert fh.placements(comp(None), TRUTH, TOL) == {"r1": "unplaced", "r2": "unplaced"}
    assert fh.placements(comp(RIGHT_T), TRUTH, TOL) == {"r1": "right", "r2": "right"}
    # the wrong placement is r2's; the anchor is not counted wrong a second time
    assert fh.placements(comp(WRONG_T), TRUTH, TOL) == {"r1": "unplaced", "r2": "wrong"}
    assert fh.placements(comp(WRONG_T), TRUTH, fh.Tolerance(2.0, 12.0))["r2"] == "right"


def test_wrong_spells_end_at_the_agents_next_right_map_or_at_the_run_end() -> None:
    maps = [
        shown(0.5, "r1", None),
        shown(1.0, "r1", WRONG_T),
        shown(2.0, "r2", WRONG_T),
        shown(2.5, "r1", WRONG_T),  # still wrong: the spell goes on
        shown(3.0, "r1", RIGHT_T),
    ]
    spells = fh.wrong_spells(maps, TRUTH, TOL, end=10.0)
    assert spells == [
        {"agent": "r1", "robot": "r2", "start": 1.0, "end": 3.0, "seconds": 2.0, "at_end": False},
        {"agent": "r2", "robot": "r2", "start": 2.0, "end": 10.0, "seconds": 8.0, "at_end": True},
    ]
    assert fh.placed_right_at_end(maps, ["r1", "r2"], TRUTH, TOL) == {"r1": False, "r2": False}
    maps.append(shown(4.0, "r2", RIGHT_T))
    assert fh.placed_right_at_end(maps, ["r1", "r2"], TRUTH, TOL) == {"r1": True, "r2": True}


def test_delay_runs_from_the_overlap_threshold_until_both_agents_place_the_pair() -> None:
    maps = [
        shown(1.0, "r1", WRONG_T),  # together, but wrongly: not placed
        shown(3.0, "r1", RIGHT_T),
        shown(4.0, "r2", None),
        shown(5.0, "r2", RIGHT_T),  # now both robots' agents show them together
    ]
    progress = [
        {"t": 0.0, "robot": "r1", "cursor": 5, "epochs": 1},
        {"t": 1.0, "robot": "r2", "cursor": 5, "epochs": 1},
        {"t": 4.0, "robot": "r1", "cursor": 9, "epochs": 3},
        {"t": 5.0, "robot": "r2", "cursor": 9, "epochs": 2},
    ]
    overlaps = [
        {"t": 1.0, "pair": "r1-r2", "overlap": 0.1},
        {"t": 2.0, "pair": "r1-r2", "overlap": 0.35},
        {"t": 4.0, "pair": "r1-r2", "overlap": 0.5},
    ]
    (delay,) = fh.pair_delays(maps, progress, overlaps, TRUTH, TOL, 0.3)
    assert delay == {
        "pair": "r1-r2",
        "overlap_at": 2.0,
        "placed_at": 5.0,
        "seconds": 3.0,
        "epochs": (3 - 1) + (2 - 1),
        "linked_at": None,
    }
    # a pair never placed has no delay; a pair that never reached the threshold is left out
    (never,) = fh.pair_delays(maps[:3], progress, overlaps, TRUTH, TOL, 0.3)
    assert never["placed_at"] is None and never["seconds"] is None and never["epochs"] is None
    assert fh.pair_delays(maps, progress, overlaps, TRUTH, TOL, 0.6) == []


def test_link_decisions_are_read_from_the_agents_logs_and_join_pairs_over_chains() -> None:
    import time

    t0 = time.mktime(time.strptime("2026-12-04 23:40:10", "%Y-%m-%d %H:%M:%S"))
    lines = [
        "2026-12-04 23:40:17,992 r1 INFO robot r4 joined",
        "2026-12-04 23:40:18,337 r1 INFO link pair=r1/r2 versions=1.0/1.0 outcome=candidate "
        'margin=0.68 holds=0 by=r1 reason="provisional: margin 0.68" how=searched seconds=0.05',
        "2026-12-04 23:40:19,500 r2 INFO link pair=r2/r3 versions=1.0/1.0 outcome=accepted "
        'margin=0.92 holds=0 by=r2 reason="margin 0.92 clears 0.89" how=searched seconds=1.2',
        "2026-12-04 23:40:20,000 r1 INFO link pair=r1/r2 versions=1.1/1.0 outcome=confirmed "
        'margin=0.80 holds=1 by=r1 reason="holds" how=rechecked seconds=0.3',
        "2026-12-04 23:40:21,250 r1 INFO link pair=r1/r3 versions=2.0/1.0 outcome=rejected "
        'margin=none holds=0 by=r1 reason="no pose" how=carried forward seconds=0.1 book=taken',
        # refused by the book: its epochs were replaced while it was searched
        "2026-12-04 23:40:21,900 r1 INFO link pair=r1/r4 versions=1.0/1.0 outcome=accepted "
        'margin=0.95 holds=0 by=r1 reason="margin 0.95 clears 0.89" how=searched seconds=0.4 '
        "book=superseded",
    ]
    events = fh.link_events(lines, t0)
    assert [(e["t"], e["pair"], e["state"], e["how"]) for e in events] == [
        (8.337, "r1-r2", "candidate", "searched"),
        (9.5, "r2-r3", "accepted", "searched"),
        (10.0, "r1-r2", "confirmed", "rechecked"),
        (11.25, "r1-r3", "rejected", "carried forward"),
    ]
    assert events[0]["margin"] == 0.68 and events[-1]["margin"] is None
    # a candidate does not join; its confirmation joins r1 to r3 over r2
    assert fh.linked_at(events, "r1", "r2") == fh.linked_at(events, "r1", "r3") == 10.0
    assert fh.linked_at(events, "r1", "r4") is None


def test_timeline_colours_a_robot_by_what_all_agents_show() -> None:
    from bench.fleet_accuracy import timeline

    case = {
        "robots": 2,
        "history": {
            "maps": [
                shown(1.0, "r1", RIGHT_T),
                shown(2.0, "r2", None),
                shown(3.0, "r2", RIGHT_T),
                shown(4.0, "r1", WRONG_T),
            ]
        },
    }
    states = [(t, s["r2"]) for t, s in timeline(case, TRUTH, TOL)]
    # r2's agent not heard from yet, then alone on it, then right on both, then wrong on r1
    assert states == [(1.0, "some"), (2.0, "some"), (3.0, "right"), (4.0, "wrong")]


def test_held_out_logs_are_every_log_but_the_development_ones(tmp_path: Path) -> None:
    from bench.fleet_accuracy import DEV_LOGS, held_out_logs

    for name in [p.name for p in DEV_LOGS] + ["other-corrected.log.gz", "notes.txt"]:
        (tmp_path / name).write_bytes(b"")
    assert held_out_logs(tmp_path) == [tmp_path / "other-corrected.log.gz"]


def test_default_buildings_are_the_development_logs_and_map_images() -> None:
    from bench.data.sources import DEVELOPMENT_MAPS
    from bench.fleet_accuracy import DEV_LOGS, DEV_MAPS, buildings_of, parse_args

    found = buildings_of(parse_args([]))
    assert [b.path for b in found] == [*DEV_LOGS, *DEV_MAPS]
    maps = [b for b in found if b.kind == "map"]
    # one image of every development building, none held out
    assert len({b.path.parent.name for b in maps}) == len(maps) == 6
    assert all(b.path.parent.name in DEVELOPMENT_MAPS for b in maps)


def walls_only(path: Path) -> Path:
    """A 5 m square map image with no free space in it."""
    write_map(path, Grid(np.full((100, 100), 4.0, np.float32), 0.05))
    return path


def bench(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    cmd = [sys.executable, "-m", "bench.fleet_accuracy", *args]
    env = {"PYTHONPATH": str(ROOT), "PATH": "/usr/bin:/bin"}
    return subprocess.run(cmd, cwd=cwd, env=env, capture_output=True, text=True, timeout=60)


@pytest.mark.parametrize(
    ("args", "why"),
    [
        (["--robots", "1"], "--robots must be between 2 and 12"),
        (["--buildings", "map:some.yaml"], "map not found: some.yaml"),
        (["--buildings", "log:no-such.log.gz"], "log not found: no-such.log.gz"),
        (["--buildings", "map:walls.yaml"], "walls.yaml: the map has no free space"),
        (["--buildings", "intel"], "a building is log:PATH or map:PATH.yaml"),
        (["--quick", "--held-out"], "exclude each other"),
        (["--min-overlap", "0"], "--min-overlap must be in (0, 1]"),
        (["--timeout", "x"], "invalid float value"),
        (["--keep", "."], "--keep must be a new or empty directory"),
    ],
)
def test_bad_arguments_are_one_line_and_exit_2(tmp_path: Path, args: list[str], why: str) -> None:
    walls_only(tmp_path / "walls.yaml")
    res = bench(*args, "--out", str(tmp_path / "out"), cwd=tmp_path)
    assert res.returncode == 2, res.stderr
    assert res.stderr.strip().count("\n") == 0 and why in res.stderr
    assert not (tmp_path / "out").exists()


@pytest.mark.fleet
@pytest.mark.slow
@pytest.mark.parametrize("kind", ["log", "map"])
def test_two_agents_report_what_their_status_files_say(tmp_path: Path, kind: str) -> None:
    """The bundled Intel log, or the simulated drive through the first development map
    image (the Intel lab's, the smallest), replayed by two real agents."""
    from agent.scenario import LOG
    from bench import fleet_accuracy as fa

    building = fa.Building(kind, LOG if kind == "log" else fa.DEV_MAPS[0])
    settings = fa.Settings(log_seconds=30.0, timeout=180.0)
    case = fa.run_case(building, 2, 7, settings, tmp_path / "fleet", verbose=kind == "log")
    assert case["agreed_s"] is not None and case["dead_agents"] == []
    # a kept run's agents log at debug level (--keep), others at info
    debug = " DEBUG " in (tmp_path / "fleet" / "r1" / "agent.log").read_text()
    assert debug == (kind == "log")
    status = {
        r: json.loads((tmp_path / "fleet" / r / "state" / "status.json").read_text())
        for r in ("r1", "r2")
    }
    truth = fa.truth_of(case)
    summary, hist = case["summary"], case["history"]
    for robot, s in status.items():
        # the bench's truth is the agents' own
        assert s["source"]["kind"] == fa.SOURCE_KIND[kind]
        assert np.allclose(truth.world_to_pixel[robot], s["source"]["world_to_pixel"])
        assert list(truth.shapes[robot]) == s["source"]["canvas_shape"]
        # the last map recorded of each agent is the one its status file holds
        last = [m for m in hist["maps"] if m["agent"] == robot][-1]
        assert [(c["anchor"], c["members"], c["digest"]) for c in last["components"]] == [
            (c["anchor"], c["members"], c["digest"]) for c in s["components"]
        ]
        cursor = [p["cursor"] for p in hist["progress"] if p["robot"] == robot][-1]
        assert cursor == s["source"]["progress"][0] == s["source"]["progress"][1]
    final = [fh.placements(s["components"], truth, TOL) for s in status.values()]
    assert summary["wrong_at_end"] == sum(p.get(r) == fh.WRONG for p in final for r in p)
    right = sorted(r for r in ("r1", "r2") if all(p.get(r) == fh.RIGHT for p in final))
    assert summary["overlapping_robots"] == ["r1", "r2"]  # the segments share a third of the log
    assert summary["placed_right_at_end"] == right
    # the pair reached the overlap threshold; placed right at the end, it was placed at a time
    (delay,) = summary["delays"]
    assert right != ["r1", "r2"] or delay["placed_at"] is not None
    assert summary["global_maps_seen"] == len(hist["maps"]) >= 2
    # the agents' logged decisions: the link that joined the pair came before it was shown
    assert {e["agent"] for e in hist["links"]} <= {"r1", "r2"} and hist["links"]
    assert delay["placed_at"] is None or delay["linked_at"] <= delay["placed_at"]
    fa.write_results([case], ["--test"], settings, case["wall_s"], tmp_path / "out", False)
    md = (tmp_path / "out" / "fleet-accuracy.md").read_text()
    assert f"| {building.name} | 2 | 7 |" in md
    assert (tmp_path / "out" / "fleet-accuracy.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    saved = json.loads((tmp_path / "out" / "fleet-accuracy.json").read_text())
    assert saved["cases"][0]["summary"] == json.loads(json.dumps(summary))
