"""Delay floor: how soon a one-shot merge could place each overlapping pair, epoch by epoch.

The fleet accuracy bench (:mod:`bench.fleet_accuracy`) measures, per pair of robots, the
delay from the pair's true overlap first reaching ``--min-overlap`` to both robots placed
together, in seconds and in registration epochs both robots began meanwhile.  This study
asks how much of that delay the pairwise merge itself imposes.  It replays the same growing
segments in the same frames (same building, N and seed), cuts each robot's map where its
agent would start a registration epoch (the change gate and epoch rule of
:class:`agent.node.NodeOptions`: :class:`agent.sources.ChangeGate`,
:func:`agent.sources.epoch_due`, on the map as peers decode it), and for each pair whose
true overlap reaches the threshold runs the agent's own registration (a one-shot
:func:`pgvd.merge.merge`, :func:`agent.worker.merge_registration`) at every pair of epochs
in time order, as if every key were searched the moment it appeared.  Per pair it records
the first epoch pair at which

- *merge*: the merge accepts the right pose (within the bench's tolerance);
- *trust*: the trust rules of a lone pair would let the right pose into the global map
  (:func:`agent.trust.first_verdict` on each search with the pair's previous verdict, and
  :func:`agent.trust.settled_verdict` on both robots' final maps); cycles through third
  robots, which may confirm a link sooner, are not modelled;
- *high*: the merge accepts the right pose with a margin at or above
  :data:`agent.trust.HIGH_BAR` (accepted at once);

and every accept of a wrong pose before the search stops (at the *high* floor, or the
final maps), with whether the trust rules would have let it in.  Epochs are counted as the
fleet bench counts them; seconds are replay seconds, with no time for computing.  The
fleet's delays are read from its results (``--fleet``) and set beside the floor.

Run: ``python3 -m bench delay_floor [--quick] [--robots 2 3 4 6] [--seeds 7]``; writes
``delay-floor.md`` and ``.json`` to ``--out`` (default ``bench/results``), rewritten after
every case: every development building and N at seed 7 took 43 min of wall time on a busy
2-core machine.  ``--report-only`` rewrites the ``.md`` from the ``.json`` without searching.
Development buildings only: those of :mod:`bench.fleet_accuracy`.
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import sys
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from agent import trust
from agent.evaluate import link_error, true_matrix
from agent.node import NodeOptions
from agent.sources import ChangeGate, compress_gaps, epoch_due
from agent.wire import on_the_wire
from agent.worker import RegisterFn, Registration, merge_registration
from bench import fleet_accuracy as fa
from bench import fleet_history as fh
from pgvd.grid import Grid
from pgvd.params import MergeParams
from pgvd.posegraph import components

#: The agent's main loop offers its source's newest map to the change gate about every
#: 0.1 s (:meth:`agent.daemon.Daemon._loop` waits that long for events between steps).
TICK_S = 0.1
#: The floors, in the order they are reached at the earliest (but "chain", which may come
#: before "trust" through other robots).
FLOORS = ("merge", "trust", "chain", "high")


@dataclass(frozen=True)
class Epoch:
    """The first map of one robot's registration epoch: its replay time and cursor, and the
    map as peers decode it."""

    robot: str
    t: float
    cursor: int
    grid: Grid
    final: bool


def epochs_of(growing: fa.GrowingMaps, speed: float) -> tuple[dict[str, list[Epoch]], list[dict]]:
    """Each robot's registration epochs as its agent would start them, replaying at ``speed``.

    Every :data:`TICK_S` of replay time, each robot's scans due by then are integrated; a
    map the change gate lets through is a new version, and a version starts an epoch when
    :func:`agent.sources.epoch_due` says so against the epoch's first map, or when it is the
    source's last (the agent's node does the same).

    Returns
    -------
    epochs : ``{robot: [Epoch, ...]}`` in time order.
    versions : ``{"t", "robot", "cursor"}`` per version, the replay's progress as
        :func:`bench.fleet_accuracy.overlap_history` reads it.
    """
    wall = {}
    for r, src in growing.sources.items():
        stamps = compress_gaps(np.array([s.timestamp for s in src.scans]), speed)
        wall[r] = (stamps - stamps[0]) / speed
    gates = {r: ChangeGate(NodeOptions.min_change, NodeOptions.min_interval) for r in wall}
    epochs: dict[str, list[Epoch]] = {r: [] for r in wall}
    versions: list[dict] = []
    pending = dict.fromkeys(wall, False)
    for step in itertools.count():
        t = round(step * TICK_S, 3)
        for r, src in growing.sources.items():
            due = int(np.searchsorted(wall[r], t, side="right"))
            if due > src.cursor:
                growing.advance(r, due)
                pending[r] = True
            final = src.done
            if not pending[r] or not gates[r].due(src.grid(), t, final=final):
                # a last map no cell of which changed class is not published at all
                pending[r] = pending[r] and not final
                continue
            pending[r] = False
            sent = on_the_wire(src.grid())
            versions.append({"t": t, "robot": r, "cursor": src.cursor})
            base = epochs[r][-1].grid if epochs[r] else None
            if final or epoch_due(base, sent, NodeOptions.epoch_change):
                epochs[r].append(Epoch(r, t, src.cursor, sent, final))
        if all(src.done for src in growing.sources.values()) and not any(pending.values()):
            return _with_final(epochs, growing, t), versions
    raise AssertionError("unreachable: itertools.count does not end")


def _with_final(
    epochs: dict[str, list[Epoch]], growing: fa.GrowingMaps, t: float
) -> dict[str, list[Epoch]]:
    """``epochs``, each robot's ending with its final map: one whose last map the gate held
    back (no cell changed class) ends with that map, at ``t``, so that the final search
    always sees the whole segment."""
    out = {}
    for r, es in epochs.items():
        src = growing.sources[r]
        ended = bool(es) and es[-1].final
        out[r] = es if ended else [*es, Epoch(r, t, src.cursor, on_the_wire(src.grid()), True)]
    return out


def epoch_pairs(first: Sequence[Epoch], second: Sequence[Epoch]) -> list[tuple[Epoch, Epoch]]:
    """Every pair of the two robots' current epochs, in the time order they appeared: a new
    pair each time either robot starts an epoch, from the moment both have one."""
    events = sorted([*first, *second], key=lambda e: (e.t, e.robot))
    current: dict[str, Epoch] = {}
    out = []
    for e in events:
        current[e.robot] = e
        if len(current) == 2:
            out.append((current[first[0].robot], current[second[0].robot]))
    return out


def epochs_begun(starts: Sequence[float], start: float, end: float) -> int:
    """Epochs begun (at times ``starts``) in ``(start, end]``, negative when ``end < start``:
    the count :func:`bench.fleet_history.pair_delays` takes from the agents' counters."""
    return sum(1 for t in starts if t <= end) - sum(1 for t in starts if t <= start)


