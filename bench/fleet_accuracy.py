"""Fleet accuracy: what a running fleet shows its users, judged against the truth over time.

For each building and each fleet size N (default 2, 3, 4, 6), N real agents replay
overlapping, growing segments of the building's log or simulated drive in random frames of
their own, peer to peer on localhost, exactly as ``pgvd demo`` runs them
(:class:`agent.launcher.LocalFleet`, :mod:`agent.scenario`).  While they run, every agent's
``status.json`` (rewritten at once on every new global map) is polled every 0.1 s and each
distinct global map of each agent (components, members, transforms, links used) is recorded
with the agent's time of writing, with each robot's replay cursor and registration epochs.
Afterwards the bench replays the same segments itself, up to each recorded cursor, for the
true overlap of every pair as the maps grew (:func:`agent.evaluate.true_overlap`), and
reports per building and N (:mod:`bench.fleet_history`):

- wrong placements ever shown: spells during which any agent's global map placed a robot
  beyond ``--max-deg`` / ``--max-cells`` of the truth, and how long each stayed;
- the fraction of truly overlapping robots (true overlap >= ``--min-overlap`` with another
  robot at the end) that every agent places right at the end;
- per pair, the delay from its true overlap first reaching ``--min-overlap`` to both
  robots' own agents showing them rightly placed together, in seconds and in registration
  epochs, split at the moment the links decided anywhere in the fleet first joined them
  (read from the agents' logs): the time the decision took, and the time the global maps
  took to show it.

What sampling can miss: a global map that an agent replaced within one poll (0.1 s) is
never seen, so a wrong placement shown for less than that may go uncounted and the
durations are exact only to about 0.1 s; the replay cursors come with the status, which an
agent writes about once a second when no new map forces it, so the true overlap's crossing
time is late by up to a second.

A building is ``log:PATH`` (a CARMEN log, replayed as the agents' ``carmen:`` source) or
``map:PATH.yaml`` (a map_server image that simulated-lidar robots drive through, the agents'
``sim:`` source: the one seeded tour of the image, split into segments as a log is).  By
default the buildings are every development log and the main image of every development map.

Run: ``python3 -m bench fleet_accuracy [--quick] [--robots 2 3 4 6] [--out DIR] [--keep DIR]``;
writes ``fleet-accuracy.md``, ``.json`` and ``.png`` to ``--out`` (default ``bench/results``);
``--keep`` keeps every run's agents' verbose logs, which the results do not hold.
``--held-out`` runs every other log of the shared data instead, once, reported
apart (``fleet-accuracy-held-out.*``); nothing is set from it.  The results are rewritten
after every case, so an interrupted run leaves the cases it finished.
"""

from __future__ import annotations

import argparse
import itertools
import json
import math
import os
import sys
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from agent.evaluate import true_matrix, true_overlap
from agent.launcher import LocalFleet, agreement, sources_done
from agent.scenario import LOG, check_run, random_frames, segments
from agent.sources import CarmenSource, parse_frame, parse_source
from bench import fleet_history as fh
from bench.data.sources import SHARED, SOURCES
from bench.workdirs import add_keep_argument, check_keep, fleet_dir

RESULTS = Path(__file__).resolve().parent / "results"
SHARED_LOGS = SHARED / "logs"
#: The development logs: the bundled Intel log and freiburg-079; every other log in the
#: shared data is held out.
DEV_LOGS = (LOG, SHARED_LOGS / "freiburg-079-corrected.log.gz")
#: The main image of every development map, as the simulated runs of the merge bench use.
DEV_MAPS = tuple(SHARED / s.path for s in SOURCES if s.simulated)
#: The agents' ``--source`` kind of each kind of building.
SOURCE_KIND = {"log": "carmen", "map": "sim"}
#: The agents' default cell size (``pgvd agent --resolution``), which the truth replays too.
RESOLUTION = 0.1
POLL_S = 0.1


class BenchError(ValueError):
    """Bad input: reported as one line on stderr, exit 2."""


@dataclass(frozen=True)
class Building:
    """A place the fleet maps: ``kind`` "log" (a CARMEN log) or "map" (a map image)."""

    kind: str
    path: Path

    @property
    def name(self) -> str:
        """Row label: the log's name, or the map's directory with "-sim" (a simulated drive)."""
        if self.kind == "map":
            return f"{self.path.parent.name}-sim"
        return self.path.name.removesuffix(".gz").removesuffix(".log").removesuffix("-corrected")

    def source(self, segment: tuple[float, float]) -> str:
        """The agents' ``--source`` replaying ``segment`` (fractions) of this building's run."""
        return f"{SOURCE_KIND[self.kind]}:{self.path}@{segment[0]}-{segment[1]}"


