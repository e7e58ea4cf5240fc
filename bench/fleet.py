"""Fleet benchmark: N agents on this machine, peer to peer, replaying the Intel log.

For each N (default 2, 4, 8) the agents replay overlapping segments (as ``pgvd demo``)
in random frames, and we measure:

- agreement: seconds from the last map update of any source to the moment every agent
  holds the same settled global map (status files polled every 0.1 s);
- bytes sent and received per robot (agent counters);
- CPU per agent: user+system seconds from /proc over the run, and as % of one core;
- RSS per agent: peak resident memory (VmHWM) from /proc; it counts every page mapped:
  shared libraries and, with ``--shm on``, Zenoh's shared-memory pools (16 MB per peer on
  one host, mapped by all agents), so the private memory (USS: private pages, from
  ``smaps_rollup``, largest sample) is reported beside it;
- registrations per agent and their mean time (the unit of work being shared);
- full searches and checks of predicted transforms (verify before you search,
  :mod:`agent.worker`), fleet-wide, and per fleet epoch: divided by the mean number of
  registration epochs the robots went through (each robot's map starts a new epoch when it
  changed enough, and every pair of it must be decided again).

Run: ``python3 -m bench fleet [--robots 2 4 8] [--speed 100] [--shm off|on]``; writes
``bench/results/fleet.md`` (and ``fleet.json``).
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import time
from pathlib import Path

import numpy as np

from agent.launcher import LocalFleet, agreement, sources_done
from agent.scenario import LOG, random_frames, segments

RESULTS = Path(__file__).resolve().parent / "results"
TICK = os.sysconf("SC_CLK_TCK")


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


def run_fleet(n: int, speed: float, timeout: float, workdir: Path, shm: str = "off") -> dict:
    """One fleet of ``n`` agents until agreement; the measurements of :mod:`bench.fleet`."""
    samples: dict[str, tuple[float, int, int]] = {}
    load_before = os.getloadavg()[0]
    t0 = time.time()
    agreed_at = None
    with LocalFleet(f"bench{n}", workdir, ["--speed", str(speed), "--shm", shm]) as fleet:
        for i, (seg, frame) in enumerate(zip(segments(n), random_frames(n, 7), strict=True)):
            fleet.add(
                f"r{i + 1}",
                f"carmen:{LOG}@{seg[0]}-{seg[1]}",
                ["--frame=" + ",".join(f"{v:.4f}" for v in frame)],
            )
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
                agreed_at = time.time()
                break
            time.sleep(0.1)
        st = fleet.statuses()
    wall = time.time() - t0
    last_update = max((s.get("last_update") or 0 for s in st.values() if s), default=0)
    merges = [s["merges"] for s in st.values() if s]
    counts = [s["counts"] for s in st.values() if s]
    total = {k: sum(c.get(k, 0) for c in counts) for k in ("searches", "checks", "epochs")}
    epochs = total["epochs"] / max(len(counts), 1)
    merge_s = sum(s["merge_seconds"] for s in st.values() if s)
    sent = [s["bytes_sent"] for s in st.values() if s]
    recv = [s["bytes_received"] for s in st.values() if s]
    cpu = [samples[r][0] for r in samples]
    rss = [samples[r][1] for r in samples]
    uss = [samples[r][2] for r in samples]
    comps = {len(c["members"]) for s in st.values() if s for c in s["components"]}
    return {
        "robots": n,
        "agreed": agreed_at is not None,
        "agreement_s": None if agreed_at is None else round(agreed_at - last_update, 2),
        "wall_s": round(wall, 1),
        "largest_component": max(comps) if comps else 0,
        "bytes_sent_per_robot": int(np.mean(sent)),
        "bytes_received_per_robot": int(np.mean(recv)),
        "cpu_s_per_agent": round(float(np.mean(cpu)), 2),
        "cpu_s_max_agent": round(float(np.max(cpu)), 2),
        "cpu_pct_per_agent": round(100 * float(np.mean(cpu)) / wall, 1),
        "rss_mb_per_agent": round(float(np.mean(rss)) / 2**20, 1),
        "rss_mb_max_agent": round(float(np.max(rss)) / 2**20, 1),
        "uss_mb_per_agent": round(float(np.mean(uss)) / 2**20, 1),
        "uss_mb_max_agent": round(float(np.max(uss)) / 2**20, 1),
        "merges_per_agent": round(float(np.mean(merges)), 1),
        "merge_s_mean": round(merge_s / max(sum(merges), 1), 3),
        "searches": total["searches"],
        "checks": total["checks"],
        "epochs_per_robot": round(epochs, 1),
        "searches_per_epoch": round(total["searches"] / max(epochs, 1.0), 1),
        "checks_per_epoch": round(total["checks"] / max(epochs, 1.0), 1),
        # Agreement in units of one registration measured in the same run: the critical
        # path, which the machine's load (other jobs) does not scale away.
        "agreement_in_registrations": None
        if agreed_at is None
        else round((agreed_at - last_update) / max(merge_s / max(sum(merges), 1), 1e-3), 1),
        # Other processes share this machine: the 1-min load before and after the run.
        "load_before_after": [round(load_before, 1), round(os.getloadavg()[0], 1)],
    }


def table(rows: list[dict]) -> str:
    head = (
        "| agents | agreed | agreement after last update (s) | sent / robot (kB) "
        "| received / robot (kB) | CPU / agent (s, mean / max) | CPU / agent (% core) "
        "| peak RSS / agent (MB, mean / max) | private (USS) / agent (MB, mean / max) "
        "| registrations / agent | mean registration (s) "
        "| agreement / mean registration | full searches / checks (all) "
        "| epochs / robot | full searches / checks per epoch | searches per epoch / N "
        "| machine load before / after |"
    )
    lines = [head, "|" + "---|" * 17]
    for r in rows:
        lines.append(
            f"| {r['robots']} | {'yes' if r['agreed'] else 'NO'} | {r['agreement_s']} "
            f"| {r['bytes_sent_per_robot'] / 1000:.0f} "
            f"| {r['bytes_received_per_robot'] / 1000:.0f} "
            f"| {r['cpu_s_per_agent']} / {r['cpu_s_max_agent']} | {r['cpu_pct_per_agent']} "
            f"| {r['rss_mb_per_agent']} / {r['rss_mb_max_agent']} "
            f"| {r['uss_mb_per_agent']} / {r['uss_mb_max_agent']} | {r['merges_per_agent']} "
            f"| {r['merge_s_mean']} | {r['agreement_in_registrations']} "
            f"| {r['searches']} / {r['checks']} | {r['epochs_per_robot']} "
            f"| {r['searches_per_epoch']} / {r['checks_per_epoch']} "
            f"| {r['searches_per_epoch'] / r['robots']:.2f} "
            f"| {r['load_before_after'][0]} / {r['load_before_after'][1]} |"
        )
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--robots", type=int, nargs="+", default=[2, 4, 8])
    ap.add_argument("--speed", type=float, default=100.0)
    ap.add_argument("--timeout", type=float, default=240.0)
    ap.add_argument("--shm", choices=("on", "off"), default="off", help="Zenoh shared memory")
    args = ap.parse_args()
    rows = []
    for n in args.robots:
        with tempfile.TemporaryDirectory(prefix=f"pgvd-fleet{n}-") as tmp:
            print(f"fleet of {n} agents ...", flush=True)
            row = run_fleet(n, args.speed, args.timeout, Path(tmp), args.shm)
            print(json.dumps(row), flush=True)
            rows.append(row)
    RESULTS.mkdir(parents=True, exist_ok=True)
    stamp = time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())
    md = (
        "# Fleet benchmark\n\n"
        f"`python3 -m bench fleet --robots {' '.join(map(str, args.robots))} "
        f"--speed {args.speed:g} --shm {args.shm}` on {os.cpu_count()} cores, {stamp}.\n"
        "Agents replay overlapping segments of the Intel log (as `pgvd demo`), peer to peer on "
        f"localhost, no router, Zenoh shared memory {args.shm} (`--shm`).\n\n"
        + table(rows)
        + "\n\nAgreement: seconds from the last own-map update of any agent to every agent "
        "holding the same settled global map (polled every 0.1 s).  CPU and peak RSS are "
        "read from /proc for each agent process over the whole run; RSS counts shared "
        "libraries and, with shared memory on, Zenoh's pools (16 MB per peer on this host, "
        "mapped by every agent), USS only the agent's private pages (largest sample).  "
        "The machine load is the "
        "1-minute load average before and after each run: other jobs shared the 2 cores, and "
        "registration time (hence agreement time) grows with it.  Full searches are the merge's "
        "whole pipeline (Fig. 1); checks verify the transform the accepted links predict "
        "(pgvd.verify).  Per epoch: fleet-wide counts over the mean number of registration "
        "epochs per robot; a pair needs a decision once per epoch of either robot.\n"
    )
    (RESULTS / "fleet.md").write_text(md)
    (RESULTS / "fleet.json").write_text(json.dumps(rows, indent=1))
    print(md)


if __name__ == "__main__":
    main()