@dataclass(frozen=True)
class Search:
    """One search of a pair at one epoch pair, judged against the truth."""

    t: float
    epochs: int
    accepted: bool
    margin: float | None
    right: bool
    state: str

    def as_json(self) -> dict:
        return {
            "t": self.t,
            "epochs": self.epochs,
            "accepted": self.accepted,
            "margin": None if self.margin is None else round(self.margin, 3),
            "right": self.right,
            "state": self.state,
        }


class Trust:
    """A lone pair's link state over its searches, by the agent's own trust rules."""

    def __init__(self, min_margin: float) -> None:
        self.min_margin = min_margin
        self.state: str | None = None
        self.margin: float | None = None
        self.matrix: np.ndarray | None = None

    def decide(self, res: Registration, b: Grid, final: bool) -> str:
        """The state of the pair after the search ``res`` on map ``b`` of a new epoch pair;
        ``final``: both maps are their robots' last."""
        held = self.matrix is not None and trust.holds(self.matrix, res.matrix, b)
        standing = trust.standing_accept(self.state, self.margin, self.margin, self.min_margin)
        verdict = trust.first_verdict(
            res.accepted, res.margin, True, res.reason, self.min_margin,
            previous=self.state, held=held, searched=True, standing=standing,
        )  # fmt: skip
        if final and trust.provisional(verdict.state, res.margin, self.min_margin):
            verdict = trust.settled_verdict(res.margin, None, None)
        self.state, self.margin, self.matrix = verdict.state, res.margin, res.matrix
        return verdict.state


