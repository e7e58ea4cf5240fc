"""Soak: 8 agents with continuous map updates for 10 minutes; memory, CPU, drops, lag.

Agents run peer to peer on localhost. Their sources (``--sources``) keep changing for the whole
run: ``cycle`` rewrites fixed-size map files (the memory check), ``replay`` replays overlapping
segments of the bundled Intel log slowly (realistic, but the maps grow as robots explore).
Every 0.5 s the agents' status files are read; every 5 s their RSS and CPU from ``/proc``.

Reported:

- RSS and CPU of every agent over time (``soak.png``);
- memory growth after warm-up: mean RSS over the last minute against the mean over the
  minute after warm-up (the first quarter of the run, or of the agent's time in it for a
  late joiner, :func:`rss_growth`); the target is under 10 %. The maps
  themselves grow while the robots explore, so some growth is the data, not a leak;
- messages dropped, by reason, summed over agents (a clean run drops none);
- update-to-agreement lag: for each new version of a robot's map, the seconds from its
  publication (the owner's ``last_update``) to the first moment every agent is settled on
  the same global map and holds that version or a newer one. With updates that never stop,
  full agreement happens only in lulls, so the propagation lag is reported too: the seconds
  until every agent holds that version or a newer one (whatever else is still moving);
- steadiness: between consecutive global maps of an agent (same members), the largest move of
  each robot's placement, in cells (over its canvas corners) and degrees. With ``cycle``
  sources each map alternates between two fixed variants, so no link evidence changes
  materially: any move is jitter. Reported for all consecutive maps, and for those whose
  links were the same candidates (a pure function of them: the move must be zero);
- the merged frame after warm-up (:func:`anchor_changes`, :func:`unchanged_moves`): how often
  the anchor of an agent's merged map changed though the anchor's map was still held and only
  lone robots joined (a jump, target 0), and the largest move of the robots whose own map did
  not change between consecutive global maps with the same anchor, above all across a join or
  a leave (target <= 1 cell and <= 0.1 deg);
- churn (``--churn``): a quarter into the run the last robot leaves (SIGTERM), half-way a new
  robot joins, with an id lower than all others (:data:`JOINER`), three quarters in the one
  that left comes back. The sources hold still after
  each change until the running agents agree (at most :data:`CHURN_HOLD` s), so that the
  seconds each change takes to reach agreement can be measured; the robots each agent holds
  just before each change show whether a departed robot was forgotten (``--forget-after``
  short enough to happen within the run).

Run: ``python3 -m bench soak [--robots 8] [--minutes 10] [--sources cycle|replay] [--churn]``;
writes ``bench/results/soak-<sources>[-churn].md``, ``.json`` and ``.png``.
"""

from __future__ import annotations

import argparse
import gzip
import itertools
import json
import os
import tempfile
import time
from pathlib import Path

import numpy as np

from agent.launcher import LocalFleet, agreement
from agent.scenario import LOG, random_frames, segments
from pgvd.grid import Grid, matrix_to_pose

RESULTS = Path(__file__).resolve().parent / "results"
#: Seconds the sources hold still after a churn event, at most, waiting for agreement.
CHURN_HOLD = 45.0
#: Canvas side (cells) over which a placement's move is measured when the source has no size.
DEFAULT_SIDE = 400
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

    def shape(self, i: int) -> tuple[int, int]:
        """Canvas of robot ``i`` for the steadiness measure: unknown here, a fixed square."""
        return (DEFAULT_SIDE, DEFAULT_SIDE)


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

    def shape(self, i: int) -> tuple[int, int]:
        side = int(min(self.base.shape) * 0.6)
        return (side, side)

    def _write(self, i: int, turn: int) -> None:
        from pgvd.io import write_map

        write_map(self.paths[i], self.variant(i, blank=turn % 2 == 1))
        self.written[i] = turn


def _own_component(status: dict) -> dict | None:
    own = status.get("robot")
    return next((c for c in status.get("components", []) if own in c["members"]), None)


