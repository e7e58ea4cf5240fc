"""Fleet simulator: N real fleet cores in one process, in simulated time, at 16 to 128 robots.

Every robot is a real :class:`agent.node.FleetNode` with its real
:class:`agent.worker.FusionWorker`, replaying its segment of the development Intel log as
:mod:`bench.fleet` does (:mod:`bench.fleetsim_fleet`), over a simulated network with latency,
jitter, loss, bandwidth, partitions and churn (:mod:`bench.fleetsim_net`).  Registrations
are real merge and check outcomes drawn from a cache by true overlap, charged at their
measured CPU cost (:mod:`bench.fleetsim_merges`); the agent's search gate runs as in ``pgvd
agent``, its verdicts real ones on the replayed map versions, cached and charged at their
measured CPU (:mod:`bench.fleetsim_gate`); global-map rebuilds really run, at a sample
(:mod:`bench.fleetsim_core`).  What every agent would compute alike is computed once and
charged to each at its measured CPU (a payload's decode), and each peer's map is held once
for all agents (:mod:`bench.fleetsim_shared`).  Above 16 robots the replay slows by
17 / (N + 1), so that each robot's segment lasts as many simulated seconds as at 16 robots
(``--no-slowdown``: not).
Each agent has a computer of its own unless ``--cores`` makes them share that many cores, as
:mod:`bench.fleet`'s agents share one machine (``--cores 2 --tag validation`` at 8 and 16);
a smaller number, a fraction too, stands for a machine other jobs load (``--cores 0.5``: the
fleet gets half a core).

Per N: searches, gated searches and checks per epoch, messages and bytes received per robot,
global-map rebuild CPU, agreement time after the last update, bytes of grids held per agent,
CPU per agent per epoch relative to 16 robots, and that CPU by term (searches, checks, gate,
rebuilds, the core's own work, the host's).  At 8 and 16 robots the counts stand beside
:mod:`bench.fleet`'s, run by run, with their mean and spread (``--real FILE ...``: result
files of ``bench.fleet --robots 8 16 --out DIR``; default ``bench/results/fleet.json``).

Run: ``python3 -m bench fleetsim [--robots 16 32 64 128] [--quick] [--cores C] [--tag T]
[--exact-poses] [--real FILE ...]``;
writes ``fleetsim.json``, ``fleetsim.md`` and ``fleetsim.png`` (``fleetsim-T.*`` with a tag)
under ``--out`` (default ``bench/results``); progress on stderr.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from agent.scenario import LOG
from bench.fleet_accuracy import OneLineParser
from bench.fleetsim_core import Meter, Rebuilds, SimClock
from bench.fleetsim_fleet import Churn, Scenario, SimFleet
from bench.fleetsim_gate import GateCache
from bench.fleetsim_merges import load_outcomes
from bench.fleetsim_net import NetParams, Partition
from bench.fleetsim_report import load_real_runs, summarise, write_results

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "bench" / "results"
CACHE = ROOT / "bench" / "cache"
#: Robots whose replay speed is the one given; more robots replay slower (module docstring).
REFERENCE_ROBOTS = 16


def _positive(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be a number, got {text!r}") from None
    if not value > 0:
        raise argparse.ArgumentTypeError(f"must be > 0, got {text}")
    return value


def _robots(text: str) -> int:
    if not text.isdigit() or not 2 <= int(text) <= 256:
        raise argparse.ArgumentTypeError(f"robots must be in 2..256, got {text!r}")
    return int(text)


def _churn(text: str) -> Churn:
    """``ROBOT:LEAVE[:BACK]``."""
    parts = text.split(":")
    if len(parts) not in (2, 3) or not parts[0]:
        raise argparse.ArgumentTypeError(f"churn must be ROBOT:LEAVE[:BACK], got {text!r}")
    try:
        times = [float(p) for p in parts[1:]]
    except ValueError:
        raise argparse.ArgumentTypeError(f"churn times must be seconds, got {text!r}") from None
    if times[0] < 0 or (len(times) == 2 and times[1] <= times[0]):
        raise argparse.ArgumentTypeError(f"churn needs 0 <= LEAVE < BACK, got {text!r}")
    return Churn(parts[0], *times)


def parser() -> argparse.ArgumentParser:
    first = __doc__.split("\n")[0]
    ap = OneLineParser(prog="python3 -m bench fleetsim", description=first, error_prefix="fleetsim")
    ap.add_argument("--robots", type=_robots, nargs="+", default=[16, 32, 64, 128])
    ap.add_argument("--quick", action="store_true", help="rarer worker polls (1 s, not 0.2 s)")
    ap.add_argument("--speed", type=_positive, default=100.0, help="replay speed at <= 16 robots")
    ap.add_argument("--no-slowdown", action="store_true", help="same speed at every N")
    ap.add_argument("--latency", type=float, default=0.002, help="one-way latency (s)")
    ap.add_argument("--jitter", type=float, default=0.002, help="uniform extra latency (s)")
    ap.add_argument("--loss", type=float, default=0.0, help="probability a message is lost")
    ap.add_argument("--bandwidth", type=_positive, default=12.5e6, help="bytes/s per robot link")
    ap.add_argument(
        "--partition", type=float, nargs=2, action="append", default=[], metavar=("START", "END"),
        help="split the fleet in two halves (by robot number) from START to END s",
    )  # fmt: skip
    ap.add_argument("--churn", type=_churn, action="append", default=[], metavar="R:LEAVE[:BACK]")
    ap.add_argument(
        "--cores",
        type=_positive,
        help="agents share this many cores, or this share of one (default: a computer each)",
    )
    ap.add_argument("--limit", type=_positive, default=900.0, help="simulated seconds at most")
    ap.add_argument("--log", type=Path, default=LOG, help="CARMEN log the robots replay")
    ap.add_argument("--cache", type=Path, default=CACHE, help="where the outcome cache lives")
    ap.add_argument("--out", type=Path, default=RESULTS, help="where the results go")
    ap.add_argument("--tag", help="results named fleetsim-TAG.* instead of fleetsim.*")
    ap.add_argument(
        "--exact-poses", action="store_true",
        help="registrations land on the true pose (the real pose errors left out)",
    )  # fmt: skip
    ap.add_argument(
        "--real", type=Path, nargs="+", default=[RESULTS / "fleet.json"], metavar="FILE",
        help="bench.fleet result files (JSON) to set the counts beside",
    )  # fmt: skip
    return ap


def scenario(args: argparse.Namespace, n: int) -> Scenario:
    """The :class:`Scenario` of ``n`` robots under ``args``; ValueError (one line) if bad."""
    names = {f"r{i + 1}" for i in range(n)}
    unknown = sorted({c.robot for c in args.churn} - names)
    if unknown:
        raise ValueError(f"churn names robots not in a fleet of {n}: {', '.join(unknown)}")
    halves = (frozenset(f"r{i + 1}" for i in range(n // 2)), frozenset(names))
    halves = (halves[0], halves[1] - halves[0])
    partitions = tuple(Partition(s, e, halves) for s, e in args.partition)
    if any(not 0 <= p.start < p.end for p in partitions):
        raise ValueError("a partition needs 0 <= START < END")
    net = NetParams(args.latency, args.jitter, args.loss, args.bandwidth, partitions)
    slow = 1.0 if args.no_slowdown else min(1.0, (REFERENCE_ROBOTS + 1) / (n + 1))
    return Scenario(
        n,
        args.log,
        speed=args.speed * slow,
        net=net,
        churn=tuple(args.churn),
        poll=1.0 if args.quick else 0.2,
        limit=args.limit,
        cores=args.cores,
    )


def run_one(sc: Scenario, outcomes, gates: GateCache) -> dict:
    """Simulate ``sc`` and summarise it; the gate verdicts it adds are saved."""
    rebuilds = Rebuilds(Meter(SimClock()))
    t0 = time.perf_counter()
    fleet = SimFleet(sc, outcomes, rebuilds, gates)
    _progress(f"{sc.robots} robots: set up in {time.perf_counter() - t0:.0f} s")
    fleet.run()
    wall = time.perf_counter() - t0
    gates.save()
    row = summarise(fleet, wall)
    _progress(
        f"{sc.robots} robots: simulated {row['sim_s']:.0f} s in {wall:.0f} s, "
        f"agreed={row['agreed']} after {row['agreement_s']} s"
    )
    return row


def _progress(line: str) -> None:
    print(f"[fleetsim] {line}", file=sys.stderr, flush=True)


def main(argv: list[str] | None = None) -> int:
    args = parser().parse_args(argv)
    try:
        scenarios = [scenario(args, n) for n in args.robots]
        if not args.log.is_file():
            raise ValueError(f"log not found: {args.log}")
        real_runs = load_real_runs(args.real)
        outcomes = load_outcomes(args.cache, args.log)
        if args.exact_poses:
            outcomes = [o.exact() for o in outcomes]
        gates = GateCache.beside(args.cache)
        rows: list[dict] = []
        for sc in scenarios:
            rows.append(run_one(sc, outcomes, gates))
            # written after each N: a run stopped at a large N keeps the smaller ones
            write_results(rows, args, args.out, real_runs)
            _progress(f"results of {[r['robots'] for r in rows]} robots in {args.out}")
    except ValueError as exc:
        print(f"fleetsim: {str(exc).splitlines()[0]}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