def pair_floor(
    first: Sequence[Epoch],
    second: Sequence[Epoch],
    overlap_at: float,
    truth: np.ndarray,
    register: RegisterFn,
    tol: fh.Tolerance,
) -> dict:
    """Search one pair at each of its epoch pairs until the merge accepts the right pose
    above :data:`agent.trust.HIGH_BAR`, then once more on the final maps.

    Parameters
    ----------
    first, second : the two robots' epochs (the link's ``a`` and ``b``).
    overlap_at : replay time the pair's true overlap first reached the threshold.
    truth : the true B-pixel -> A-pixel matrix.
    register : the agent's registration.
    tol : how far from ``truth`` a pose is still right.

    Returns
    -------
    dict
        ``floors``: per floor of :data:`FLOORS`, ``{"epochs", "seconds"}`` or None if never
        reached; ``searches``: each search (:class:`Search`); ``final``: the search on the
        final maps.
    """
    rules = Trust(MergeParams().min_margin)
    searches: list[Search] = []
    pairs = epoch_pairs(first, second)

    def search(ea: Epoch, eb: Epoch) -> Search:
        t = max(ea.t, eb.t)
        res = register(ea.grid, eb.grid)
        right = tol.allows(link_error(res.matrix, truth, eb.grid.shape))
        state = rules.decide(res, eb.grid, ea.final and eb.final)
        begun = sum(epochs_begun([e.t for e in es], overlap_at, t) for es in (first, second))
        return Search(t, begun, res.accepted, res.margin, right, state)

    for ea, eb in pairs:
        searches.append(search(ea, eb))
        if searches[-1].accepted and searches[-1].right and _high(searches[-1].margin):
            break
    # stopped early, the final maps are searched once more, after the searches kept
    final = searches[-1] if len(searches) == len(pairs) else search(*pairs[-1])
    reached = {
        "merge": lambda s: s.accepted and s.right,
        "trust": lambda s: s.right and s.state in trust.IN_MAP,
        "high": lambda s: s.accepted and s.right and _high(s.margin),
    }
    return {
        "floors": {name: _first(searches, test, overlap_at) for name, test in reached.items()},
        "searches": [s.as_json() for s in searches],
        "final": final.as_json(),
    }


def _high(margin: float | None) -> bool:
    return margin is None or margin >= trust.HIGH_BAR


def _first(searches: Sequence[Search], test: Callable[[Search], bool], start: float) -> dict | None:
    hit = next((s for s in searches if test(s)), None)
    return None if hit is None else {"epochs": hit.epochs, "seconds": round(hit.t - start, 2)}


def run_case(building: fa.Building, n: int, seed: int, settings: fa.Settings) -> dict:
    """The floor of every pair of ``n`` robots on ``building`` in the frames of ``seed``, as
    the fleet accuracy bench ran them."""
    specs = fa.fleet_specs(building, n, seed)
    growing = fa.GrowingMaps(specs)
    speed = fa.replay_speed(growing, settings.log_seconds)
    truth = growing.truth()
    epochs, versions = epochs_of(growing, speed)
    overlaps = fa.overlap_history(fa.GrowingMaps(specs), versions)
    register = merge_registration()
    pairs = {}
    for pair in sorted({o["pair"] for o in overlaps}):
        start = fh.first_reaching(overlaps, pair, settings.min_overlap)
        if start is None:
            continue
        a, b = pair.split("-")
        true = true_matrix(truth.world_to_pixel[a], truth.world_to_pixel[b])
        pairs[pair] = {"overlap_at": start} | pair_floor(
            epochs[a], epochs[b], start, true, register, settings.tolerance
        )
    return {
        "building": building.name,
        "robots": n,
        "seed": seed,
        "speed": round(speed, 2),
        "epochs": {r: [[e.t, e.cursor] for e in es] for r, es in epochs.items()},
        "pairs": pairs,
    }