def _record_placements(history: dict[str, list], statuses: dict[str, dict | None], now: float):
    """Append each agent's own component when its global map changed (new digest), with the
    robots of the agent's other merged maps (two or more members) at the last poll that saw
    it (:func:`anchor_changes`)."""
    for robot, status in statuses.items():
        comp = status and _own_component(status)
        if not comp or "transforms" not in comp:
            continue
        seen = history.setdefault(robot, [])
        others = [
            r
            for c in status["components"]
            if c is not comp and len(c["members"]) > 1
            for r in c["members"]
        ]
        if seen and seen[-1]["digest"] == comp["digest"]:
            # the other merged maps just before the next change: a merge is told from a jump
            seen[-1]["others"] = others
            continue
        seen.append(
            {
                "t": now,
                "digest": comp["digest"],
                "anchor": comp["anchor"],
                "members": comp["members"],
                "versions": comp["versions"],
                "transforms": comp["transforms"],
                "links": comp.get("evidence", []),
                "others": others,
            }
        )


#: The id of the robot that joins under churn: lower than every other robot's ``r1``...
#: ``rN``, so that a rule anchoring the merged frame at the lowest id would move the frame
#: when it joins (the jump :func:`anchor_changes` counts).
JOINER = "r0"


def robot_ids(robots: int, churn: bool) -> list[str]:
    """The ids of the declared sources, in order: ``r1``...``rN``, then the joiner if churn."""
    return [f"r{i + 1}" for i in range(robots)] + ([JOINER] if churn else [])


def _churn_plan(robots: int, minutes: float) -> list[tuple[float, str, str]]:
    """(second, leave|join|return, robot): the last robot leaves, :data:`JOINER` joins, the
    one that left returns."""
    total = minutes * 60
    last = f"r{robots}"
    return [
        (total / 4, "leave", last),
        (total / 2, "join", JOINER),
        (3 * total / 4, "return", last),
    ]


