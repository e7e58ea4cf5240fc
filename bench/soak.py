"""Soak: 8 agents with continuous map updates for 10 minutes; memory, CPU, drops, lag.

Agents run peer to peer on localhost. Their sources (``--sources``) keep changing for the whole
run: ``cycle`` rewrites fixed-size map files (the memory check), ``replay`` replays overlapping
segments of the bundled Intel log slowly (realistic, but the maps grow as robots explore).
Every 0.5 s the agents' status files are read; every 5 s their RSS and CPU from ``/proc``.

Reported:

- RSS and CPU of every agent over time (``soak.png``);
- memory growth after warm-up: mean RSS over the last minute against the mean over the
  minute after warm-up (the first quarter of the run); the target is under 10 %. The maps
  themselves grow while the robots explore, so some growth is the data, not a leak;
- messages dropped, by reason, summed over agents (a clean run drops none);
- update-to-agreement lag: for each new version of a robot's map, the seconds from its
  publication (the owner's ``last_update``) to the first moment every agent is settled on
  the same global map and holds that version or a newer one. With updates that never stop,
  full agreement happens only in lulls, so the propagation lag is reported too: the seconds
  until every agent holds that version or a newer one (whatever else is still moving).

Run: ``python3 -m bench.soak [--robots 8] [--minutes 10] [--sources cycle|replay]``; writes
``bench/results/soak-<sources>.md``, ``.json`` and ``.png``.
"""

from __future__ import annotations

import argparse
import gzip
import json
import os
import tempfile
import time
from pathlib import Path

import numpy as np

from agent.launcher import LocalFleet, agreement
from agent.scenario import LOG, random_frames, segments
from pgvd.grid import Grid

RESULTS = Path(__file__).resolve().parent / "results"
INTEL_MAP = Path(__file__).resolve().parents[2] / "shared" / "maps" / "intel" / "intel.yaml"
TICK = os.sysconf("SC_CLK_TCK")


def log_seconds(path: Path) -> float:
    """Duration of a CARMEN log: last minus first FLASER timestamp."""
    stamps = []
    with gzip.open(path, "rt") as f:
        for line in f:
            if line.startswith("FLASER"):
                stamps.append(float(line.split()[-3]))
    return stamps[-1] - stamps[0]


