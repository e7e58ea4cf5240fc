"""Fleet benchmark: N agents on this machine, peer to peer, replaying a laser log split among them.

For each N (default 2, 4, 8) the agents replay overlapping segments of one CARMEN log (as
``pgvd demo``: :mod:`agent.scenario`, its gaps cut short by :func:`agent.sources.compress_gaps`)
in random frames, and we measure:

- agreement: seconds from the last map update of any source to the moment every agent
  holds the same settled global map (status files polled every :func:`poll_period` s);
- messages and bytes per robot: bytes sent and received, messages received (agent counters);
- CPU per agent: user+system seconds from /proc over the run, and as % of one core;
- RSS per agent: peak resident memory (VmHWM) from /proc; it counts every page mapped:
  shared libraries and, with ``--shm on``, Zenoh's shared-memory pools (16 MB per peer on
  one host, mapped by all agents), so the private memory (USS: private pages, from
  ``smaps_rollup``, largest sample) is reported beside it;
- registrations per agent and their mean time (the unit of work being shared);
- full searches and checks of predicted transforms (verify before you search,
  :mod:`agent.worker`), fleet-wide, and per fleet epoch: divided by the mean number of
  registration epochs the robots went through (each robot's map starts a new epoch when it
  changed enough, and every pair of it must be decided again), and that per robot.

Run: ``python3 -m bench fleet [--robots 2 4 8] [--log LOG ...] [--speed 100] [--shm off|on]
[--timeout S]``.  Without ``--log`` the agents replay the bundled Intel log and the run writes
``bench/results/fleet.md`` (and ``fleet.json``); each ``--log`` writes ``fleet-log-NAME.md``
(and ``.json``), NAME the log's name (``freiburg-079``), and then ``fleet-logs.md``: one
table of every ``fleet-log-*.json`` in the results.  A log that cannot give every robot a
map is refused in one line (exit 2) before any agent starts.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from agent.launcher import LocalFleet, agreement, sources_done
from agent.scenario import LOG, random_frames, segments
from bench.fleet_accuracy import BenchError, Building, OneLineParser, check_building
from bench.workdirs import add_keep_argument, check_keep, fleet_dir

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "bench" / "results"
TICK = os.sysconf("SC_CLK_TCK")
#: Seconds between two reads of every agent's status, up to 8 agents.
POLL_S = 0.1


def poll_period(n: int) -> float:
    """Seconds between two polls of a fleet of ``n`` agents.

    Each poll parses every agent's status (which lists every link it holds, O(N^2) in all)
    and reads /proc three times per agent: at a fixed 0.1 s the bench itself would take a
    large share of 2 cores at 32 agents, and slow the fleet it measures.  The period grows
    with N past 8 agents, so the poll's cost stays about that of 8 agents at 0.1 s, and the
    error it adds to the agreement time stays a small fraction of that time.
    """
    return POLL_S * max(1.0, n / 8)


def default_timeout(n: int) -> float:
    """Seconds a fleet of ``n`` agents gets to agree: 360 s at 8, 1080 s at 32.

    Generous: on a machine other jobs share, 32 agents took nearly 600 s from launch to
    agreement; only a fleet that stalled reaches the timeout.
    """
    return 120.0 + 30.0 * n


def proc_sample(pid: int) -> tuple[float, int, int] | None:
    """(CPU seconds user+system, peak RSS bytes, private bytes now) of a live process."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        cpu = (int(fields[11]) + int(fields[12])) / TICK
        status = Path(f"/proc/{pid}/status").read_text().splitlines()
        hwm = next(int(line.split()[1]) * 1024 for line in status if line.startswith("VmHWM:"))
        rollup = Path(f"/proc/{pid}/smaps_rollup").read_text().splitlines()
        private = sum(int(line.split()[1]) * 1024 for line in rollup if line.startswith("Private_"))
        return cpu, hwm, private
    except (OSError, StopIteration, IndexError, ValueError):
        return None