def soak(
    sources: ReplaySources | CycleSources,
    minutes: float,
    workdir: Path,
    settle: float = 90.0,
    churn: list[tuple[float, str, str]] | None = None,
    agent_args: list[str] | None = None,
) -> dict:
    """Run the fleet for ``minutes``; the raw time series and events.

    The sources of ``sources.agents`` are robots :func:`robot_ids`.  With ``churn``, the robot
    of a ``join`` event is the last of them and is started only then; ``leave`` stops a robot
    with SIGTERM and ``return`` restarts it.
    """
    series: dict[str, list[tuple[float, float, float]]] = {}
    published: dict[tuple[str, int], float] = {}
    agreed: list[tuple[float, dict[str, int]]] = []
    held_by_all: list[tuple[float, dict[str, int]]] = []
    history: dict[str, list] = {}
    held: dict[str, list[tuple[float, int]]] = {}
    changes: list[dict] = []
    drops: dict[str, int] = {}
    plan = sorted(churn or [])
    joiners = {r for _, kind, r in plan if kind == "join"}
    with LocalFleet("soak", workdir / "fleet", agent_args or []) as fleet:
        started = sources.agents(workdir)
        ids = robot_ids(len(started) - len(joiners), bool(joiners))
        declared = list(zip(ids, started, strict=True))
        later = {r: a for r, a in declared if r in joiners}
        for robot, (source, args) in declared:
            if robot not in joiners:
                fleet.add(robot, source, args)
        t0 = time.time()
        next_sample = next_print = t0
        pending: dict | None = None
        while time.time() - t0 < minutes * 60:
            now = time.time()
            if pending is None or now - t0 - pending["t"] >= CHURN_HOLD:
                sources.step(now - t0)
            while plan and now - t0 >= plan[0][0]:
                _, kind, robot = plan.pop(0)
                held_now = {r: rows[-1][1] for r, rows in held.items() if rows}
                if kind == "leave":
                    fleet.agents[robot].stop()
                elif kind == "join":
                    fleet.add(robot, *later[robot])
                else:
                    fleet.restart(robot)
                pending = {
                    "t": round(now - t0, 1),
                    "event": kind,
                    "robot": robot,
                    "agreed_after_s": None,
                    "robots_held_before": held_now,
                }
                changes.append(pending)
                print(f"{now - t0:6.0f} s  {robot} {kind}", flush=True)
            running = {r for r, a in fleet.agents.items() if a.alive()}
            statuses = {r: s for r, s in fleet.statuses().items() if r in running}
            for robot, status in statuses.items():
                if status and status.get("own_version") and status.get("last_update"):
                    published.setdefault((robot, status["own_version"]), status["last_update"])
                if status:
                    count = sum(1 for v in status["robots"].values() if v["version"] is not None)
                    held.setdefault(robot, []).append((now - t0, count))
            _record_placements(history, statuses, now - t0)
            if all(statuses.values()):
                held_by_all.append((now, least_held(statuses)))  # type: ignore[arg-type]
            if agreement(statuses):
                first = next(iter(statuses.values()))["robots"]  # type: ignore[index]
                agreed.append((now, {r: v["version"] or 0 for r, v in first.items()}))
                if pending is not None and _includes_change(statuses, pending):
                    pending["agreed_after_s"] = round(now - t0 - pending["t"], 1)
                    pending = None
            if now >= next_sample:
                for robot, agent in fleet.agents.items():
                    sample = agent.alive() and agent.proc and proc_sample(agent.proc.pid)
                    if sample:
                        series.setdefault(robot, []).append((now - t0, *sample))
                next_sample = now + 5
            if now >= next_print:
                versions = [(s or {}).get("own_version") for s in statuses.values()]
                print(f"{now - t0:6.0f} s  versions {versions}", flush=True)
                print(f"        agreements {len(agreed)}  running {sorted(running)}", flush=True)
                next_print = now + 30
            time.sleep(0.5)
        # Updates stop here: give the fleet up to ``settle`` s to agree on the last ones.
        running = {r for r, a in fleet.agents.items() if a.alive()}

        def live() -> dict[str, dict | None]:
            return {r: s for r, s in fleet.statuses().items() if r in running}

        deadline = time.time() + settle
        while time.time() < deadline and not agreement(live()):
            time.sleep(0.5)
        statuses = live()
        if agreement(statuses):
            first = next(iter(statuses.values()))["robots"]  # type: ignore[index]
            agreed.append((time.time(), {r: v["version"] or 0 for r, v in first.items()}))
        for status in statuses.values():
            for reason, n in (status or {}).get("drops", {}).items():
                drops[reason] = drops.get(reason, 0) + n
        dead = [r for r, a in fleet.agents.items() if not a.alive() and r in running]
    return {
        "t0": t0,
        "series": series,
        "published": published,
        "agreed": agreed,
        "held_by_all": held_by_all,
        "history": history,
        "held": held,
        "changes": changes,
        "drops": drops,
        "dead": dead,
    }


def _includes_change(statuses: dict[str, dict | None], change: dict) -> bool:
    """Whether agreed statuses reflect a churn event: the robot held (join/return) by all."""
    if change["event"] == "leave":
        return True  # the others agreeing again is the convergence
    return all(
        (s or {}).get("robots", {}).get(change["robot"], {}).get("version") is not None
        for s in statuses.values()
    )


def placement_move(before: list, after: list, shape: tuple[int, int]) -> tuple[float, float]:
    """(cells over the canvas corners, degrees) between two placements of one robot."""
    m0, m1 = np.array(before, float), np.array(after, float)
    h, w = shape
    corners = np.array([[0, 0, 1], [w - 1, 0, 1], [0, h - 1, 1], [w - 1, h - 1, 1]], float).T
    cells = float(np.linalg.norm((m1 @ corners - m0 @ corners)[:2], axis=0).max())
    turn = matrix_to_pose(m1)[0] - matrix_to_pose(m0)[0]
    return cells, float(np.degrees(abs(np.angle(np.exp(1j * turn)))))


def jumps(history: dict[str, list], shape_of) -> dict[str, dict[str, float]]:
    """Largest move of any robot between consecutive global maps with the same members.

    ``all``: every such pair of maps; ``same_links``: those whose accepted links were the same
    candidates (the placements are a function of them, so the move must be zero).
    """
    out = {k: {"cells": 0.0, "deg": 0.0, "pairs": 0} for k in ("all", "same_links")}
    for maps in history.values():
        for prev, cur in itertools.pairwise(maps):
            if prev["members"] != cur["members"]:
                continue
            kinds = ["all"] + (["same_links"] if prev["links"] == cur["links"] else [])
            for robot, m in cur["transforms"].items():
                cells, deg = placement_move(prev["transforms"][robot], m, shape_of(robot))
                for k in kinds:
                    out[k]["cells"] = max(out[k]["cells"], round(cells, 3))
                    out[k]["deg"] = max(out[k]["deg"], round(deg, 4))
            for k in kinds:
                out[k]["pairs"] += 1
    return out