def parse_building(spec: str) -> Building:
    """``log:PATH`` or ``map:PATH.yaml``; :class:`BenchError` (one line) if malformed."""
    kind, sep, rest = spec.partition(":")
    if not sep or kind not in SOURCE_KIND or not rest:
        raise BenchError(f"a building is log:PATH or map:PATH.yaml, got {spec!r}")
    return Building(kind, Path(rest))


def check_building(building: Building, robots: int) -> None:
    """:class:`BenchError` (one line) unless the building's run gives ``robots`` robots a map
    each (:func:`agent.scenario.check_run`: a missing file, a log with no scans, a map with no
    room to drive)."""
    try:
        check_run(SOURCE_KIND[building.kind], building.path, robots)
    except ValueError as exc:
        raise BenchError(str(exc)) from None  # it names the file


def held_out_logs(logs: Path = SHARED_LOGS) -> list[Path]:
    """Every log of the shared data that is not a development log."""
    dev = {p.name for p in DEV_LOGS}
    return sorted(p for p in logs.glob("*.log.gz") if p.name not in dev)


# ------------------------------------------------------------------------------ the truth


class GrowingMaps:
    """The robots' maps as their segments grow, replayed here with the agents' own source.

    A ``carmen:`` log and a ``sim:`` drive through a map image replay alike
    (:class:`agent.sources.CarmenSource`): the same scans, cast into the same canvas, give
    the maps the agents had at each cursor.

    Parameters
    ----------
    specs : ``{robot: (--source, --frame)}`` as the agents were given them.
    """

    def __init__(self, specs: Mapping[str, tuple[str, str]]) -> None:
        self.sources = {
            r: CarmenSource(parse_source(spec), parse_frame(frame), RESOLUTION, math.inf)
            for r, (spec, frame) in specs.items()
        }

    def truth(self) -> fh.Truth:
        """The robots' true frames, as their agents report them (``world_to_pixel``, the run's
        world metres -> map pixels, and ``canvas_shape``)."""
        described = {r: s.describe() for r, s in self.sources.items()}
        return fh.Truth(
            {r: np.array(d["world_to_pixel"]) for r, d in described.items()},
            {r: tuple(d["canvas_shape"]) for r, d in described.items()},
        )

    def advance(self, robot: str, cursor: int) -> None:
        """Integrate ``robot``'s scans up to ``cursor`` (scans already integrated stay)."""
        from pgvd.integrate import integrate_scan

        src = self.sources[robot]
        for scan in src.scans[src.cursor : cursor]:
            integrate_scan(src.logodds, scan, src.map_frame)
        src.cursor = max(src.cursor, min(cursor, len(src.scans)))

    def overlaps(self, truth: fh.Truth) -> dict[str, float]:
        """True overlap of every pair "a-b" now."""
        grids = {r: s.grid() for r, s in self.sources.items()}
        w2p = truth.world_to_pixel
        return {
            f"{a}-{b}": true_overlap(grids[a], grids[b], true_matrix(w2p[a], w2p[b]))
            for a, b in itertools.combinations(sorted(grids), 2)
        }


def overlap_history(maps: GrowingMaps, progress: Sequence[Mapping]) -> list[dict]:
    """True overlaps of every pair at each recorded change of a replay cursor."""
    truth = maps.truth()
    out = []
    for t, group in itertools.groupby(sorted(progress, key=lambda p: p["t"]), key=lambda p: p["t"]):
        for p in group:
            maps.advance(p["robot"], p["cursor"])
        out += [
            {"t": t, "pair": pair, "overlap": round(f, 4)}
            for pair, f in maps.overlaps(truth).items()
        ]
    return out


# ------------------------------------------------------------------------------ recording