def launch(fleet: LocalFleet, n: int, building: Building) -> None:
    """Start ``n`` agents, each replaying its segment of ``building``'s log in its own frame."""
    for i, (seg, frame) in enumerate(zip(segments(n), random_frames(n, 7), strict=True)):
        fleet.add(
            f"r{i + 1}",
            building.source(seg),
            ["--frame=" + ",".join(f"{v:.4f}" for v in frame)],
        )


def watch(
    fleet: LocalFleet, timeout: float, period: float, workdir: Path
) -> tuple[float | None, dict[str, tuple[float, int, int]]]:
    """Poll the fleet until it agrees on every source's final map, or ``timeout`` s.

    Returns
    -------
    (agreed_at, samples)
        The wall time of agreement (None on timeout) and, per robot, its last CPU seconds,
        peak RSS and largest private memory seen.

    Raises
    ------
    RuntimeError
        When an agent died; the message ends with the end of its log.
    """
    samples: dict[str, tuple[float, int, int]] = {}
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        for robot, agent in fleet.agents.items():
            s = proc_sample(agent.proc.pid) if agent.proc else None
            if s is not None:
                peak_private = max(s[2], samples.get(robot, (0, 0, 0))[2])
                samples[robot] = (s[0], s[1], peak_private)
        dead = [r for r, a in fleet.agents.items() if not a.alive()]
        if dead:
            log = (workdir / dead[0] / "agent.log").read_text()[-2000:]
            raise RuntimeError(f"agents {dead} died; {dead[0]}'s log ends:\n{log}")
        st = fleet.statuses()
        final = {r: s["own_version"] for r, s in st.items() if s}
        if sources_done(st) and agreement(st, final):
            return time.time(), samples
        time.sleep(period)
    return None, samples


def run_fleet(
    building: Building,
    n: int,
    speed: float,
    timeout: float,
    workdir: Path,
    shm: str = "off",
    verbose: bool = False,
) -> dict:
    """One fleet of ``n`` agents on ``building``'s log until agreement; one row of results.

    ``verbose`` runs the agents with ``--verbose``: their logs then tell every map received
    and every registration's timings, for a fleet kept to be looked into (``--keep``).
    """
    load_before = os.getloadavg()[0]
    t0, bench_cpu0 = time.time(), time.process_time()
    period = poll_period(n)
    common = ["--speed", str(speed), "--shm", shm] + (["--verbose"] if verbose else [])
    with LocalFleet(f"bench{n}", workdir, common) as fleet:
        launch(fleet, n, building)
        agreed_at, samples = watch(fleet, timeout, period, workdir)
        st = {r: s for r, s in fleet.statuses().items() if s}
    wall = time.time() - t0
    row = {"log": building.name, "robots": n, "agreed": agreed_at is not None}
    row |= agreement_numbers(st, agreed_at)
    row |= disagreement_numbers(st)
    row |= traffic_numbers(st)
    row |= process_numbers(samples, wall)
    row |= work_numbers(st, n)
    row |= {
        "wall_s": round(wall, 1),
        "largest_component": max(
            (len(c["members"]) for s in st.values() for c in s["components"]), default=0
        ),
        "poll_s": round(period, 3),
        # the bench's own share of the machine: polling must not be what slows the fleet
        "bench_cpu_pct": round(100 * (time.process_time() - bench_cpu0) / wall, 1),
        # Other processes share this machine: the 1-min load before and after the run.
        "load_before_after": [round(load_before, 1), round(os.getloadavg()[0], 1)],
    }
    return row


def agreement_numbers(st: dict[str, dict], agreed_at: float | None) -> dict:
    """Agreement after the last update, in seconds and in mean registrations."""
    last_update = max((s.get("last_update") or 0 for s in st.values()), default=0)
    merges = [s["merges"] for s in st.values()]
    merge_s = sum(s["merge_seconds"] for s in st.values()) / max(sum(merges), 1)
    after = None if agreed_at is None else agreed_at - last_update
    return {
        "agreement_s": None if after is None else round(after, 2),
        "merges_per_agent": round(float(np.mean(merges)), 1) if merges else 0.0,
        "merge_s_mean": round(merge_s, 3),
        # Agreement in units of one registration measured in the same run: the critical
        # path, which the machine's load (other jobs) does not scale away.
        "agreement_in_registrations": None
        if after is None
        else round(after / max(merge_s, 1e-3), 1),
    }