def anchor_changes(history: dict[str, list], since: float = 0.0) -> dict:
    """Changes of the anchor of an agent's merged map between its consecutive global maps.

    Only a merged map (two or more members) has a frame to keep.  When its anchor changed, at
    ``since`` s into the run or later, the change is one of:

    - ``left``: the earlier anchor is no longer a member (its robot was forgotten, or the
      merged map split): the frame had to move;
    - ``merged``: a robot of another merged map (at the last poll before) is now a member:
      two frames became one, and one of them had to give way;
    - ``jumps``: neither: the earlier anchor's map is still held in the merged map and only
      lone robots joined it, yet the frame moved (the target is none).  Each is listed in
      ``jumped`` as ``[agent, second, anchor before, anchor after]``.

    Changes before ``since`` (the merged map forming while robots start) are not counted: a
    global map that is a pure function of the maps held cannot keep the frame of a partial
    merged map when an older robot joins it.
    """
    out: dict = {"jumps": 0, "left": 0, "merged": 0, "jumped": []}
    for agent, maps in sorted(history.items()):
        for prev, cur in itertools.pairwise(maps):
            if cur["t"] < since or len(prev["members"]) < 2 or prev["anchor"] == cur["anchor"]:
                continue
            if prev["anchor"] not in cur["members"]:
                out["left"] += 1
            elif set(cur["members"]) & set(prev["others"]):
                out["merged"] += 1
            else:
                out["jumps"] += 1
                out["jumped"].append([agent, round(cur["t"], 1), prev["anchor"], cur["anchor"]])
    return out


def unchanged_moves(history: dict[str, list], shape_of, since: float = 0.0) -> dict:
    """Largest move of a robot whose map did not change, between consecutive global maps.

    Over every pair of consecutive global maps of an agent with the same anchor, at ``since``
    s into the run or later: the robots other than the anchor held at the same version in
    both, their placement's move in cells (over the robot's canvas corners) and degrees.
    ``all``: every such pair; ``membership_changed``: those where robots joined or left in
    between, the churn that must not move the others (the target is <= 1 cell, <= 0.1 deg).
    """
    out = {k: {"cells": 0.0, "deg": 0.0, "pairs": 0} for k in ("all", "membership_changed")}
    for maps in history.values():
        for prev, cur in itertools.pairwise(maps):
            if cur["t"] < since or prev["anchor"] != cur["anchor"]:
                continue
            kinds = ["all"] + (["membership_changed"] if prev["members"] != cur["members"] else [])
            same = [
                r
                for r in cur["members"]
                if r in prev["members"]
                and r != cur["anchor"]
                and prev["versions"][r] == cur["versions"][r]
            ]
            for robot in same:
                m0, m1 = prev["transforms"][robot], cur["transforms"][robot]
                cells, deg = placement_move(m0, m1, shape_of(robot))
                for k in kinds:
                    out[k]["cells"] = max(out[k]["cells"], round(cells, 3))
                    out[k]["deg"] = max(out[k]["deg"], round(deg, 4))
            for k in kinds:
                out[k]["pairs"] += bool(same)
    return out


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


def rss_growth(rows: list[tuple[float, float, float]]) -> float:
    """Memory growth of one agent after its warm-up, in %: its mean RSS over its last minute
    against the mean over the minute after the first quarter of its own samples' span (an
    agent that joins late warms up after it started, not a quarter into the run)."""
    t, _, rss = np.array(rows).T
    warm = t[0] + (t[-1] - t[0]) / 4
    after_warm = rss[(t >= warm) & (t < warm + 60)]
    at_warm = after_warm.mean() if after_warm.size else rss[-1]
    tail = rss[t >= t[-1] - 60].mean()
    return float((tail - at_warm) / at_warm * 100)