def proc_sample(pid: int) -> tuple[float, float] | None:
    """(CPU seconds user+system, RSS MB) of a live process, from /proc."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        rss = next(
            int(line.split()[1]) / 1024
            for line in Path(f"/proc/{pid}/status").read_text().splitlines()
            if line.startswith("VmRSS:")
        )
    except (OSError, StopIteration, IndexError, ValueError):
        return None
    return (int(fields[11]) + int(fields[12])) / TICK, rss


class ReplaySources:
    """Overlapping segments of the Intel log, replayed so slowly that they last the whole run.

    The maps grow while the robots explore: memory growth here is partly the data.
    """

    def __init__(self, robots: int, minutes: float) -> None:
        self.segments = segments(robots)
        longest = max(b - a for a, b in self.segments)
        self.speed = longest * log_seconds(LOG) / (minutes * 60)
        self.frames = random_frames(robots, 11)

    def agents(self, workdir: Path) -> list[tuple[str, list[str]]]:
        return [
            (
                f"carmen:{LOG}@{a}-{b}",
                ["--speed", f"{self.speed:.4f}", "--frame=" + ",".join(f"{v:.4f}" for v in f)],
            )
            for (a, b), f in zip(self.segments, self.frames, strict=True)
        ]

    def step(self, elapsed: float) -> None:
        """Nothing to do: the agents replay on their own."""


class CycleSources:
    """Map files an external "SLAM" rewrites every ``period`` s, alternating two versions.

    Robot i follows a fixed crop of the Intel map; every other version a band of its known
    cells is blanked (unknown), so each rewrite is a new version of the same size: continuous
    updates with no data growth, the setting in which memory must stay flat.
    """

    def __init__(self, robots: int, period: float = 10.0) -> None:
        from pgvd.io import read_map

        self.base = read_map(INTEL_MAP)
        self.robots, self.period = robots, period
        self.paths: list[Path] = []
        self.written = [-1] * robots

    def variant(self, i: int, blank: bool) -> Grid:
        h, w = self.base.shape
        side = int(min(h, w) * 0.6)
        y0 = (h - side) * i // max(self.robots - 1, 1)
        x0 = (w - side) * (self.robots - 1 - i) // max(self.robots - 1, 1)
        cells = self.base.logodds[y0 : y0 + side, x0 : x0 + side].copy()
        if blank:
            band = side // 8
            top = side // 2 - band // 2
            cells[top : top + band] = 0.0
        # Origin of the crop in the Intel map's world frame (row 0 is the image top).
        ox = self.base.origin[0] + x0 * self.base.resolution
        oy = self.base.origin[1] + (h - y0 - side) * self.base.resolution
        return Grid(cells, self.base.resolution, (ox, oy, 0.0))

    def agents(self, workdir: Path) -> list[tuple[str, list[str]]]:
        self.paths = [workdir / f"map{i + 1}" / "map.yaml" for i in range(self.robots)]
        for i, path in enumerate(self.paths):
            path.parent.mkdir(parents=True, exist_ok=True)
            self._write(i, 0)
        return [(f"map:{path}", []) for path in self.paths]

    def step(self, elapsed: float) -> None:
        for i in range(self.robots):
            turn = int((elapsed + i * self.period / self.robots) // self.period)
            if turn != self.written[i]:
                self._write(i, turn)

    def _write(self, i: int, turn: int) -> None:
        from pgvd.io import write_map

        write_map(self.paths[i], self.variant(i, blank=turn % 2 == 1))
        self.written[i] = turn


def soak(
    sources: ReplaySources | CycleSources, minutes: float, workdir: Path, settle: float = 90.0
) -> dict:
    """Run the fleet for ``minutes``; the raw time series and events."""
    series: dict[str, list[tuple[float, float, float]]] = {}
    published: dict[tuple[str, int], float] = {}
    agreed: list[tuple[float, dict[str, int]]] = []
    held_by_all: list[tuple[float, dict[str, int]]] = []
    drops: dict[str, int] = {}
    with LocalFleet("soak", workdir / "fleet") as fleet:
        for i, (source, args) in enumerate(sources.agents(workdir)):
            fleet.add(f"r{i + 1}", source, args)
        t0 = time.time()
        next_sample = next_print = t0
        while time.time() - t0 < minutes * 60:
            now = time.time()
            sources.step(now - t0)
            statuses = fleet.statuses()
            for robot, status in statuses.items():
                if status and status.get("own_version") and status.get("last_update"):
                    published.setdefault((robot, status["own_version"]), status["last_update"])
            if all(statuses.values()):
                held_by_all.append((now, least_held(statuses)))  # type: ignore[arg-type]
            if agreement(statuses):
                held = next(iter(statuses.values()))["robots"]  # type: ignore[index]
                agreed.append((now, {r: v["version"] or 0 for r, v in held.items()}))
            if now >= next_sample:
                for robot, agent in fleet.agents.items():
                    sample = agent.proc and proc_sample(agent.proc.pid)
                    if sample:
                        series.setdefault(robot, []).append((now - t0, *sample))
                next_sample = now + 5
            if now >= next_print:
                dead = [r for r, a in fleet.agents.items() if not a.alive()]
                versions = [(s or {}).get("own_version") for s in statuses.values()]
                print(f"{now - t0:6.0f} s  versions {versions}", flush=True)
                print(f"        agreements {len(agreed)}  dead {dead}", flush=True)
                next_print = now + 30
            time.sleep(0.5)
        # Updates stop here: give the fleet up to ``settle`` s to agree on the last ones.
        deadline = time.time() + settle
        while time.time() < deadline and not agreement(fleet.statuses()):
            time.sleep(0.5)
        statuses = fleet.statuses()
        if agreement(statuses):
            held = next(iter(statuses.values()))["robots"]  # type: ignore[index]
            agreed.append((time.time(), {r: v["version"] or 0 for r, v in held.items()}))
        for status in fleet.statuses().values():
            for reason, n in (status or {}).get("drops", {}).items():
                drops[reason] = drops.get(reason, 0) + n
        dead = [r for r, a in fleet.agents.items() if not a.alive()]
    return {
        "t0": t0,
        "series": series,
        "published": published,
        "agreed": agreed,
        "held_by_all": held_by_all,
        "drops": drops,
        "dead": dead,
    }


def least_held(statuses: dict[str, dict]) -> dict[str, int]:
    """Per robot, the oldest version any agent holds (0 where an agent holds none)."""
    robots = {r for s in statuses.values() for r in s["robots"]}
    return {
        r: min((s["robots"].get(r, {}).get("version") or 0) for s in statuses.values())
        for r in robots
    }


def lags(published: dict[tuple[str, int], float], agreed: list[tuple[float, dict]]) -> list:
    """Seconds from each version's publication to the first agreement that includes it."""
    out = []
    for (robot, version), when in sorted(published.items(), key=lambda kv: kv[1]):
        first = next((t for t, held in agreed if t >= when and held.get(robot, 0) >= version), None)
        if first is not None:
            out.append(first - when)
    return out


