"""The fleet simulator: its event loop, its network model, a tiny fleet that agrees, its CLI."""

from __future__ import annotations

import json
import math
import subprocess
import sys

import numpy as np
import pytest

from agent.scenario import LOG
from bench.fleetsim import main
from bench.fleetsim_core import Meter, Rebuilds, SimClock
from bench.fleetsim_fleet import Scenario, SimFleet
from bench.fleetsim_merges import measure_outcomes
from bench.fleetsim_net import EventLoop, NetParams, Network, Partition
from bench.fleetsim_report import load_real_runs, summarise, validation


def test_event_loop_runs_in_time_order_and_ties_in_order_set():
    loop = EventLoop()
    seen = []
    for when, tag in [(3.0, "c"), (1.0, "a"), (2.0, "b1"), (2.0, "b2"), (9.0, "late")]:
        loop.at(when, lambda t=tag: seen.append((loop.now, t)))
    loop.run(until=5.0)
    assert seen == [(1.0, "a"), (2.0, "b1"), (2.0, "b2"), (3.0, "c")]
    assert loop.now == 5.0 and len(loop) == 1  # the event after the horizon waits


def _network(**params) -> tuple[EventLoop, Network, list[tuple[float, str, bytes]]]:
    loop = EventLoop()
    got: list[tuple[float, str, bytes]] = []
    net = Network(
        loop,
        NetParams(**params),
        lambda receiver, key, payload: got.append((loop.now, receiver, payload)),
        lambda target, asker, selector: None,
    )
    net.online |= {"r1", "r2", "r3"}
    return loop, net, got


def test_put_fans_out_after_latency_and_bandwidth():
    loop, net, got = _network(latency=0.01, jitter=0.0, bandwidth=1000.0)
    net.put("r1", "k", b"x" * 100, ["r1", "r2", "r3"])
    loop.run(until=10.0)
    # 0.1 s on r1's uplink per copy, 0.01 s in flight, 0.1 s on the receiver's downlink
    assert [(round(t, 3), r) for t, r, _ in got] == [(0.21, "r2"), (0.31, "r3")]
    assert net.traffic["r1"].sent_bytes == 100  # a put is sent once, as an agent counts it
    assert net.traffic["r2"].received_bytes == net.traffic["r3"].received_bytes == 100


def test_loss_drops_about_its_share():
    loop, net, got = _network(loss=0.3, seed=1)
    for _ in range(1000):
        net.put("r1", "k", b"m", ["r2"])
    loop.run(until=10.0)
    assert net.traffic["r1"].lost + len(got) == 1000
    assert 250 <= net.traffic["r1"].lost <= 350


def test_partition_and_churn_drop_what_crosses_them():
    apart = Partition(1.0, 2.0, (frozenset({"r1"}), frozenset({"r2", "r3"})))
    loop, net, got = _network(partitions=(apart,))
    for t in (0.5, 1.5, 2.5):
        loop.at(t, net.put, "r1", "k", str(t).encode(), ["r2", "r3"])
    loop.at(1.5, net.put, "r2", "k", b"inside", ["r3"])
    loop.at(2.2, net.online.discard, "r3")
    loop.run(until=10.0)
    delivered = sorted((r, p) for _, r, p in got)
    assert delivered == [("r2", b"0.5"), ("r2", b"2.5"), ("r3", b"0.5"), ("r3", b"inside")]


def test_a_query_is_answered_by_its_target_only():
    loop = EventLoop()
    asked = []
    net = Network(loop, NetParams(), lambda *a: None, lambda t, a, s: asked.append((t, a, s)))
    net.online |= {"r1", "r2", "r3"}
    net.query("r1", "r3", "pgvd/default/r3/latest?")
    loop.run(until=1.0)
    assert asked == [("r3", "r1", "pgvd/default/r3/latest?")]


@pytest.fixture(scope="module")
def tiny_outcomes():
    """The three pairs of three robots on the Intel log, measured for real."""
    return measure_outcomes(LOG, [(3, 1.0, [(0, 1), (1, 2), (0, 2)])])


@pytest.fixture(scope="module")
def tiny_fleet(tiny_outcomes):
    """Three robots on the Intel log, drawing from their pairs' real outcomes."""
    fleet = SimFleet(
        Scenario(3, LOG, speed=200.0, limit=120.0), tiny_outcomes, Rebuilds(Meter(SimClock()))
    )
    fleet.run()
    return fleet


def test_a_drawn_search_carries_its_real_pose_error(tiny_outcomes):
    accepted = [o.search for o in tiny_outcomes if o.search.accepted]
    assert accepted
    turn = math.radians(30.0)
    other = np.array([[math.cos(turn), -math.sin(turn), 40.0],
                      [math.sin(turn), math.cos(turn), -25.0], [0.0, 0.0, 1.0]])  # fmt: skip
    for outcome in accepted:
        # a real merge lands near the truth, never exactly on it
        assert not np.allclose(outcome.error, np.eye(3), atol=1e-9)
        shift_m = float(np.hypot(*outcome.error[:2, 2])) * 0.1
        assert shift_m < 2.0
        # on another pair, the same error against that pair's truth
        drawn = outcome.at(other).matrix
        np.testing.assert_allclose(np.linalg.inv(other) @ drawn, outcome.error, atol=1e-9)
    # --exact-poses: the same outcomes, on the truth
    for pair in tiny_outcomes:
        exact = pair.exact()
        assert exact.search.accepted == pair.search.accepted
        np.testing.assert_array_equal(exact.search.at(other).matrix, other)