class Recorder:
    """Keeps each distinct global map of each agent, and each change of a robot's progress."""

    def __init__(self, t0: float) -> None:
        self.t0 = t0
        self.maps: list[dict] = []
        self.progress: list[dict] = []
        self._last_map: dict[str, object] = {}
        self._last_progress: dict[str, tuple[int, int]] = {}

    def sample(self, statuses: Mapping[str, dict | None]) -> None:
        """Record what changed in the agents' statuses, at the time each agent wrote it."""
        for robot, s in statuses.items():
            if s is None:
                continue
            t = round(float(s["time"]) - self.t0, 3)
            comps = [
                {
                    "anchor": c["anchor"],
                    "members": c["members"],
                    "transforms": c["transforms"],
                    "used": c["used"],
                    "digest": c["digest"],
                }
                for c in s.get("components", [])
            ]
            key = [(c["anchor"], c["members"], c["digest"]) for c in comps]
            if comps and key != self._last_map.get(robot):
                self._last_map[robot] = key
                self.maps.append({"t": t, "agent": robot, "components": comps})
            prog = (int(s["source"]["progress"][0]), int(s.get("counts", {}).get("epochs", 0)))
            if prog != self._last_progress.get(robot):
                self._last_progress[robot] = prog
                self.progress.append({"t": t, "robot": robot, "cursor": prog[0], "epochs": prog[1]})


@dataclass(frozen=True)
class Settings:
    """What every run of one bench invocation shares."""

    seeds: tuple[int, ...] = (7, 8, 9)
    log_seconds: float = 60.0
    timeout: float = 300.0
    tolerance: fh.Tolerance = field(default_factory=fh.Tolerance)
    min_overlap: float = 0.3


def run_case(
    building: Building, n: int, seed: int, settings: Settings, workdir: Path, verbose: bool = False
) -> dict:
    """Run ``n`` agents on ``building``, in frames drawn from ``seed``, until they agree on
    final maps (or time out).  ``verbose`` runs the agents with ``--verbose``, for a run kept
    to be looked into (``--keep``): their logs then tell every map received and every
    decision's timings.

    Returns
    -------
    dict
        The case: its setup, whether and when the fleet agreed, the recorded history
        (times in seconds since launch) and its summary (:func:`summarise`).
    """
    robots = [f"r{i + 1}" for i in range(n)]
    specs = fleet_specs(building, n, seed)
    growing = GrowingMaps(specs)
    speed = replay_speed(growing, settings.log_seconds)
    t0 = time.time()
    rec = Recorder(t0)
    agreed_at = None
    common = ["--speed", f"{speed:.3f}"] + (["--verbose"] if verbose else [])
    with LocalFleet(f"acc{n}", workdir, common) as fleet:
        for r, (spec, frame) in specs.items():
            fleet.add(r, spec, ["--frame=" + frame])
        deadline = time.monotonic() + settings.timeout
        next_line = 0.0
        while time.monotonic() < deadline:
            st = fleet.statuses()
            rec.sample(st)
            if time.monotonic() >= next_line:
                _progress_line(building, n, time.time() - t0, st, rec)
                next_line = time.monotonic() + 5.0
            if not all(a.alive() for a in fleet.agents.values()):
                break
            final = {r: int(s["own_version"] or 0) for r, s in st.items() if s}
            if sources_done(st) and agreement(st, final):
                agreed_at = time.time() - t0
                break
            time.sleep(POLL_S)
        dead = sorted(r for r, a in fleet.agents.items() if not a.alive())
    end = time.time() - t0
    overlaps = overlap_history(growing, rec.progress)
    links = [
        event for r in robots for event in fh.link_events(_log_lines(workdir / r / "agent.log"), t0)
    ]
    truth = growing.truth()
    case = {
        "building": building.name,
        "source": f"{building.kind}:{building.path}",
        "robots": n,
        "seed": seed,
        "speed": round(speed, 2),
        "agreed_s": None if agreed_at is None else round(agreed_at, 2),
        "wall_s": round(end, 2),
        "dead_agents": dead,
        "truth": {
            "world_to_pixel": {r: m.tolist() for r, m in truth.world_to_pixel.items()},
            "shapes": {r: list(s) for r, s in truth.shapes.items()},
        },
        "history": {
            "maps": rec.maps,
            "progress": rec.progress,
            "overlaps": overlaps,
            "links": sorted(links, key=lambda e: e["t"]),
        },
    }
    case["summary"] = summarise(case, truth, settings)
    return case


def fleet_specs(building: Building, n: int, seed: int) -> dict[str, tuple[str, str]]:
    """``{robot: (--source, --frame)}`` of ``n`` agents on ``building``, in the frames drawn
    from ``seed``: robots ``r1`` ... ``rN`` on the segments of :func:`agent.scenario.segments`."""
    robots = [f"r{i + 1}" for i in range(n)]
    return {
        r: (building.source(seg), ",".join(f"{v:.4f}" for v in frame))
        for r, seg, frame in zip(robots, segments(n), random_frames(n, seed), strict=True)
    }