def disagreement_numbers(st: dict[str, dict]) -> dict:
    """Why a fleet had not agreed when the bench stopped watching it (all agreed: 1 and 0).

    ``distinct_global_maps``: how many different global maps the agents held;
    ``final_maps_missing``: (agent, robot) pairs where the agent did not hold the robot's
    final map (its own last version), a map that never reached it.
    """
    final = {r: s["own_version"] for r, s in st.items()}
    missing = sum(
        1
        for s in st.values()
        for robot, version in final.items()
        if (s["robots"].get(robot, {}).get("version") or 0) < (version or 0)
    )
    digests = {(s.get("global") or {}).get("digest") for s in st.values()}
    return {"distinct_global_maps": len(digests), "final_maps_missing": missing}


def traffic_numbers(st: dict[str, dict]) -> dict:
    """Bytes sent and received and messages received, per robot (mean over agents)."""

    def mean(values: list[int]) -> int:
        return int(np.mean(values)) if values else 0

    return {
        "bytes_sent_per_robot": mean([s["bytes_sent"] for s in st.values()]),
        "bytes_received_per_robot": mean([s["bytes_received"] for s in st.values()]),
        "messages_received_per_robot": mean(
            [s["counts"].get("messages_received", 0) for s in st.values()]
        ),
    }


def process_numbers(samples: dict[str, tuple[float, int, int]], wall: float) -> dict:
    """CPU, peak RSS and peak private memory per agent, mean and max, from /proc samples."""
    cpu = np.array([s[0] for s in samples.values()] or [0.0])
    rss = np.array([s[1] for s in samples.values()] or [0]) / 2**20
    uss = np.array([s[2] for s in samples.values()] or [0]) / 2**20
    return {
        "cpu_s_per_agent": round(float(cpu.mean()), 2),
        "cpu_s_max_agent": round(float(cpu.max()), 2),
        "cpu_pct_per_agent": round(100 * float(cpu.mean()) / wall, 1),
        "rss_mb_per_agent": round(float(rss.mean()), 1),
        "rss_mb_max_agent": round(float(rss.max()), 1),
        "uss_mb_per_agent": round(float(uss.mean()), 1),
        "uss_mb_max_agent": round(float(uss.max()), 1),
    }


def work_numbers(st: dict[str, dict], n: int) -> dict:
    """Full searches and checks, fleet-wide, per fleet epoch, and per epoch per robot."""
    counts = [s["counts"] for s in st.values()]
    total = {k: sum(c.get(k, 0) for c in counts) for k in ("searches", "checks", "epochs")}
    epochs = max(total["epochs"] / max(len(counts), 1), 1.0)
    return {
        "searches": total["searches"],
        "checks": total["checks"],
        "epochs_per_robot": round(total["epochs"] / max(len(counts), 1), 1),
        "searches_per_epoch": round(total["searches"] / epochs, 1),
        "checks_per_epoch": round(total["checks"] / epochs, 1),
        "searches_per_epoch_per_robot": round(total["searches"] / epochs / n, 2),
        "checks_per_epoch_per_robot": round(total["checks"] / epochs / n, 2),
    }


def agreed(row: dict) -> str:
    """The agreed cell: yes, or NO with how many global maps and maps missing there were."""
    if row["agreed"]:
        return "yes"
    return (
        f"NO: {row['distinct_global_maps']} global maps, "
        f"{row['final_maps_missing']} final maps missing"
    )


