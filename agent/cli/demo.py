"""``pgvd demo``: a fleet of agents on this machine maps a building together, no server.

Each agent replays an overlapping segment of one run in a random frame of its own
(:mod:`agent.scenario`), peer to peer over Zenoh on localhost.  The run is

- by default the bundled Intel Research Lab log (``agent/data``, CC-BY 1.0,
  recorded by Dirk Haehnel; Radish, Howard and Roy 2003);
- ``--log LOG``: your own CARMEN laser log (``FLASER`` lines, gzip or plain),
  e.g. one of the Radish "corrected" logs;
- ``--map IMAGE.yaml``: a ROS map_server map of your building, which simulated
  robots drive through with a simulated laser scanner (``sim:`` sources).

A run that cannot give every robot a map (missing, unreadable, no scans, no room
to drive, too short for ``--robots``) is refused in one line before any agent
starts.  The demo prints live progress, then writes ``--out``:

- ``<robot>/global.png`` (and ``.yaml``/``.pgm``): each agent's global map;
  ``<robot>/agent.log``: what the agent did;
- ``side_by_side.png``: local maps (top row) and each agent's global map (bottom
  row) with the robots it placed and its links drawn, the verdict in the title;
- ``report.json``: the verdict and why, per robot its placement error against the
  truth, per agent the robots known, the accepted links with their error against
  the true frames, the global map's hash, the bytes sent, the time to converge.

``--out`` must be new, empty, or a directory of an earlier demo holding only the
files that demo wrote; those are replaced, any other file makes the demo refuse
to start.

The verdict is about placement.  PASSED (exit 0) when all agents hold the same
global map and in it every robot that truly overlaps another (true overlap >=
``--min-overlap``) is placed, all together, within ``--max-deg`` / ``--max-cells``
of the truth.  A pair placed right through other robots needs no direct link of
its own: such pairs are listed, not failed.  FAILED (exit 1) otherwise.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from agent.cli import outdir
from agent.cli.common import EXIT_FAILED, EXIT_OK, CliError
from agent.evaluate import link_error, placement_errors, true_matrix, true_overlap
from agent.launcher import LocalFleet, agreement, sources_done
from agent.scenario import LOG, check_run, known_pose, random_frames, segments
from agent.sidebyside import AgentView, write_side_by_side
from agent.state import StateDir
from pgvd.grid import Grid


def configure(p: argparse.ArgumentParser) -> None:
    """Add the arguments of ``pgvd demo`` to its parser."""
    p.description = __doc__
    p.add_argument("--robots", type=int, default=3, help="number of agents (2-12)")
    p.add_argument(
        "--out",
        type=Path,
        default=Path("demo-out"),
        help="output directory: new, empty, or an earlier demo's (default demo-out)",
    )
    p.add_argument("--speed", type=float, default=100.0, help="log replay speed x real time")
    p.add_argument("--seed", type=int, default=1, help="seed of the agents' random frames")
    p.add_argument("--timeout", type=float, default=180.0, help="give up after this many s")
    p.add_argument("--max-deg", type=float, default=2.0, help="largest rotation error allowed")
    p.add_argument("--max-cells", type=float, default=3.0, help="largest translation error")
    p.add_argument(
        "--min-overlap", type=float, default=0.3, help="true overlap that must be placed"
    )
    p.add_argument(
        "--known-poses",
        action="store_true",
        help="give every agent each robot's true initial pose (--known-pose): pairs are "
        "checked there first and searched only where the check fails",
    )
    run_group = p.add_mutually_exclusive_group()
    run_group.add_argument(
        "--log",
        type=Path,
        help="a CARMEN laser log (FLASER lines, .log or .log.gz) the robots split "
        "(default: the bundled Intel Research Lab log)",
    )
    run_group.add_argument(
        "--map",
        type=Path,
        help="a ROS map_server map (IMAGE.yaml) that simulated robots drive through",
    )
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    if not 2 <= args.robots <= 12:
        raise CliError("--robots must be between 2 and 12")
    if args.speed <= 0 or args.timeout <= 0:
        raise CliError("--speed and --timeout must be > 0")
    if not args.max_deg > 0 or not args.max_cells > 0:
        raise CliError("--max-deg and --max-cells must be > 0")
    if not 0 < args.min_overlap <= 1:
        raise CliError(f"--min-overlap must be in (0, 1], got {args.min_overlap}")
    kind, path = ("sim", args.map) if args.map is not None else ("carmen", args.log or LOG)
    try:
        check_run(kind, path, args.robots)
    except ValueError as exc:
        raise CliError(f"--{'map' if kind == 'sim' else 'log'}: {exc}") from None
    # the agents run in the project root, not here
    args.kind, args.path = kind, path.resolve()
    out: Path = args.out
    outdir.claim(out)
    try:
        report = _run_fleet(args, out)
    finally:
        outdir.record(out)  # also after a crash or ^C: the next run may replace these files
    _print_summary(report, out)
    return EXIT_OK if report["ok"] else EXIT_FAILED


def _run_fleet(args: argparse.Namespace, out: Path) -> dict:
    """Run the fleet until agreement or timeout; write report.json and side_by_side.png."""
    robots = [f"r{i + 1}" for i in range(args.robots)]
    frames = random_frames(args.robots, args.seed)
    what = "map" if args.kind == "sim" else "log"
    print(f"pgvd demo: {args.robots} agents, peer to peer on localhost, {what} {args.path.name}")
    # --verbose: each agent.log tells what its agent did, not only what went wrong
    common = ["--speed", str(args.speed), "--verbose"]
    if args.known_poses:
        for robot, frame in zip(robots, frames, strict=True):
            common.append("--known-pose=" + robot + "=" + ",".join(map(repr, known_pose(frame))))
    t_start = time.time()
    labels = {}
    with LocalFleet("demo", out, common) as fleet:
        for robot, seg, frame in zip(robots, segments(args.robots), frames, strict=True):
            spec = f"{args.kind}:{args.path}@{seg[0]}-{seg[1]}"
            fleet.add(robot, spec, ["--frame=" + ",".join(f"{v:.4f}" for v in frame)])
            labels[robot] = f"{seg[0]:.2f}-{seg[1]:.2f} of the {what}'s run"
            print(f"  {robot}: {labels[robot]}, frame {frame[2]:.0f} deg")
        agreed_at = _watch(fleet, args.timeout)
        statuses = fleet.statuses()
        dead = [r for r, a in fleet.agents.items() if not a.alive()]
    grids = _local_grids(fleet)
    report = evaluate(statuses, grids, agreed_at, t_start, dead, args)
    report["wall_s"] = round(time.time() - t_start, 3)
    (out / "report.json").write_text(json.dumps(report, indent=1, sort_keys=True))
    views = [
        AgentView(r, grids.get(r), labels[r], _global_map(a.out_dir), statuses.get(r))
        for r, a in sorted(fleet.agents.items())
    ]
    write_side_by_side(out / "side_by_side.png", views, grids, _title(report))
    return report


def _watch(fleet: LocalFleet, timeout: float) -> float | None:
    """Print progress until the agents agree on final maps; wall time of agreement or None."""
    deadline = time.monotonic() + timeout
    last = ""
    while time.monotonic() < deadline:
        statuses = fleet.statuses()
        line = _progress(statuses)
        if line != last:
            print(f"  [{time.strftime('%H:%M:%S')}] {line}", flush=True)
            last = line
        if sources_done(statuses) and agreement(statuses, _final_versions(statuses)):
            return time.time()
        if not all(a.alive() for a in fleet.agents.values()):
            print("  an agent died; see its agent.log", file=sys.stderr)
            return None
        time.sleep(0.25)
    print(f"  no agreement within {timeout:.0f} s", file=sys.stderr)
    return None


def _final_versions(statuses: dict[str, dict | None]) -> dict[str, int]:
    return {r: int(s["own_version"] or 0) for r, s in statuses.items() if s is not None}


def _progress(statuses: dict[str, dict | None]) -> str:
    parts = []
    for robot, s in sorted(statuses.items()):
        if s is None:
            parts.append(f"{robot}: starting")
            continue
        done, total = s["source"].get("progress", [0, 1])
        glob = s.get("global") or {}
        # the links between the robots' current versions: older versions' links stay in the
        # status (3 robots showed "links 6"), but only these hold the global map together
        links = sum(1 for ln in s.get("links", []) if ln["accepted"] and ln.get("current"))
        parts.append(
            f"{robot}: {100 * done // max(total, 1):3d}% "
            f"{s.get('counts', {}).get('versions_published', 0)} versions "
            f"knows {len(s.get('robots', {}))} links {links} "
            f"map {str(glob.get('digest', '-'))[:6]}{'*' if s.get('settled') else ''}"
        )
    return " | ".join(parts)


def _local_grids(fleet: LocalFleet) -> dict[str, Grid]:
    """Every robot's last persisted local map, from its own agent's state directory."""
    grids = {}
    for robot, agent in fleet.agents.items():
        maps, _ = StateDir(agent.state_dir).load_maps()
        if robot in maps:
            grids[robot] = maps[robot].grid
    return grids


def _global_map(out_dir: Path) -> Grid | None:
    from pgvd.io import MapFormatError, read_map

    try:
        return read_map(out_dir / "global.yaml")
    except (MapFormatError, OSError):
        return None


def evaluate(
    statuses: dict[str, dict | None],
    grids: dict[str, Grid],
    agreed_at: float | None,
    t_start: float,
    dead: list[str],
    args: argparse.Namespace,
) -> dict:
    """The report: placements and links against the truth, agreement, traffic, the verdict."""
    w2p = {r: np.array(s["source"]["world_to_pixel"]) for r, s in statuses.items() if s is not None}
    updates = [s.get("last_update") or 0.0 for s in statuses.values() if s]
    last_update = max(updates, default=0.0) or None
    robots = sorted(statuses)
    overlaps = {}
    for i, a in enumerate(robots):
        for b in robots[i + 1 :]:
            if a in grids and b in grids and a in w2p and b in w2p:
                overlaps[(a, b)] = true_overlap(grids[a], grids[b], true_matrix(w2p[a], w2p[b]))
    agents = {
        robot: _agent_report(s, grids, w2p, last_update, args)
        for robot, s in sorted(statuses.items())
    }
    linked = {ln["pair"] for a in agents.values() for ln in a.get("links_accepted", [])}
    false_links = sorted(
        {
            ln["pair"]
            for a in agents.values()
            for ln in a.get("links_accepted", [])
            if ln["error_deg"] > args.max_deg or ln["error_cells"] > args.max_cells
        }
    )
    to_place = [(a, b) for (a, b), f in sorted(overlaps.items()) if f >= args.min_overlap]
    must_place = sorted({r for pair in to_place for r in pair})
    placements = _placements(statuses, grids, w2p, args)
    hashes = {a.get("global_hash") for a in agents.values()}
    same = agreed_at is not None and len(hashes) == 1
    why = _failures(same, agreed_at, dead, must_place, placements)
    return {
        "ok": not why,
        "verdict": "FAILED" if why else "PASSED",
        "why": why,
        "same_global_map": same,
        "true_overlaps": {f"{a}-{b}": round(f, 3) for (a, b), f in overlaps.items()},
        "overlaps_to_link": [f"{a}-{b}" for a, b in to_place],
        "must_be_placed": must_place,
        "placements": placements,
        # truly overlapping pairs with no direct link, placed through the other robots
        "missing_links": [f"{a}-{b}" for a, b in to_place if f"{a}-{b}" not in linked],
        "false_links": false_links,
        "dead_agents": dead,
        "agreement_s_after_last_update": None
        if agreed_at is None or last_update is None
        else round(agreed_at - last_update, 3),
        "agreement_s_after_start": None if agreed_at is None else round(agreed_at - t_start, 3),
        "tolerance": {"deg": args.max_deg, "cells": args.max_cells},
        "agents": agents,
    }


def _agent_report(
    s: dict | None,
    grids: dict[str, Grid],
    w2p: dict[str, np.ndarray],
    last_update: float | None,
    args: argparse.Namespace,
) -> dict:
    """One agent's part of the report: what it holds, its current accepted links' errors."""
    if s is None:
        return {"status": None}
    links = []
    for ln in s.get("links", []):
        if not (ln["accepted"] and ln["current"]) or ln["a"] not in w2p or ln["b"] not in w2p:
            continue
        shape_b = grids[ln["b"]].shape if ln["b"] in grids else (1, 1)
        deg, cells = link_error(ln["matrix"], true_matrix(w2p[ln["a"]], w2p[ln["b"]]), shape_b)
        links.append(
            {
                "pair": f"{ln['a']}-{ln['b']}",
                "versions": [ln["version_a"], ln["version_b"]],
                "score": ln["score"],
                "error_deg": round(deg, 3),
                "error_cells": round(cells, 3),
                "decided_by": ln["decided_by"],
            }
        )
    settled_at = s.get("settled_at")
    return {
        "robots_known": {r: v["version"] for r, v in s.get("robots", {}).items()},
        "links_accepted": links,
        "global_hash": (s.get("global") or {}).get("digest"),
        "global_members": (s.get("global") or {}).get("members"),
        "bytes_sent": s.get("bytes_sent"),
        "bytes_received": s.get("bytes_received"),
        "merges": s.get("merges"),
        "registrations": {
            k: s.get("counts", {}).get(k, 0)
            for k in ("searches", "checks", "prior_checks", "prior_confirmed", "prior_failed")
        },
        "drops": s.get("drops"),
        "converged_s_after_last_update": None
        if settled_at is None or last_update is None
        else round(max(0.0, settled_at - last_update), 3),
    }


def _placements(
    statuses: dict[str, dict | None],
    grids: dict[str, Grid],
    w2p: dict[str, np.ndarray],
    args: argparse.Namespace,
) -> dict[str, dict]:
    """Per robot, where the global map put it against the truth.

    Read from the lowest robot id with a status: when the agents agree (the verdict asks
    it), every agent's components are the same.
    """
    seen = next((s for _, s in sorted(statuses.items()) if s is not None), None)
    out: dict[str, dict] = {r: {"placed_with": []} for r in statuses}
    if seen is None:
        return out
    shapes = {r: g.shape for r, g in grids.items()}
    for comp in seen.get("components", []):
        if len(comp["members"]) < 2:
            continue
        transforms = {r: np.asarray(m) for r, m in comp["transforms"].items()}
        errors = placement_errors(comp["anchor"], transforms, w2p, shapes)
        for robot in comp["members"]:
            deg, cells = errors.get(robot, (float("inf"), float("inf")))
            out[robot] = {
                "placed_with": list(comp["members"]),
                "anchor": comp["anchor"],
                "error_deg": round(deg, 3),
                "error_cells": round(cells, 3),
                "right": bool(deg <= args.max_deg and cells <= args.max_cells),
            }
    return out


def _failures(
    same: bool,
    agreed_at: float | None,
    dead: list[str],
    must_place: list[str],
    placements: dict[str, dict],
) -> list[str]:
    """Why the demo failed, one phrase each; empty if it passed."""
    why = [f"agent {r} died" for r in dead]
    if agreed_at is None:
        why.append("no agreement before the timeout")
    elif not same:
        why.append("agents hold different global maps")
    biggest = max(
        (p["placed_with"] for p in placements.values()),
        key=lambda members: sum(r in members for r in must_place),
        default=[],
    )
    apart = [r for r in must_place if r not in biggest]
    if apart:
        why.append(f"{', '.join(apart)} not placed with {', '.join(biggest) or 'anyone'}")
    for robot, p in sorted(placements.items()):
        if p["placed_with"] and not p["right"]:
            why.append(
                f"{robot} misplaced by {p['error_deg']:.1f} deg, {p['error_cells']:.1f} cells"
            )
    return why


def _title(report: dict) -> list[str]:
    """The picture's title: the verdict and why, then the pairs placed without a direct link."""
    placed = [r for r, p in report["placements"].items() if p["placed_with"]]
    if report["ok"]:
        head = (
            f"PASSED: {len(placed)} robots placed right in one global map held by all agents "
            f"(within {report['tolerance']['deg']} deg, {report['tolerance']['cells']} cells)"
        )
    else:
        head = "FAILED: " + "; ".join(report["why"])
    lines = [head]
    if report["missing_links"]:
        lines.append("placed through others, no direct link: " + ", ".join(report["missing_links"]))
    return lines