def summarise(run: dict, minutes: float) -> dict:
    warm = minutes * 60 / 4
    growth = {}
    for robot, rows in run["series"].items():
        t, _, rss = np.array(rows).T
        after_warm = rss[(t >= warm) & (t < warm + 60)]
        at_warm = after_warm.mean() if after_warm.size else rss[-1]
        tail = rss[t >= t[-1] - 60].mean()
        growth[robot] = float((tail - at_warm) / at_warm * 100)
    cpu = {
        robot: float((rows[-1][1] - rows[0][1]) / max(rows[-1][0] - rows[0][0], 1e-9) * 100)
        for robot, rows in run["series"].items()
    }
    lag = lags(run["published"], run["agreed"])
    spread = lags(run["published"], run["held_by_all"])
    last_update = max(run["published"].values(), default=None)
    final = next((t for t, _ in run["agreed"] if last_update and t >= last_update), None)
    return {
        "robots": len(run["series"]),
        "minutes": minutes,
        "versions_published": len(run["published"]),
        "versions_agreed": len(lag),
        "lag_s": {
            "median": round(float(np.median(lag)), 2) if lag else None,
            "p90": round(float(np.percentile(lag, 90)), 2) if lag else None,
            "max": round(float(max(lag)), 2) if lag else None,
        },
        "last_update_to_agreement_s": None if final is None else round(final - last_update, 2),
        "agreements_polled": len(run["agreed"]),
        "propagation_lag_s": {
            "median": round(float(np.median(spread)), 2) if spread else None,
            "p90": round(float(np.percentile(spread, 90)), 2) if spread else None,
            "max": round(float(max(spread)), 2) if spread else None,
        },
        "rss_growth_after_warmup_pct": {r: round(g, 2) for r, g in sorted(growth.items())},
        "rss_end_mb": {r: round(rows[-1][2], 1) for r, rows in sorted(run["series"].items())},
        "cpu_pct_of_core": {r: round(c, 1) for r, c in sorted(cpu.items())},
        "drops": run["drops"],
        "dead": run["dead"],
    }


def plot(run: dict, summary: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax_rss, ax_cpu, ax_lag) = plt.subplots(3, 1, figsize=(9, 10))
    for robot, rows in sorted(run["series"].items()):
        t, cpu, rss = np.array(rows).T
        ax_rss.plot(t / 60, rss, label=robot)
        ax_cpu.plot(t[1:] / 60, np.diff(cpu) / np.diff(t) * 100, label=robot)
    warm = summary["minutes"] / 4
    for ax in (ax_rss, ax_cpu):
        ax.axvline(warm, color="gray", ls="--", lw=0.8)
        ax.set_xlabel("minutes")
        ax.legend(ncol=4, fontsize=7)
    ax_rss.set_ylabel("RSS (MB)")
    ax_rss.set_title("RSS per agent (dashed: end of warm-up)")
    ax_cpu.set_ylabel("CPU (% of one core)")
    lag = lags(run["published"], run["agreed"])
    ax_lag.hist(lag, bins=30)
    if not lag:
        ax_lag.text(0.5, 0.5, "the fleet never agreed", ha="center", transform=ax_lag.transAxes)
    ax_lag.set_xlabel("seconds from a map update to fleet-wide agreement")
    ax_lag.set_ylabel("updates")
    fig.tight_layout()
    fig.savefig(path, dpi=90)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--robots", type=int, default=8)
    parser.add_argument("--minutes", type=float, default=10.0)
    parser.add_argument(
        "--sources",
        choices=("cycle", "replay"),
        default="cycle",
        help="cycle: map files rewritten every 10 s, same size (memory must stay flat); "
        "replay: the Intel log, maps growing as the robots explore",
    )
    parser.add_argument(
        "--settle", type=float, default=90.0, help="s to wait for agreement after the run"
    )
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args()
    if args.sources == "cycle":
        sources: ReplaySources | CycleSources = CycleSources(args.robots)
    else:
        sources = ReplaySources(args.robots, args.minutes)
    print(f"{args.robots} agents, {args.sources} sources, {args.minutes:g} min", flush=True)
    with tempfile.TemporaryDirectory(prefix="pgvd-soak-") as tmp:
        run = soak(sources, args.minutes, Path(tmp), args.settle)
    summary = summarise(run, args.minutes)
    name = f"soak-{args.sources}"
    args.out.mkdir(parents=True, exist_ok=True)
    raw = {"series": run["series"], "published": [[*k, v] for k, v in run["published"].items()]}
    (args.out / f"{name}.json").write_text(json.dumps({"summary": summary, "raw": raw}))
    plot(run, summary, args.out / f"{name}.png")
    growth = summary["rss_growth_after_warmup_pct"]
    lines = [
        f"# Soak ({args.sources} sources)",
        "",
        f"`python3 -m bench.soak --robots {args.robots} --minutes {args.minutes:g} --sources "
        f"{args.sources} --settle {args.settle:g}` on {os.cpu_count()} cores, "
        f"{time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}.",
        "",
        (sources.__doc__ or "").strip().replace("\n    ", " "),
        "",
        f"- versions published: {summary['versions_published']}, of which reached fleet-wide "
        f"agreement: {summary['versions_agreed']}",
        f"- update-to-agreement lag (s): {summary['lag_s']}; polls that found the whole fleet"
        f" in agreement: {summary['agreements_polled']}",
        f"- last update of the run to agreement: {summary['last_update_to_agreement_s']} s",
        f"- propagation lag, update to held by every agent (s): {summary['propagation_lag_s']}",
        f"- RSS growth after warm-up (%): {growth} (max {max(growth.values()):.1f} %, target < 10)",
        f"- RSS at the end (MB): {summary['rss_end_mb']}",
        f"- CPU (% of one core): {summary['cpu_pct_of_core']}",
        f"- messages dropped: {summary['drops'] or 'none'}",
        f"- agents that died: {summary['dead'] or 'none'}",
        "",
        f"![soak]({name}.png)",
    ]
    (args.out / f"{name}.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