def table(rows: list[dict]) -> str:
    """The full table of one log's runs, one row per fleet size."""
    head = (
        "| agents | agreed | agreement after last update (s) | sent / robot (kB) "
        "| received / robot (kB) | messages received / robot "
        "| CPU / agent (s, mean / max) | CPU / agent (% core) "
        "| peak RSS / agent (MB, mean / max) | private (USS) / agent (MB, mean / max) "
        "| registrations / agent | mean registration (s) "
        "| agreement / mean registration | full searches / checks (all) "
        "| epochs / robot | full searches / checks per epoch "
        "| full searches / checks per epoch per robot "
        "| poll (s) / bench CPU (% core) | machine load before / after |"
    )
    lines = [head, "|" + "---|" * 19]
    for r in rows:
        lines.append(
            f"| {r['robots']} | {agreed(r)} | {r['agreement_s']} "
            f"| {r['bytes_sent_per_robot'] / 1000:.0f} "
            f"| {r['bytes_received_per_robot'] / 1000:.0f} | {r['messages_received_per_robot']} "
            f"| {r['cpu_s_per_agent']} / {r['cpu_s_max_agent']} | {r['cpu_pct_per_agent']} "
            f"| {r['rss_mb_per_agent']} / {r['rss_mb_max_agent']} "
            f"| {r['uss_mb_per_agent']} / {r['uss_mb_max_agent']} | {r['merges_per_agent']} "
            f"| {r['merge_s_mean']} | {r['agreement_in_registrations']} "
            f"| {r['searches']} / {r['checks']} | {r['epochs_per_robot']} "
            f"| {r['searches_per_epoch']} / {r['checks_per_epoch']} "
            f"| {r['searches_per_epoch_per_robot']} / {r['checks_per_epoch_per_robot']} "
            f"| {r['poll_s']} / {r['bench_cpu_pct']} "
            f"| {r['load_before_after'][0]} / {r['load_before_after'][1]} |"
        )
    return "\n".join(lines)


def combined_table(rows: list[dict]) -> str:
    """The headline numbers of every log's runs in one table, one row per (log, N)."""
    head = (
        "| log | agents | agreed | agreement after last update (s) "
        "| full searches / checks per epoch per robot | messages received / robot "
        "| sent / received per robot (kB) | peak RSS / agent (MB, mean / max) "
        "| machine load before / after |"
    )
    lines = [head, "|" + "---|" * 9]
    for r in sorted(rows, key=lambda r: (r["log"], r["robots"])):
        lines.append(
            f"| {r['log']} | {r['robots']} | {agreed(r)} "
            f"| {r['agreement_s']} "
            f"| {r['searches_per_epoch_per_robot']} / {r['checks_per_epoch_per_robot']} "
            f"| {r['messages_received_per_robot']} "
            f"| {r['bytes_sent_per_robot'] / 1000:.0f} / "
            f"{r['bytes_received_per_robot'] / 1000:.0f} "
            f"| {r['rss_mb_per_agent']} / {r['rss_mb_max_agent']} "
            f"| {r['load_before_after'][0]} / {r['load_before_after'][1]} |"
        )
    return "\n".join(lines)


EXPLAINED = (
    "Agreement: seconds from the last own-map update of any agent to every agent holding the "
    "same settled global map (polled every `poll` s: 0.1 s up to 8 agents, longer beyond so "
    "that polling costs the machine about the same; the bench's own CPU is shown).  Messages "
    "received count the tiles, manifests and links an agent's subscribers took from its peers "
    "(replies to its fetches count in bytes only).  CPU and peak RSS are read from /proc for "
    "each agent process over the whole run; RSS counts shared libraries and, with shared "
    "memory on, Zenoh's pools (16 MB per peer on this host, mapped by every agent), USS only "
    "the agent's private pages (largest sample).  The machine load is the 1-minute load "
    "average before and after each run: other jobs shared the 2 cores, and registration time "
    "(hence agreement time) grows with it.  Full searches are the merge's whole pipeline "
    "(Fig. 1); checks verify the transform the accepted links predict (pgvd.verify).  Per "
    "epoch: fleet-wide counts over the mean number of registration epochs per robot; a pair "
    "needs a decision once per epoch of either robot.\n"
)