def test_tiny_fleet_agrees_on_the_final_maps(tiny_fleet):
    assert tiny_fleet.agreed_at is not None
    robots = list(tiny_fleet.robots.values())
    final = {r.name: r.final_version for r in robots}
    assert all(r.node.book.versions() == final for r in robots)
    views = {tiny_fleet._view(r) for r in robots}
    assert len(views) == 1 and None not in views
    (comp,) = robots[0].state.components  # one component of all three
    assert comp.members == ("r1", "r2", "r3")


def test_tiny_fleet_counts_add_up(tiny_fleet):
    row = summarise(tiny_fleet, wall_s=1.0)
    robots = tiny_fleet.robots.values()
    counts = [r.node.counters.snapshot()["counts"] for r in robots]
    assert row["searches"] == sum(c.get("searches", 0) for c in counts) >= 1
    assert row["checks"] == sum(c.get("checks", 0) for c in counts)
    assert row["epochs_per_robot"] == pytest.approx(sum(c["epochs"] for c in counts) / 3, abs=0.01)
    # every robot received at least every version of the two others, as tiles and manifests
    published = {r.name: r.node.counters.snapshot()["counts"]["versions_published"] for r in robots}
    for r in robots:
        others = sum(v for n, v in published.items() if n != r.name)
        assert tiny_fleet.net.traffic[r.name].received_messages >= 2 * others
    assert row["worker_cpu_s_per_agent"] > 0 and row["rebuilds_per_agent"] >= 1
    assert row["rebuilds_run_with_fusion"] >= 1
    held = [sum(g.logodds.nbytes for _, g in r.node.book.snapshot().maps.values()) for r in robots]
    assert row["grid_bytes_per_agent"] > sum(held) / 3  # plus each one's global map
    assert row["agreement_s"] is not None and row["agreement_s"] >= 0


def test_tiny_fleet_holds_one_read_only_copy_of_each_peer_map(tiny_fleet):
    robots = list(tiny_fleet.robots.values())
    for peer in robots:
        held = [r.node.book.snapshot().maps[peer.name][1] for r in robots if r is not peer]
        assert all(g is held[0] for g in held)  # one object for every receiver
        assert not held[0].logodds.flags.writeable
        with pytest.raises(ValueError):
            held[0].logodds[0, 0] = 1.0
    shared = tiny_fleet.shared
    # each payload decoded once though two robots received it; the two charged alike
    received = sum(t.received_messages for t in tiny_fleet.net.traffic.values())
    assert 0 < shared.decodes < received
    assert shared.owed > 0


def test_validation_sets_each_count_against_the_real_runs_mean_and_range(tmp_path):
    runs = []
    for i, (searches, checks) in enumerate([(30, 40), (50, 44)]):
        path = tmp_path / f"fleet-{i}.json"
        path.write_text(json.dumps([{"robots": 8, "searches": searches, "checks": checks}]))
        runs.append(path)
    real = load_real_runs(runs)
    sim = [{"robots": 8, "searches": 45, "checks": 50}, {"robots": 16, "searches": 9}]
    by_measure = {c["measure"]: c for c in validation(sim, real)}
    assert set(by_measure) == {"searches", "checks"}  # nothing real at 16
    searches, checks = by_measure["searches"], by_measure["checks"]
    assert searches["fleet"] == [30.0, 50.0] and searches["fleet_mean"] == 40.0
    assert searches["spread"] == 0.5 and searches["difference"] == 0.125
    assert searches["within"]  # 12.5 % off the mean, but inside the runs' range
    assert checks["difference"] == pytest.approx(0.190, abs=1e-3) and not checks["within"]


def test_a_bad_real_result_file_is_refused_in_one_line(tmp_path, capsys):
    bad = tmp_path / "fleet.json"
    bad.write_text('{"robots": 8}')
    code = main(["--robots", "3", "--real", str(bad), "--out", str(tmp_path / "out")])
    assert code == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert lines == [f"fleetsim: not a bench.fleet result file (a list of rows by robots): {bad}"]


@pytest.mark.parametrize(
    "args, message",
    [
        (["--robots", "1"], "robots must be in 2..256"),
        (["--churn", "r1"], "churn must be ROBOT:LEAVE[:BACK]"),
        (["--robots", "3", "--churn", "r9:1"], "churn names robots not in a fleet of 3"),
        (["--loss", "1.5", "--robots", "3"], "loss in [0, 1)"),
        (["--partition", "5", "1", "--robots", "3"], "a partition needs 0 <= START < END"),
        (["--cores", "0", "--robots", "3"], "argument --cores: must be > 0, got 0"),
    ],
)
def test_bad_arguments_give_one_line_and_exit_2(args, message, tmp_path, capsys):
    try:
        code = main([*args, "--out", str(tmp_path)])
    except SystemExit as exc:  # argparse's own refusals
        code = exc.code
    assert code == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and message in lines[0], lines
    assert not list(tmp_path.iterdir())


def test_bench_entry_point_refuses_bad_arguments_in_one_line(tmp_path):
    proc = subprocess.run(
        [sys.executable, "-m", "bench", "fleetsim", "--robots", "x", "--out", str(tmp_path)],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 2
    assert proc.stderr.strip().splitlines() == [
        "fleetsim: argument --robots: robots must be in 2..256, got 'x'"
    ]