def replay_speed(growing: GrowingMaps, log_seconds: float) -> float:
    """The agents' ``--speed``: the whole run replayed in ``log_seconds``, and never slower
    than real time."""
    return max(_run_duration(growing) / log_seconds, 1.0)


def _log_lines(path: Path) -> list[str]:
    """The lines of an agent's log; none if it never wrote one."""
    try:
        return path.read_text(errors="replace").splitlines()
    except FileNotFoundError:
        return []


def _run_duration(growing: GrowingMaps) -> float:
    """Seconds of the whole log or drive, from the segments' scans (they cover it together)."""
    scans = growing.sources.values()
    return max(s.scans[-1].timestamp for s in scans) - min(s.scans[0].timestamp for s in scans)


def _progress_line(
    building: Building, n: int, t: float, st: Mapping[str, dict | None], rec: Recorder
) -> None:
    done = " ".join(_percent(s["source"]["progress"]) if s else "-" for s in st.values())
    print(
        f"  {building.name} N={n} {t:5.0f} s: replay {done}, {len(rec.maps)} global maps seen",
        file=sys.stderr,
        flush=True,
    )


def _percent(progress: Sequence[int]) -> str:
    return f"{100 * progress[0] // max(progress[1], 1)}%"


# ------------------------------------------------------------------------------ summary


def summarise(case: Mapping, truth: fh.Truth, settings: Settings) -> dict:
    """The case's numbers: wrong spells, right placements at the end, overlap-to-placed delays."""
    hist = case["history"]
    tol, end = settings.tolerance, case["wall_s"]
    robots = [f"r{i + 1}" for i in range(case["robots"])]
    spells = fh.wrong_spells(hist["maps"], truth, tol, end)
    final = _final_overlaps(hist["overlaps"])
    pairs = [p.split("-") for p, f in final.items() if f >= settings.min_overlap]
    overlapping = sorted({r for pair in pairs for r in pair})
    right = fh.placed_right_at_end(hist["maps"], robots, truth, tol)
    delays = fh.pair_delays(
        hist["maps"], hist["progress"], hist["overlaps"], truth, tol, settings.min_overlap,
        hist.get("links", ()),
    )  # fmt: skip
    return {
        "global_maps_seen": len(hist["maps"]),
        "wrong_spells": spells,
        "wrong_spells_count": len(spells),
        "wrong_robots": sorted({s["robot"] for s in spells}),
        "wrong_longest_s": round(max((s["seconds"] for s in spells), default=0.0), 2),
        "wrong_at_end": sum(s["at_end"] for s in spells),
        "final_overlaps": final,
        "overlapping_robots": overlapping,
        "placed_right_at_end": sorted(r for r in overlapping if right[r]),
        "placed_right_fraction": None
        if not overlapping
        else round(sum(right[r] for r in overlapping) / len(overlapping), 3),
        "delays": delays,
    }


def _final_overlaps(overlaps: Sequence[Mapping]) -> dict[str, float]:
    last: dict[str, float] = {}
    for o in sorted(overlaps, key=lambda o: o["t"]):
        last[o["pair"]] = o["overlap"]
    return last


# ------------------------------------------------------------------------------ report


def table(cases: Sequence[Mapping]) -> str:
    """One markdown row per building, N and seed."""
    head = (
        "| building | N | seed | agreed after (s) | global maps seen | wrong placements shown "
        "| robots ever wrong | longest wrong (s) | wrong at end | overlapping robots placed "
        "right at end | pairs reaching overlap | placed together | delay s (median / max) "
        "| delay epochs (median / max) | of which deciding / showing s (median) |"
    )
    lines = [head, "|" + "---|" * 15]
    for c in cases:
        s = c["summary"]
        placed = [d for d in s["delays"] if d["seconds"] is not None]
        secs = [d["seconds"] for d in placed]
        eps = [d["epochs"] for d in placed]
        split = [d for d in placed if d.get("linked_at") is not None]
        deciding = [d["linked_at"] - d["overlap_at"] for d in split]
        showing = [d["placed_at"] - d["linked_at"] for d in split]
        frac = s["placed_right_fraction"]
        agreed = "NO" if c["agreed_s"] is None else c["agreed_s"]
        lines.append(
            f"| {c['building']} | {c['robots']} | {c['seed']} | {agreed} "
            f"| {s['global_maps_seen']} | {s['wrong_spells_count']} "
            f"| {','.join(s['wrong_robots']) or '-'} | {s['wrong_longest_s']} "
            f"| {s['wrong_at_end']} "
            f"| {len(s['placed_right_at_end'])}/{len(s['overlapping_robots'])}"
            f"{'' if frac is None else f' ({frac:.0%})'} "
            f"| {len(s['delays'])} | {len(placed)} | {_median_max(secs, '.1f')} "
            f"| {_median_max(eps, '.0f')} | {_median(deciding)} / {_median(showing)} |"
        )
    return "\n".join(lines)