def summarise(run: dict, minutes: float, shape_of=lambda robot: (DEFAULT_SIDE,) * 2) -> dict:
    warm = minutes * 60 / 4
    growth = {robot: rss_growth(rows) for robot, rows in run["series"].items()}
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
        "jumps": jumps(run["history"], shape_of),
        "anchor_changes": anchor_changes(run["history"], warm),
        "unchanged_moves": unchanged_moves(run["history"], shape_of, warm),
        "global_maps_per_agent": {r: len(h) for r, h in sorted(run["history"].items())},
        "churn": run["changes"],
        "robots_held_max": {r: max(c for _, c in rows) for r, rows in sorted(run["held"].items())},
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
    parser.add_argument(
        "--churn", action="store_true", help="a robot leaves, a new one joins, the first returns"
    )
    parser.add_argument(
        "--forget-after", type=float, default=30.0, help="the agents' --forget-after (s)"
    )
    args = parser.parse_args()
    declared = args.robots + (1 if args.churn else 0)  # the joiner is declared last
    if args.sources == "cycle":
        sources: ReplaySources | CycleSources = CycleSources(declared)
    else:
        sources = ReplaySources(declared, args.minutes)
    plan = _churn_plan(args.robots, args.minutes) if args.churn else None
    print(f"{args.robots} agents, {args.sources} sources, {args.minutes:g} min", flush=True)
    agent_args = ["--forget-after", f"{args.forget_after:g}"]
    with tempfile.TemporaryDirectory(prefix="pgvd-soak-") as tmp:
        run = soak(sources, args.minutes, Path(tmp), args.settle, plan, agent_args)
    ids = robot_ids(args.robots, args.churn)
    summary = summarise(run, args.minutes, lambda robot: sources.shape(ids.index(robot)))
    name = f"soak-{args.sources}" + ("-churn" if args.churn else "")
    args.out.mkdir(parents=True, exist_ok=True)
    raw = {"series": run["series"], "published": [[*k, v] for k, v in run["published"].items()]}
    (args.out / f"{name}.json").write_text(json.dumps({"summary": summary, "raw": raw}))
    plot(run, summary, args.out / f"{name}.png")
    growth = summary["rss_growth_after_warmup_pct"]
    lines = [
        f"# Soak ({args.sources} sources)",
        "",
        f"`python3 -m bench soak --robots {args.robots} --minutes {args.minutes:g} --sources "
        f"{args.sources} --settle {args.settle:g}"
        f"{' --churn' if args.churn else ''} --forget-after {args.forget_after:g}` "
        f"on {os.cpu_count()} cores, "
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
        f"- largest placement move between consecutive global maps with the same members "
        f"(cells over the robot's canvas corners, degrees): {summary['jumps']['all']}; "
        f"of those whose links were the same candidates: {summary['jumps']['same_links']} "
        "(target <= 1 cell and <= 0.1 deg where the link evidence did not change)",
        f"- anchor changes of an agent's merged map after warm-up: "
        f"{ {k: v for k, v in summary['anchor_changes'].items() if k != 'jumped'} } "
        "(jumps: the anchor's map still held and only lone robots joined, yet the frame "
        "moved, target 0; left: the anchor's robot left the merged map; merged: two merged "
        f"maps joined); the jumps (agent, s, from, to): "
        f"{summary['anchor_changes']['jumped'] or 'none'}",
        f"- largest move of robots whose map did not change, between consecutive global maps "
        f"with the same anchor after warm-up (cells over the robot's canvas corners, degrees): "
        f"{summary['unchanged_moves']['all']}; of those where robots joined or left in "
        f"between: {summary['unchanged_moves']['membership_changed']} "
        "(target <= 1 cell and <= 0.1 deg)",
        f"- global maps seen per agent: {summary['global_maps_per_agent']}",
        f"- churn (event, seconds into the run, seconds to agreement among running agents "
        f"with the sources held for at most {CHURN_HOLD:g} s, robots each agent held just "
        "before): "
        f"{summary['churn'] or 'none'}",
        f"- robots held at most per agent: {summary['robots_held_max']} "
        f"(--forget-after {args.forget_after:g} s)",
        "",
        f"![soak]({name}.png)",
    ]
    (args.out / f"{name}.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