# ------------------------------------------------------------------------------ the fleet


def fleet_delays(path: Path) -> dict[tuple[str, int, int], dict[str, dict]]:
    """The delays the fleet accuracy bench measured: ``{(building, N, seed): {pair: delay}}``
    (:func:`bench.fleet_history.pair_delays`); empty if ``path`` does not exist."""
    if not path.is_file():
        return {}
    cases = json.loads(path.read_text())["cases"]
    return {
        (c["building"], c["robots"], c["seed"]): {d["pair"]: d for d in c["summary"]["delays"]}
        for c in cases
    }


# ------------------------------------------------------------------------------ report


def chain_floors(case: Mapping) -> dict[str, dict | None]:
    """Per pair of a case, the first time the right links the trust rules let in join its two
    robots, directly or through others: ``{"epochs", "seconds"}`` from its overlap reaching
    the threshold (as :func:`pair_floor`'s floors), None if never.

    Each searched pair's link stands as its latest search left it, and after its last one
    (a search stopped at the high floor) as that.  Links of pairs whose overlap never
    reached the threshold were not searched, and join nothing here.
    """
    events = sorted(
        (s["t"], pair, s["right"] and s["state"] in trust.IN_MAP)
        for pair, p in case["pairs"].items()
        for s in p["searches"]
    )
    robots = list(case["epochs"])
    inside: dict[tuple[str, str], bool] = {}
    joined: dict[str, float] = {}
    for t, group in itertools.groupby(events, key=lambda e: e[0]):
        for _, pair, ok in group:
            inside[tuple(pair.split("-"))] = ok
        groups = components(robots, [p for p, ok in inside.items() if ok])
        for pair in case["pairs"]:
            a, b = pair.split("-")
            if pair not in joined and any(a in g and b in g for g in groups):
                joined[pair] = t
    out: dict[str, dict | None] = {}
    for pair, p in case["pairs"].items():
        if pair not in joined:
            out[pair] = None
            continue
        starts = [[t for t, _ in case["epochs"][r]] for r in pair.split("-")]
        begun = sum(epochs_begun(ts, p["overlap_at"], joined[pair]) for ts in starts)
        out[pair] = {"epochs": begun, "seconds": round(joined[pair] - p["overlap_at"], 2)}
    return out


def _values(case: Mapping, floor: str, key: str) -> list[float]:
    found = (
        chain_floors(case).values()
        if floor == "chain"
        else (p["floors"][floor] for p in case["pairs"].values())
    )
    return [f[key] for f in found if f is not None]


def _fleet_values(fleet: Mapping[str, Mapping], key: str) -> list[float]:
    return [d[key] for d in fleet.values() if d[key] is not None]


def _wrong(case: Mapping) -> tuple[int, int]:
    """Searches that accepted a wrong pose, and those the trust rules let into the map."""
    found = [s for p in case["pairs"].values() for s in p["searches"] if s["accepted"]]
    wrong = [s for s in found if not s["right"]]
    return len(wrong), sum(s["state"] in trust.IN_MAP for s in wrong)


def _unplaced(case: Mapping) -> int:
    """Pairs whose final maps the merge does not accept at the right pose."""
    return sum(not (p["final"]["accepted"] and p["final"]["right"]) for p in case["pairs"].values())


def table(cases: Sequence[Mapping], fleet: Mapping) -> str:
    """One markdown row per building, N and seed: the floors beside the fleet's delays."""
    head = (
        "| building | N | seed | pairs reaching overlap "
        "| merge / trust / chain / high floor reached "
        "| floor epochs merge / trust / chain / high (median) | fleet epochs (median / max) "
        "| floor s merge / trust / chain (median) | fleet s (median) | wrong accepts (let in) "
        "| pairs not placed on final maps |"
    )
    lines = [head, "|" + "---|" * 11]
    for c in cases:
        measured = fleet.get((c["building"], c["robots"], c["seed"]), {})
        reached = " / ".join(str(len(_values(c, f, "epochs"))) for f in FLOORS)
        eps = " / ".join(_median(_values(c, f, "epochs"), ".0f") for f in FLOORS)
        secs = " / ".join(_median(_values(c, f, "seconds"), ".1f") for f in FLOORS[:3])
        fleet_eps = _fleet_values(measured, "epochs")
        wrong, let_in = _wrong(c)
        lines.append(
            f"| {c['building']} | {c['robots']} | {c['seed']} | {len(c['pairs'])} | {reached} "
            f"| {eps} | {_median(fleet_eps, '.0f')} / {_max(fleet_eps)} | {secs} "
            f"| {_median(_fleet_values(measured, 'seconds'), '.1f')} | {wrong} ({let_in}) "
            f"| {_unplaced(c)} |"
        )
    return "\n".join(lines)