def _print_summary(report: dict, out: Path) -> None:
    print(f"\nresults in {out}/ (report.json, side_by_side.png, <robot>/global.png)")
    for robot, a in sorted(report["agents"].items()):
        if "links_accepted" not in a:
            print(f"  {robot}: no status")
            continue
        errs = ", ".join(
            f"{ln['pair']} {ln['error_deg']:.2f} deg {ln['error_cells']:.2f} cells"
            for ln in a["links_accepted"]
        )
        p = report["placements"][robot]
        where = (
            f"placed {p['error_deg']:.2f} deg {p['error_cells']:.2f} cells from the truth"
            if p["placed_with"]
            else "not placed"
        )
        print(
            f"  {robot}: {where}; map {str(a['global_hash'])[:12]} of "
            f"{','.join(a['global_members'] or [])}  sent {a['bytes_sent']} B  "
            f"links: {errs or 'none'}"
        )
    if report["missing_links"]:
        print(f"  placed through others, no direct link: {', '.join(report['missing_links'])}")
    if report["false_links"]:
        print(f"  links beyond the tolerance: {', '.join(report['false_links'])}")
    print(
        f"{_title(report)[0]}; agreement {report['agreement_s_after_last_update']} s after the "
        f"last map update, wall time {report['wall_s']} s"
    )
