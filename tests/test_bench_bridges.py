"""bench.studies.bridges: which links no cycle checks, on graphs and on the committed fleet
results of the development buildings."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

from agent.launcher import ROOT
from bench.studies import bridges as br

RESULTS = ROOT / "bench" / "results" / "fleet-accuracy.json"


def test_a_tail_on_a_triangle_is_the_only_bridge() -> None:
    nodes = ["r1", "r2", "r3", "r4"]
    edges = [("r1", "r2"), ("r2", "r3"), ("r1", "r3"), ("r3", "r4")]
    assert br.bridges(nodes, edges) == {frozenset(("r3", "r4"))}
    groups = br.cycle_groups({"members": nodes, "used": [list(e) for e in edges]})
    assert sorted(map(sorted, groups)) == [["r1", "r2", "r3"], ["r4"]]


def test_a_chain_is_all_bridges_and_a_ring_has_none() -> None:
    nodes = ["a", "b", "c", "d"]
    chain = [("a", "b"), ("b", "c"), ("c", "d")]
    assert br.bridges(nodes, chain) == {frozenset(e) for e in chain}
    assert br.bridges(nodes, [*chain, ("d", "a")]) == set()


def test_a_wrong_spell_is_judged_on_the_map_shown_when_it_began() -> None:
    tail = {"members": ["r1", "r2", "r3"], "used": [["r1", "r2"], ["r2", "r3"]]}
    ring = {"members": ["r1", "r2", "r3"], "used": [["r1", "r2"], ["r2", "r3"], ["r1", "r3"]]}
    case = {
        "building": "b", "robots": 3, "seed": 7,
        "history": {"maps": [
            {"t": 1.0, "agent": "r1", "components": [tail]},
            {"t": 2.0, "agent": "r1", "components": [ring]},
        ]},
        "summary": {
            "delays": [{"pair": "r1-r3", "placed_at": 1.0}],
            "wrong_spells": [
                {"agent": "r1", "robot": "r3", "start": 1.5},
                {"agent": "r1", "robot": "r3", "start": 2.0},
            ],
        },
    }  # fmt: skip
    case["history"]["links"] = [
        {"t": 0.5, "pair": "r2-r3", "how": "searched", "margin": 0.7},
        {"t": 1.8, "pair": "r1-r3", "how": "checked", "margin": 0.8},
    ]
    row = br.study_case(case)
    assert [s["by_bridges"] for s in row["wrong_spells"]] == [True, False]
    # what held r3 when each spell began: the last decision on each pair by then
    assert row["wrong_spells"][0]["held_by"] == [("r2-r3", "searched", 0.7)]
    assert row["wrong_spells"][1]["held_by"] == [
        ("r2-r3", "searched", 0.7), ("r1-r3", "checked", 0.8),
    ]  # fmt: skip
    assert sorted(row["came_in"]) == ["?", "checked", "searched"]
    assert row["extra_s"] == [1.0]
    assert row["placed"] == row["on_cycle"] == ["r1", "r2", "r3"]


def test_the_development_results_read_whole(tmp_path: Path) -> None:
    out = subprocess.run(
        [sys.executable, "-m", "bench", "bridges", str(RESULTS), "--out", str(tmp_path)],
        cwd=ROOT, capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert out.returncode == 0, out.stderr
    rows = json.loads((tmp_path / "bridges.json").read_text())["rows"]
    assert len(rows) == len(json.loads(RESULTS.read_text())["cases"])
    for row in rows:
        assert set(row["on_cycle"]) <= set(row["placed"])
        # two robots hold one link: a cycle needs a third
        if row["robots"] == 2:
            assert row["on_cycle"] == [] and row["extra_s"] == []
    assert "| **all** |" in (tmp_path / "bridges.md").read_text()


def test_a_missing_file_is_one_line_and_exit_2(tmp_path: Path) -> None:
    out = subprocess.run(
        [sys.executable, "-m", "bench", "bridges", str(tmp_path / "none.json")],
        cwd=ROOT, capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    assert out.returncode == 2
    assert out.stderr.strip().count("\n") == 0 and "no such result file" in out.stderr
