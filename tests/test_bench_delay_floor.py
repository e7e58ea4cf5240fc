"""bench.studies.delay_floor: epochs cut as the agent cuts them, the trust rules of a lone pair,
and the floor of a real pair of the bundled Intel log."""

from __future__ import annotations

import itertools
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from agent.launcher import ROOT
from agent.node import NodeOptions
from agent.scenario import LOG
from agent.sources import epoch_due
from agent.trust import ACCEPTED, CANDIDATE, CONFIRMED, HIGH_BAR
from agent.worker import Registration
from bench import fleet_accuracy as fa
from bench.studies import delay_floor as df
from pgvd.grid import Grid

INTEL = fa.Building("log", LOG)


@pytest.fixture(scope="module")
def intel_pair() -> tuple[dict, dict]:
    """Two robots on the bundled Intel log in the frames of seed 7, as the fleet bench runs
    them: their epochs, and the study's case."""
    growing = fa.GrowingMaps(fa.fleet_specs(INTEL, 2, 7))
    epochs, _ = df.epochs_of(growing, fa.replay_speed(growing, fa.Settings.log_seconds))
    return epochs, df.run_case(INTEL, 2, 7, fa.Settings())


def test_each_epoch_starts_where_the_agents_rule_says(intel_pair) -> None:
    epochs, _ = intel_pair
    for robot, found in epochs.items():
        assert len(found) >= 3, robot
        assert [e.t for e in found] == sorted(e.t for e in found)
        assert all(b.cursor > a.cursor for a, b in itertools.pairwise(found))
        # every epoch but the last changed enough since the one before; the last is final
        for before, after in itertools.pairwise(found[:-1]):
            assert epoch_due(before.grid, after.grid, NodeOptions.epoch_change)
        assert found[-1].final and not any(e.final for e in found[:-1])


def test_epoch_pairs_are_every_pair_of_current_epochs_in_time_order(intel_pair) -> None:
    epochs, _ = intel_pair
    pairs = df.epoch_pairs(epochs["r1"], epochs["r2"])
    starts = [max(a.t, b.t) for a, b in pairs]
    assert starts == sorted(starts)
    # a new pair each time either robot starts an epoch, once both have one
    assert len(pairs) == len(epochs["r1"]) + len(epochs["r2"]) - 1
    assert pairs[-1] == (epochs["r1"][-1], epochs["r2"][-1])


def test_a_real_pair_floor_orders_merge_trust_and_high(intel_pair) -> None:
    _, case = intel_pair
    pair = case["pairs"]["r1-r2"]
    floors = pair["floors"]
    assert floors["merge"] is not None and floors["trust"] is not None
    assert floors["merge"]["epochs"] <= floors["trust"]["epochs"]
    if floors["high"] is not None:
        assert floors["trust"]["epochs"] <= floors["high"]["epochs"]
    assert pair["final"]["accepted"] and pair["final"]["right"]
    counted = [s["epochs"] for s in pair["searches"]]
    assert counted == sorted(counted)


def test_the_fleet_delays_are_read_per_building_size_and_seed() -> None:
    measured = df.fleet_delays(fa.RESULTS / "fleet-accuracy.json")
    assert set(measured[("intel", 2, 7)]) == {"r1-r2"}
    assert df.fleet_delays(Path("no-such-results.json")) == {}


def _registration(margin: float, matrix: np.ndarray) -> Registration:
    return Registration(margin >= 0.57, matrix, np.eye(3), 0.9, "", margin)


def test_a_lone_pair_is_let_in_at_the_high_bar_or_when_a_newer_epoch_finds_it_again() -> None:
    b = Grid(np.ones((50, 50), np.float32), 0.05, (0.0, 0.0))
    pose, elsewhere = np.eye(3), np.array([[1.0, 0, 40], [0, 1, 0], [0, 0, 1]])
    rules = df.Trust(0.57)
    assert rules.decide(_registration(0.7, pose), b, final=False) == CANDIDATE
    assert rules.decide(_registration(0.7, pose), b, final=False) == CONFIRMED
    rules = df.Trust(0.57)
    assert rules.decide(_registration(0.7, pose), b, final=False) == CANDIDATE
    assert rules.decide(_registration(0.7, elsewhere), b, final=False) == CANDIDATE
    assert rules.decide(_registration(HIGH_BAR, pose), b, final=False) == ACCEPTED
    # a provisional accept on both robots' final maps is confirmed, as a one-shot merge
    assert df.Trust(0.57).decide(_registration(0.7, pose), b, final=True) == CONFIRMED


@pytest.mark.parametrize(
    ("args", "why"),
    [
        (["--robots", "1"], "--robots must be between 2 and 12"),
        (["--min-overlap", "0"], "--min-overlap must be in (0, 1]"),
        (["--buildings", "nowhere"], "a building is log:PATH"),
    ],
)
def test_bad_arguments_are_one_line_and_exit_2(tmp_path: Path, args: list[str], why: str) -> None:
    run = subprocess.run(
        [sys.executable, "-m", "bench", "delay_floor", *args, "--out", str(tmp_path)],
        cwd=ROOT, capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    lines = run.stderr.strip().splitlines()
    assert run.returncode == 2 and len(lines) == 1, run.stderr
    assert lines[0].startswith("delay_floor: ") and why in lines[0]


def _searched(t: float, state: str, right: bool = True) -> dict:
    return {"t": t, "epochs": 0, "accepted": True, "margin": 0.7, "right": right, "state": state}


def test_a_chain_of_right_links_let_in_joins_a_pair_before_its_own_link() -> None:
    case = {
        "epochs": {"r1": [[0.0, 1], [2.0, 9]], "r2": [[0.0, 1]], "r3": [[0.0, 1], [3.0, 9]]},
        "pairs": {
            "r1-r2": {"overlap_at": 0.0, "searches": [_searched(1.0, CONFIRMED)]},
            "r1-r3": {"overlap_at": 0.0, "searches": [_searched(4.0, CONFIRMED)]},
            "r2-r3": {
                "overlap_at": 0.0,
                "searches": [_searched(1.0, CANDIDATE), _searched(3.0, CONFIRMED)],
            },
        },
    }
    floors = df.chain_floors(case)
    # r1-r3 is joined at 3.0 through r2, before its own link at 4.0; r1's epoch at 2.0 and
    # r3's at 3.0 were begun meanwhile
    assert floors["r1-r3"] == {"epochs": 2, "seconds": 3.0}
    assert floors["r1-r2"] == {"epochs": 0, "seconds": 1.0}
    # a wrong link let in joins nothing: r2-r3 waits for the chain through r1 at 4.0
    case["pairs"]["r2-r3"]["searches"][-1] = _searched(3.0, CONFIRMED, right=False)
    assert df.chain_floors(case)["r2-r3"] == {"epochs": 1, "seconds": 4.0}