def _median(values: Sequence[float]) -> str:
    return f"{float(np.median(values)):.1f}" if values else "-"


def _median_max(values: Sequence[float], fmt: str) -> str:
    if not values:
        return "-"
    return f"{format(float(np.median(values)), fmt)} / {format(float(max(values)), fmt)}"


def markdown(cases: Sequence[Mapping], argv: Sequence[str], settings: Settings, wall: float) -> str:
    stamp = time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())
    tol = settings.tolerance
    return (
        "# Fleet accuracy\n\n"
        f"`{' '.join(['python3 -m bench fleet_accuracy', *argv])}` on {os.cpu_count()} cores "
        f"(shared with other jobs), {stamp}; wall time {wall / 60:.1f} min.\n"
        "Real agents replay overlapping, growing segments of each log, or of a simulated "
        "drive through each map image (`-sim`), in random frames "
        f"(seeds {', '.join(map(str, settings.seeds))}; the whole log or drive lasts "
        f"{settings.log_seconds:g} s of replay), "
        "peer to peer on localhost, as `pgvd demo` runs them.  Every agent's status.json "
        f"was polled every {POLL_S:g} s and each distinct global map recorded.\n\n"
        + table(cases)
        + "\n\nA placement is wrong when a robot's transform to its component's anchor is "
        f"beyond {tol.deg:g} deg or {tol.cells:g} cells (largest corner displacement) of the "
        "truth; a wrong placement shown is one spell of one agent showing one robot wrongly "
        "placed, lasting until that agent's next global map that does not.  Overlapping "
        f"robots: true overlap >= {settings.min_overlap:g} with another robot once the "
        "segments are complete; placed right at the end: by every agent's last global map.  "
        "Delay: from a pair's true overlap first reaching that threshold (as the segments "
        "grew) to both robots' own agents showing the two rightly placed together, in seconds "
        "and in registration epochs both robots began meanwhile; negative when the fleet "
        "placed them before the overlap reached the threshold.  Deciding: until the links "
        "decided anywhere (the agents' logs) first joined the pair; showing: from then until "
        "both robots' agents showed it.  A global map replaced within "
        "one poll is not seen; replay cursors come with the status, about once a second.\n\n"
        "![placements over time](fleet-accuracy.png)\n"
    )


COLOURS = {"unplaced": "#d9d9d9", "some": "#a1d99b", "right": "#238b45", "wrong": "#d7301f"}
LABELS = {
    "unplaced": "unplaced",
    "some": "right on some agents",
    "right": "right on every agent",
    "wrong": "wrong on an agent",
}


def timeline(case: Mapping, truth: fh.Truth, tol: fh.Tolerance) -> list[tuple[float, dict]]:
    """``(t, {robot: state})`` over the run: "wrong" if any agent shows it wrong, "right" if
    every agent places it right, "some" if some do, else "unplaced"."""
    robots = [f"r{i + 1}" for i in range(case["robots"])]
    out = []
    for t, held in fh.views(case["history"]["maps"]):
        shown = [fh.placements(c, truth, tol) for c in held.values()]
        states = {}
        for r in robots:
            seen = [s.get(r, fh.UNPLACED) for s in shown]
            if fh.WRONG in seen:
                states[r] = "wrong"
            elif len(held) == len(robots) and all(x == fh.RIGHT for x in seen):
                states[r] = "right"
            else:
                states[r] = "some" if fh.RIGHT in seen else "unplaced"
        out.append((t, states))
    return out


