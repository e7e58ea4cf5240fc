"""Bridges: how much of a fleet's placement rests on lone links that no cycle checks.

A link of the global map is a *bridge* when no other path of links joins its two robots:
nothing in the fleet but that one pair decision says where one side lies from the other.
A link on a cycle has a second opinion, the composition of the others (the pose graph's
cycle consistency, eqs. (4)-(8) propagated through the robust solve).  A fleet rule that let
only links on cycles into the global map would trade placement and delay for that second
opinion.  This study reads the results of :mod:`bench.fleet_accuracy` and measures the
trade on what the agents really showed:

- **placement**: robots placed at the end (in a merged map of the last global map shown),
  and how many of them share a *2-edge-connected* group (robots joined by links on cycles,
  once every bridge is cut) with another robot: those would stay placed;
- **delay**: for truly overlapping pairs of fleets of 3 or more robots, the seconds from
  the pair first shown together (the bench's ``placed_at``) to the pair first shown in one
  2-edge-connected group, by any agent;
- **wrong spells**: for every spell of a robot shown wrong, whether the agent's global map
  at the spell's start held that robot by bridges alone (no cycle of links through it),
  and the decisions that held it;
- **how links came in**: the last decision logged on each link of the last global maps (a
  search, a check from the links' prediction, a cycle, a provisional accept confirmed on
  final maps, a check carrying an accept forward).  A check starts from the pose the links
  predict, so a cycle it closes repeats the decisions that predicted it; only searches,
  which weigh every pose, are independent opinions.

The links in a global map are those it used (the ``used`` of each component the bench
recorded); a rule withholding bridges would also withhold the links that later close
cycles until they do, so the delay is a lower bound.

Run: ``python3 -m bench bridges [FILE ...]`` (default the development results,
``bench/results/fleet-accuracy.json``); writes ``bridges.md`` and ``.json`` to ``--out``
(default ``bench/results``).  It reads results only, runs no fleet, and sets nothing.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
from collections import Counter
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path

from bench import fleet_accuracy as fa
from pgvd.posegraph import components

Edge = tuple[str, str]


def _connected(nodes: Iterable[str], edges: Iterable[Edge]) -> list[set[str]]:
    """The connected components of the graph ``nodes``, ``edges``, as sets."""
    return [set(group) for group in components(nodes, edges)]


def bridges(nodes: Sequence[str], edges: Sequence[Edge]) -> set[frozenset[str]]:
    """The links of ``edges`` that no other path joins: each cut alone splits its robots.

    Global maps hold a few robots, so each link is cut in turn (``O(E (V + E))``).
    """
    out = set()
    for i, (a, b) in enumerate(edges):
        rest = edges[:i] + edges[i + 1 :]
        if not any(a in g and b in g for g in _connected(nodes, rest)):
            out.add(frozenset((a, b)))
    return out


def cycle_groups(component: Mapping) -> list[set[str]]:
    """The 2-edge-connected groups of one recorded component: its members joined by its used
    links once every bridge is cut (a lone robot is a group of one)."""
    nodes = list(component["members"])
    edges = [(str(a), str(b)) for a, b in component["used"]]
    cut = bridges(nodes, edges)
    return _connected(nodes, [e for e in edges if frozenset(e) not in cut])


def _map_groups(global_map: Mapping) -> list[set[str]]:
    """The 2-edge-connected groups of every component of ``global_map``."""
    return [g for comp in global_map["components"] for g in cycle_groups(comp)]


def _together(groups: Sequence[set[str]], a: str, b: str) -> bool:
    """Whether ``a`` and ``b`` share one of ``groups`` (:func:`_map_groups`)."""
    return any(a in g and b in g for g in groups)


def _on_cycle(groups: Sequence[set[str]], robot: str) -> bool:
    """Whether ``robot`` shares one of ``groups`` (:func:`_map_groups`) with another robot."""
    return any(robot in g and len(g) > 1 for g in groups)


def _map_at(maps: Sequence[Mapping], agent: str, t: float) -> int | None:
    """The index in ``maps`` of the global map ``agent`` showed at ``t``: its last before or
    at ``t``."""
    shown = [i for i, m in enumerate(maps) if m["agent"] == agent and m["t"] <= t + 1e-6]
    return shown[-1] if shown else None


def _decisions(global_map: Mapping, case: Mapping, t: float, robot: str | None = None) -> list:
    """The used links of ``global_map`` (those at ``robot`` only, when given), each as
    ``(pair, how, margin)``: the last decision on the pair any agent logged by ``t``, which
    says how the link came in (a search, a check from the links' prediction, a cycle, final
    maps...)."""
    last: dict[str, Mapping] = {}
    for rec in case["history"]["links"]:
        if rec["t"] <= t + 1e-6:
            last[rec["pair"]] = rec
    out = []
    for comp in global_map["components"]:
        for a, b in comp["used"]:
            if robot is None or robot in (a, b):
                rec = last.get("-".join(sorted((a, b))), {})
                out.append(("-".join(sorted((a, b))), rec.get("how", "?"), rec.get("margin")))
    return out


def study_case(case: Mapping) -> dict:
    """Placement, delay and wrong spells of one fleet run (module docstring)."""
    maps = case["history"]["maps"]
    # each map's groups once: every pair's delay and every spell reads them
    groups = [_map_groups(m) for m in maps]
    last = maps[-1] if maps else {"components": []}
    placed = sorted(
        r for comp in last["components"] if len(comp["members"]) > 1 for r in comp["members"]
    )
    on_cycle = [r for r in placed if _on_cycle(groups[-1] if groups else [], r)]
    extra, never = [], 0
    # two robots hold one link, which no cycle can check: only larger fleets have a delay
    placed_pairs = [d for d in case["summary"]["delays"] if d.get("placed_at") is not None]
    for delay in placed_pairs if case["robots"] >= 3 else []:
        a, b = delay["pair"].split("-")
        times = (m["t"] for m, g in zip(maps, groups, strict=True) if _together(g, a, b))
        shown = next(times, None)
        if shown is None:
            never += 1
        else:
            extra.append(round(max(shown - delay["placed_at"], 0.0), 3))
    spells = []
    for spell in case["summary"]["wrong_spells"]:
        i = _map_at(maps, spell["agent"], spell["start"])
        bridged = i is not None and not _on_cycle(groups[i], spell["robot"])
        held_by = [] if i is None else _decisions(maps[i], case, spell["start"], spell["robot"])
        spells.append({**spell, "by_bridges": bridged, "held_by": held_by})
    return {
        "building": case["building"],
        "robots": case["robots"],
        "seed": case["seed"],
        "placed": placed,
        "on_cycle": on_cycle,
        "extra_s": extra,
        "never_on_cycle": never,
        "came_in": [how for _, how, _ in _decisions(last, case, last.get("t", 0.0))],
        "wrong_spells": spells,
    }


def _stats(values: Sequence[float]) -> str:
    """``median / p90 / max`` of ``values``, or a dash."""
    if not values:
        return "-"
    ordered = sorted(values)
    p90 = ordered[min(len(ordered) - 1, int(0.9 * len(ordered)))]
    return f"{statistics.median(ordered):.1f} / {p90:.1f} / {ordered[-1]:.1f}"


def table(rows: Sequence[Mapping]) -> str:
    """One line per run, then the pooled line."""
    out = [
        "| building | N | seed | placed at the end | of them on a cycle | extra s to a cycle, "
        "median / p90 / max (N >= 3) | wrong spells | of them held by bridges alone |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        spells = r["wrong_spells"]
        out.append(
            f"| {r['building']} | {r['robots']} | {r['seed']} | {len(r['placed'])} | "
            f"{len(r['on_cycle'])} | {_stats(r['extra_s'])} | {len(spells)} | "
            f"{sum(s['by_bridges'] for s in spells)} |"
        )
    spells = [s for r in rows for s in r["wrong_spells"]]
    out.append(
        f"| **all** | | | {sum(len(r['placed']) for r in rows)} | "
        f"{sum(len(r['on_cycle']) for r in rows)} | "
        f"{_stats([e for r in rows for e in r['extra_s']])} | {len(spells)} | "
        f"{sum(s['by_bridges'] for s in spells)} |"
    )
    return "\n".join(out)


def markdown(rows: Sequence[Mapping], sources: Sequence[Path], argv: Sequence[str]) -> str:
    """The report: what was read, the table, what it means."""
    never = sum(r["never_on_cycle"] for r in rows)
    return "\n".join([
        "# Bridges: placement that rests on lone links",
        "",
        f"`python3 -m bench bridges {' '.join(argv)}`, reading "
        + ", ".join(f"`{p.name}`" for p in sources) + ".",
        "",
        "A bridge is a link of a global map that no other path of links joins: only that "
        "pair decision places one side from the other. *On a cycle*: the robot shares a "
        "group with another once every bridge is cut (2-edge-connected). *Extra s*: from a "
        "truly overlapping pair first shown together to first shown on a cycle, a lower "
        "bound of what a rule admitting only links on cycles would add. *Held by bridges "
        "alone*: the agent's global map at the spell's start placed the wrong robot by "
        "bridges only.",
        "",
        table(rows),
        "",
        f"Pairs of fleets of 3 or more placed but never shown on a cycle: {never}.",
        "",
        "How the links of the last global maps came in (the last decision logged on each "
        "pair): " + _counts(how for r in rows for how in r["came_in"]) + ".",
        "",
        *_spell_lines(rows),
    ])  # fmt: skip


def _counts(values: Iterable[str]) -> str:
    """``value count`` pairs, most common first."""
    return ", ".join(f"{v} {n}" for v, n in Counter(values).most_common()) or "none"


def _spell_lines(rows: Sequence[Mapping]) -> list[str]:
    """One line per wrong spell: where, how long, and the decisions of the links that held
    the wrong robot when it began."""
    lines = [
        f"- {r['building']} N={r['robots']}: agent {s['agent']} showed {s['robot']} wrong "
        f"for {s['seconds']:.1f} s, held by "
        + ("bridges alone" if s["by_bridges"] else "a cycle")
        + ": " + "; ".join(f"{pair} {how} {margin}" for pair, how, margin in s["held_by"])
        for r in rows
        for s in r["wrong_spells"]
    ]  # fmt: skip
    return ["Wrong spells:", "", *lines, ""] if lines else []


def parse_args(argv: Sequence[str]) -> argparse.Namespace:
    ap = fa.OneLineParser(
        prog="python3 -m bench bridges",
        description=__doc__.splitlines()[0],
        error_prefix="bridges",
    )
    ap.add_argument("files", type=Path, nargs="*", default=[fa.RESULTS / "fleet-accuracy.json"],
                    help="fleet_accuracy result files (JSON)")  # fmt: skip
    ap.add_argument("--out", type=Path, default=fa.RESULTS, help="directory of the results")
    ap.add_argument("--name", default="bridges", help="results named NAME.md and NAME.json")
    args = ap.parse_args(argv)
    for path in args.files:
        if not path.is_file():
            ap.error(f"no such result file: {path}")
    if args.out.exists() and not args.out.is_dir():
        ap.error(f"--out is not a directory: {args.out}")
    return args


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    args = parse_args(argv)
    try:
        cases = [c for p in args.files for c in json.loads(p.read_text())["cases"]]
        rows = [study_case(c) for c in cases]
    except (OSError, ValueError, KeyError, TypeError) as exc:
        print(f"bridges: cannot read the fleet results: {exc}", file=sys.stderr)
        return 2
    md = markdown(rows, args.files, argv)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / f"{args.name}.md").write_text(md)
    (args.out / f"{args.name}.json").write_text(json.dumps({"argv": argv, "rows": rows}, indent=1))
    print(md)
    return 0


if __name__ == "__main__":
    sys.exit(main())