def _median(values: Sequence[float], fmt: str) -> str:
    return format(float(np.median(values)), fmt) if values else "-"


def _max(values: Sequence[float]) -> str:
    return f"{max(values):.0f}" if values else "-"


def pooled(cases: Sequence[Mapping], fleet: Mapping) -> dict[str, str]:
    """The whole run's numbers: median floors and the fleet's, over every pair."""
    out = {}
    for f in FLOORS:
        eps = [v for c in cases for v in _values(c, f, "epochs")]
        secs = [v for c in cases for v in _values(c, f, "seconds")]
        within = sum(v <= 2 for v in eps)
        out[f"{f} floor"] = (
            f"{_median(eps, '.1f')} epochs, {_median(secs, '.1f')} s (median of {len(eps)} "
            f"pairs reached); {within} pairs within 2 epochs"
        )
    measured = [fleet.get((c["building"], c["robots"], c["seed"]), {}) for c in cases]
    eps = [v for m in measured for v in _fleet_values(m, "epochs")]
    secs = [v for m in measured for v in _fleet_values(m, "seconds")]
    out["fleet"] = (
        f"{_median(eps, '.1f')} epochs, {_median(secs, '.1f')} s (median of {len(eps)} pairs "
        f"placed); {sum(v <= 2 for v in eps)} pairs within 2 epochs"
    )
    pairs = sum(len(c["pairs"]) for c in cases)
    out["pairs not placed on final maps"] = f"{sum(map(_unplaced, cases))} of {pairs}"
    wrong = [_wrong(c) for c in cases]
    gaps = [
        d["epochs"] - floor["epochs"]
        for c, m in zip(cases, measured, strict=True)
        for pair, floor in chain_floors(c).items()
        if floor is not None and (d := m.get(pair)) is not None and d["epochs"] is not None
    ]
    out["fleet minus chain floor, same pairs"] = (
        f"{_median(gaps, '.1f')} epochs (median of {len(gaps)} pairs); "
        f"{sum(g <= 0 for g in gaps)} pairs placed by the fleet no later than the floor"
    )
    out["wrong accepts"] = (
        f"{sum(w for w, _ in wrong)} searches, {sum(i for _, i in wrong)} let in by the "
        "trust rules of a lone pair"
    )
    return out


def markdown(
    cases: Sequence[Mapping], fleet: Mapping, argv: Sequence[str], wall: float | None
) -> str:
    """The result file; ``wall``: seconds the searches took, None when not recorded."""
    stamp = time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())
    took = "" if wall is None else f"; wall time {wall / 60:.1f} min"
    bullets = "\n".join(f"- {k}: {v}" for k, v in pooled(cases, fleet).items())
    return (
        "# Delay floor\n\n"
        f"`{' '.join(['python3 -m bench delay_floor', *argv])}` on {os.cpu_count()} cores "
        f"(shared with other jobs), {stamp}{took}.\n"
        "The fleet accuracy bench's segments and frames replayed offline, each robot's map "
        "cut where its agent starts a registration epoch, and the agent's registration run on "
        "every pair of epochs in time order, for every pair whose true overlap reaches the "
        "threshold.  Floor epochs: registration epochs both robots began from the overlap "
        "reaching the threshold to the first epoch pair at which the merge accepts the right "
        "pose (merge), the trust rules of a lone pair let it in (trust), the right links let "
        "in join the pair, directly or through other robots (chain), or its margin clears "
        f"{trust.HIGH_BAR} (high); the fleet's delay is from its accuracy run of the same "
        "cases.  Searches stop at the high floor.  Wrong accepts: searches that accepted a "
        "pose beyond the tolerance, and of those the ones the trust rules let in.\n\n"
        + table(cases, fleet)
        + "\n\n"
        + bullets
        + "\n"
    )