def picture(cases: Sequence[Mapping], tol: fh.Tolerance, path: Path) -> None:
    """Per building and seed (rows) and N (columns): robots on y, time on x, coloured by
    placement."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Patch

    rows = list(dict.fromkeys((c["building"], c["seed"]) for c in cases))
    sizes = sorted({c["robots"] for c in cases})
    fig, axes = plt.subplots(
        len(rows), len(sizes), figsize=(3.6 * len(sizes), 0.6 + 1.6 * len(rows)),
        squeeze=False,
    )  # fmt: skip
    for ax in axes.flat:
        ax.set_axis_off()
    for case in cases:
        ax = axes[rows.index((case["building"], case["seed"])), sizes.index(case["robots"])]
        ax.set_axis_on()
        _panel(ax, case, truth_of(case), tol)
    fig.legend(
        handles=[Patch(color=c, label=LABELS[k]) for k, c in COLOURS.items()]
        + [Patch(color="black", label="true overlap reaches threshold")],
        loc="lower center", ncol=5, fontsize=8,
    )  # fmt: skip
    fig.tight_layout(rect=(0, 0.06, 1, 1))
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _panel(ax, case: Mapping, truth: fh.Truth, tol: fh.Tolerance) -> None:
    robots = [f"r{i + 1}" for i in range(case["robots"])]
    steps = timeline(case, truth, tol)
    end = case["wall_s"]
    for y, r in enumerate(robots):
        # one bar per run of a state: bars drawn edge to edge leave hairline gaps
        changes = [(0.0, "unplaced")] + [(t, states[r]) for t, states in steps] + [(end, "")]
        runs = [changes[0]] + [c for p, c in itertools.pairwise(changes) if c[1] != p[1]]
        for (t0, state), (t1, _) in itertools.pairwise(runs):
            ax.broken_barh([(t0, t1 - t0)], (y - 0.4, 0.8), color=COLOURS[state])
    for d in case["summary"]["delays"]:
        for r in d["pair"].split("-"):
            y = robots.index(r)
            ax.plot([d["overlap_at"]] * 2, [y - 0.45, y + 0.45], color="black", lw=1.2)
    ax.set_yticks(range(len(robots)), robots, fontsize=7)
    ax.set_xlim(0, end)
    ax.set_title(f"{case['building']}, N={case['robots']}, seed {case['seed']}", fontsize=9)
    ax.set_xlabel("s since launch", fontsize=7)
    ax.tick_params(axis="x", labelsize=7)


# ------------------------------------------------------------------------------ CLI


class OneLineParser(argparse.ArgumentParser):
    """An argument parser whose every error is one line on stderr, exit 2.

    Parameters
    ----------
    error_prefix : what the line starts with, before ``": "`` (default: ``prog``).
    **kwargs : those of :class:`argparse.ArgumentParser`.
    """

    def __init__(self, *, error_prefix: str | None = None, **kwargs) -> None:
        super().__init__(**kwargs)
        self.error_prefix = error_prefix or self.prog

    def error(self, message: str) -> None:  # type: ignore[override]
        print(f"{self.error_prefix}: {message}", file=sys.stderr)
        raise SystemExit(2)


def parse_args(argv: Sequence[str]) -> argparse.Namespace:
    ap = OneLineParser(
        prog="python3 -m bench fleet_accuracy",
        description=__doc__.splitlines()[0],
        error_prefix="fleet_accuracy",
    )
    ap.add_argument("--buildings", nargs="+", default=None, help="log:PATH or map:PATH.yaml")
    ap.add_argument("--robots", type=int, nargs="+", default=[2, 3, 4, 6])
    ap.add_argument("--quick", action="store_true", help="the bundled Intel log, N=2,3 only")
    ap.add_argument("--held-out", action="store_true",
                    help="every held-out log, reported apart")  # fmt: skip
    ap.add_argument("--seeds", type=int, nargs="+", default=list(Settings.seeds),
                    help="one fleet run per seed of the random frames")  # fmt: skip
    ap.add_argument("--log-seconds", type=float, default=Settings.log_seconds,
                    help="wall seconds a whole log's replay lasts")  # fmt: skip
    ap.add_argument("--timeout", type=float, default=Settings.timeout, help="s per fleet run")
    ap.add_argument("--max-deg", type=float, default=fh.Tolerance.deg)
    ap.add_argument("--max-cells", type=float, default=fh.Tolerance.cells)
    ap.add_argument("--min-overlap", type=float, default=Settings.min_overlap)
    ap.add_argument("--out", type=Path, default=RESULTS, help="directory of the results")
    add_keep_argument(ap, "BUILDING-N-seedS")
    args = ap.parse_args(argv)
    check_keep(ap, args.keep)
    if args.quick and args.held_out:
        ap.error("--quick and --held-out exclude each other")
    if args.held_out and args.buildings:
        ap.error("--held-out chooses the buildings itself; drop --buildings")
    if any(not 2 <= n <= 12 for n in args.robots):
        ap.error(f"--robots must be between 2 and 12, got {args.robots}")
    if min(args.log_seconds, args.timeout, args.max_deg, args.max_cells) <= 0:
        ap.error("--log-seconds, --timeout, --max-deg and --max-cells must be > 0")
    if not 0 < args.min_overlap <= 1:
        ap.error(f"--min-overlap must be in (0, 1], got {args.min_overlap}")
    if args.out.exists() and not args.out.is_dir():
        ap.error(f"--out is not a directory: {args.out}")
    return args


def buildings_of(args: argparse.Namespace) -> list[Building]:
    """The buildings asked for, each checked to hold a map for the largest fleet."""
    if args.held_out:
        # the held-out logs: real robots' runs, as a fleet meets them; the held-out map
        # images are measured pair by pair (bench mapimages --held-out)
        found = [Building("log", p) for p in held_out_logs()]
        if not found:
            raise BenchError(f"no held-out logs in {SHARED}")
    elif args.quick:
        found = [Building("log", LOG)]
    elif args.buildings:
        found = [parse_building(s) for s in args.buildings]
    else:
        found = [Building("log", p) for p in DEV_LOGS] + [Building("map", p) for p in DEV_MAPS]
    for building in found:
        check_building(building, max(args.robots))
    return found


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    args = parse_args(argv)
    try:
        buildings = buildings_of(args)
    except BenchError as exc:
        print(f"fleet_accuracy: {exc}", file=sys.stderr)
        return 2
    sizes = [2, 3] if args.quick else args.robots
    settings = Settings(
        tuple(args.seeds[:1] if args.quick else args.seeds), args.log_seconds, args.timeout,
        fh.Tolerance(args.max_deg, args.max_cells), args.min_overlap,
    )  # fmt: skip
    t_start = time.time()
    cases = []
    for building, seed, n in itertools.product(buildings, settings.seeds, sizes):
        name = f"{building.name} N={n} seed {seed}"
        print(f"fleet_accuracy: {name} ...", file=sys.stderr, flush=True)
        with fleet_dir(args.keep, f"{building.name}-{n}-seed{seed}") as workdir:
            case = run_case(building, n, seed, settings, workdir, verbose=args.keep is not None)
        cases.append(case)
        write_results(cases, argv, settings, time.time() - t_start, args.out, args.held_out)
        s = case["summary"]
        print(
            f"fleet_accuracy: {name}: agreed {case['agreed_s']} s, "
            f"{s['wrong_spells_count']} wrong placements shown, right at end "
            f"{len(s['placed_right_at_end'])}/{len(s['overlapping_robots'])}",
            file=sys.stderr,
            flush=True,
        )
    print((args.out / f"{stem(args.held_out)}.md").read_text())
    return 0


def truth_of(case: Mapping) -> fh.Truth:
    """The truth a case recorded, back from its JSON form."""
    return fh.Truth(
        {r: np.array(m) for r, m in case["truth"]["world_to_pixel"].items()},
        {r: tuple(s) for r, s in case["truth"]["shapes"].items()},
    )


def write_results(
    cases: Sequence[Mapping],
    argv: Sequence[str],
    settings: Settings,
    wall: float,
    out: Path,
    held_out: bool,
) -> None:
    """Write ``<stem>.md``, ``.json`` and ``.png`` of the cases so far to ``out``."""
    name = stem(held_out)
    out.mkdir(parents=True, exist_ok=True)
    md = markdown(cases, argv, settings, wall).replace("fleet-accuracy.png", f"{name}.png")
    (out / f"{name}.md").write_text(md)
    (out / f"{name}.json").write_text(json.dumps({"argv": list(argv), "cases": cases}, indent=1))
    picture(cases, settings.tolerance, out / f"{name}.png")


def stem(held_out: bool) -> str:
    """File name of the results, without suffix: held-out results are kept apart."""
    return "fleet-accuracy-held-out" if held_out else "fleet-accuracy"


if __name__ == "__main__":
    sys.exit(main())