def markdown(rows: list[dict], command: str, building: Building, shm: str) -> str:
    """The result file of one log's runs."""
    stamp = time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())
    what = "the Intel log" if building.path == LOG else f"the {building.name} log"
    return (
        f"# Fleet benchmark{'' if building.path == LOG else f': {building.name} log'}\n\n"
        f"`{command}` on {os.cpu_count()} cores, {stamp}.\n"
        f"Agents replay overlapping segments of {what} (as `pgvd demo`), peer to peer on "
        f"localhost, no router, Zenoh shared memory {shm} (`--shm`).\n\n"
        + table(rows)
        + "\n\n"
        + EXPLAINED
    )


def write_results(rows: list[dict], command: str, building: Building, shm: str, out: Path) -> str:
    """Write one log's results (and, for a ``--log``, the table of all logs); its Markdown."""
    name = "fleet" if building.path == LOG else f"fleet-log-{building.name}"
    md = markdown(rows, command, building, shm)
    out.mkdir(parents=True, exist_ok=True)
    (out / f"{name}.md").write_text(md)
    (out / f"{name}.json").write_text(json.dumps(rows, indent=1))
    if building.path != LOG:
        every = [
            row for p in sorted(out.glob("fleet-log-*.json")) for row in json.loads(p.read_text())
        ]
        (out / "fleet-logs.md").write_text(
            "# Fleet benchmark on every log\n\n"
            f"`python3 -m bench fleet --log LOG ...`: the rows of every `fleet-log-*.json` "
            f"in the results, latest {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}.\n\n"
            + combined_table(every)
            + "\n\nThe full rows, with CPU, private memory and registrations, are in each "
            "log's `fleet-log-NAME.md`.\n"
        )
    return md


def shown_path(path: Path) -> str:
    """``path`` as the results show it: relative to the project when it can be, so that a
    result names no directory of the machine it ran on."""
    return os.path.relpath(path.resolve(), ROOT) if path.is_absolute() else str(path)


def parse_args(argv: Sequence[str]) -> argparse.Namespace:
    ap = OneLineParser(prog="python3 -m bench fleet", description=__doc__.splitlines()[0])
    ap.add_argument("--robots", type=int, nargs="+", default=[2, 4, 8])
    ap.add_argument(
        "--log",
        type=Path,
        nargs="+",
        help="CARMEN laser logs (FLASER lines, .log or .log.gz), each split among the robots "
        "in its own runs (default: the bundled Intel log)",
    )
    ap.add_argument("--speed", type=float, default=100.0, help="log replay speed x real time")
    ap.add_argument(
        "--timeout", type=float, help="s a fleet gets to agree (default 120 + 30 per agent)"
    )
    ap.add_argument("--shm", choices=("on", "off"), default="off", help="Zenoh shared memory")
    ap.add_argument("--out", type=Path, default=RESULTS, help="directory of the results")
    add_keep_argument(ap, "LOG-N")
    args = ap.parse_args(argv)
    if min(args.robots) < 2:
        ap.error(f"--robots must be at least 2, got {args.robots}")
    if args.speed <= 0 or (args.timeout is not None and args.timeout <= 0):
        ap.error("--speed and --timeout must be > 0")
    check_keep(ap, args.keep)
    return args


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    args = parse_args(argv)
    buildings = [Building("log", p) for p in args.log or [LOG]]
    try:
        for building in buildings:
            check_building(building, max(args.robots))
    except BenchError as exc:
        print(f"python3 -m bench fleet: --log: {exc}", file=sys.stderr)
        return 2
    for building in buildings:
        rows = []
        for n in args.robots:
            with fleet_dir(args.keep, f"{building.name}-{n}") as workdir:
                print(f"fleet of {n} agents on {building.name} in {workdir} ...", flush=True)
                timeout = args.timeout or default_timeout(n)
                keep = args.keep is not None
                row = run_fleet(building, n, args.speed, timeout, workdir, args.shm, keep)
                print(json.dumps(row), flush=True)
                rows.append(row)
        command = " ".join(
            ["python3 -m bench fleet", "--robots", *map(str, args.robots)]
            + ([] if building.path == LOG else ["--log", shown_path(building.path)])
            + ["--speed", f"{args.speed:g}", "--shm", args.shm]
        )
        print(write_results(rows, command, building, args.shm, args.out))
    return 0


if __name__ == "__main__":
    sys.exit(main())