# ------------------------------------------------------------------------------ CLI


def parse_args(argv: Sequence[str]) -> argparse.Namespace:
    ap = fa.OneLineParser(
        prog="python3 -m bench delay_floor",
        description=__doc__.splitlines()[0],
        error_prefix="delay_floor",
    )
    ap.add_argument("--buildings", nargs="+", default=None, help="log:PATH or map:PATH.yaml")
    ap.add_argument("--robots", type=int, nargs="+", default=[2, 3, 4, 6])
    ap.add_argument("--quick", action="store_true", help="N=2,3 only")
    ap.add_argument("--seeds", type=int, nargs="+", default=[7])
    ap.add_argument("--min-overlap", type=float, default=fa.Settings.min_overlap)
    ap.add_argument("--fleet", type=Path, default=fa.RESULTS / "fleet-accuracy.json",
                    help="the fleet accuracy results to compare with")  # fmt: skip
    ap.add_argument("--out", type=Path, default=fa.RESULTS, help="directory of the results")
    ap.add_argument("--report-only", action="store_true",
                    help="rewrite delay-floor.md from --out's delay-floor.json")  # fmt: skip
    args = ap.parse_args(argv)
    if any(not 2 <= n <= 12 for n in args.robots):
        ap.error(f"--robots must be between 2 and 12, got {args.robots}")
    if not 0 < args.min_overlap <= 1:
        ap.error(f"--min-overlap must be in (0, 1], got {args.min_overlap}")
    if args.out.exists() and not args.out.is_dir():
        ap.error(f"--out is not a directory: {args.out}")
    if args.fleet.exists() and not args.fleet.is_file():
        ap.error(f"--fleet is not a file: {args.fleet}")
    return args


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    args = parse_args(argv)
    if args.report_only:
        return report_only(args.out, args.fleet)
    sizes = [n for n in args.robots if n <= 3] if args.quick else args.robots
    try:
        buildings = fa.buildings_of(argparse.Namespace(
            held_out=False, quick=False, buildings=args.buildings, robots=sizes,
        ))  # fmt: skip
        fleet = fleet_delays(args.fleet)
    except (fa.BenchError, ValueError, KeyError) as exc:
        print(f"delay_floor: {exc}", file=sys.stderr)
        return 2
    settings = fa.Settings(tuple(args.seeds), min_overlap=args.min_overlap)
    t_start = time.time()
    cases = []
    for building, seed, n in itertools.product(buildings, settings.seeds, sizes):
        print(f"delay_floor: {building.name} N={n} seed {seed} ...", file=sys.stderr, flush=True)
        cases.append(run_case(building, n, seed, settings))
        args.out.mkdir(parents=True, exist_ok=True)
        (args.out / "delay-floor.md").write_text(
            markdown(cases, fleet, argv, time.time() - t_start)
        )
        record = {"argv": argv, "wall_s": round(time.time() - t_start, 1), "cases": cases}
        (args.out / "delay-floor.json").write_text(json.dumps(record, indent=1))
    print((args.out / "delay-floor.md").read_text())
    return 0


def report_only(out: Path, fleet_json: Path) -> int:
    """Rewrite ``out/delay-floor.md`` from the recorded ``out/delay-floor.json``; 2 (one line
    on stderr) if that cannot be read."""
    path = out / "delay-floor.json"
    try:
        record = json.loads(path.read_text())
        md = markdown(
            record["cases"], fleet_delays(fleet_json), record["argv"], record.get("wall_s")
        )
    except (OSError, ValueError, KeyError, TypeError) as exc:
        print(f"delay_floor: cannot report {path}: {exc}", file=sys.stderr)
        return 2
    (out / "delay-floor.md").write_text(md)
    print(md)
    return 0


if __name__ == "__main__":
    sys.exit(main())
