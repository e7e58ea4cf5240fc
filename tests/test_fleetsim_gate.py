"""The fleet simulator runs the agent's search gate: real verdicts, cached, charged, counted."""

from __future__ import annotations

import time

import pytest

from agent.scenario import LOG, random_frames, segments
from bench.fleetsim_core import Meter, Rebuilds, SimClock
from bench.fleetsim_fleet import Scenario, SimFleet
from bench.fleetsim_gate import GateCache, grid_digest
from bench.fleetsim_merges import measure_outcomes, render
from bench.fleetsim_report import summarise

#: The counts a run of the same scenario must repeat.
COUNTED = ("searches", "searches_gated", "checks", "epochs", "versions_published")


@pytest.fixture(scope="module")
def outcomes():
    """The three pairs of three robots on the Intel log, measured for real."""
    return measure_outcomes(LOG, [(3, 1.0, [(0, 1), (1, 2), (0, 2)])])


def _fleet(outcomes, gates: GateCache) -> tuple[SimFleet, list[bytes]]:
    """Three robots on the Intel log, and the digests of every map A a worker searched."""
    fleet = SimFleet(
        Scenario(3, LOG, speed=200.0, limit=120.0),
        outcomes,
        Rebuilds(Meter(SimClock())),
        gates,
    )
    searched: list[bytes] = []
    for robot in fleet.robots.values():
        register = robot.worker.register

        def recorded(a, b, register=register):
            searched.append(grid_digest(a))
            return register(a, b)

        robot.worker.register = recorded
    fleet.run()
    return fleet, searched


class CountingCPU:
    """``time.thread_time`` for a repeatable run: it moves a fixed step at each read, so
    what a run charges depends on what it did, not on how busy the machine was."""

    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        self.now += 1e-4
        return self.now


def _counted_fleet(outcomes) -> tuple[SimFleet, list[bytes], GateCache]:
    gates = GateCache()
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(time, "thread_time", CountingCPU())
        fleet, searched = _fleet(outcomes, gates)
    return fleet, searched, gates


@pytest.fixture(scope="module")
def gated_fleet(outcomes):
    return _counted_fleet(outcomes)


def _counts(fleet: SimFleet) -> dict[str, dict[str, int]]:
    return {
        name: {k: r.node.counters.snapshot()["counts"].get(k, 0) for k in COUNTED}
        for name, r in fleet.robots.items()
    }


def test_a_gated_tiny_first_map_is_not_searched(gated_fleet):
    fleet, searched, gates = gated_fleet
    assert fleet.agreed_at is not None
    rejected = {key for key, (why, _) in gates.verdicts.items() if why is not None}
    assert rejected, "no first map was small enough for the gate"
    assert not rejected & set(searched)  # a map the gate rejects is never a search's map A
    row = summarise(fleet, wall_s=1.0)
    gated = sum(c["searches_gated"] for c in _counts(fleet).values())
    assert row["searches_gated"] == gated >= 1
    # each verdict is made once, and charged to every agent that asks for it
    made = sum(cpu for _, cpu in gates.verdicts.values())
    assert fleet.meter.by_kind["gate"] >= made > 0


def test_the_counts_repeat_for_a_seed(outcomes, gated_fleet):
    # the simulation's only other input is the CPU its core really spends (module
    # docstring of bench.fleetsim_core); with that held fixed, a run repeats exactly
    first, _, gates = gated_fleet
    again, _, regated = _counted_fleet(outcomes)
    assert _counts(again) == _counts(first)
    assert regated.verdicts == gates.verdicts


def test_verdicts_are_kept_beside_the_outcome_cache(tmp_path):
    seg, frame = segments(16)[3], random_frames(16, 7)[3]
    tiny, _ = render(LOG, (seg[0], seg[0] + 0.02 * (seg[1] - seg[0])), frame)  # a few metres
    whole, _ = render(LOG, seg, frame)
    made = GateCache.beside(tmp_path)
    assert made.verdict(tiny)[0] is not None and made.verdict(whole)[0] is None
    made.save()
    kept = GateCache.beside(tmp_path)
    assert kept.verdict(tiny) == made.verdict(tiny)  # same verdict, same charged CPU
    assert kept.verdict(whole) == made.verdict(whole)
    assert kept.computed == 0
