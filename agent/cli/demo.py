"""``pgvd demo``: a fleet of agents on this machine maps the Intel lab together, no server.

Each agent replays an overlapping segment of the bundled Intel Research Lab log
(``agent/data``, CC-BY 1.0, recorded by Dirk Haehnel; Radish, Howard and Roy 2003) in a
random frame of its own (:mod:`agent.scenario`), peer to peer over Zenoh on localhost.
The demo prints live progress, then writes ``--out``:

- ``<robot>/global.png`` (and ``.yaml``/``.pgm``): each agent's global map;
- ``side_by_side.png``: local maps (top row) and each agent's global map (bottom row);
- ``report.json``: per agent the robots known, the accepted links with their error
  against the true frames, the global map's hash, the bytes sent, the time to converge.

``--out`` must be new, empty, or a directory of an earlier demo holding only the files that
demo wrote; those are replaced, any other file makes the demo refuse to start.

Exit 0 only if all agents hold the same global map, every truly overlapping pair was
linked and no link is false (beyond ``--max-deg`` / ``--max-cells``); 1 otherwise.
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
from agent.evaluate import link_error, true_matrix, true_overlap
from agent.launcher import LocalFleet, agreement, sources_done
from agent.scenario import LOG, known_pose, random_frames, segments
from agent.state import StateDir


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
        "--min-overlap", type=float, default=0.3, help="true overlap that must be linked"
    )
    p.add_argument(
        "--known-poses",
        action="store_true",
        help="give every agent each robot's true initial pose (--known-pose): pairs are "
        "checked there first and searched only where the check fails",
    )
    p.add_argument("--log", type=Path, default=LOG, help=argparse.SUPPRESS)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    if not 2 <= args.robots <= 12:
        raise CliError("--robots must be between 2 and 12")
    if not args.log.is_file():
        raise CliError(f"log not found: {args.log}")
    if args.speed <= 0 or args.timeout <= 0:
        raise CliError("--speed and --timeout must be > 0")
    if not args.max_deg > 0 or not args.max_cells > 0:
        raise CliError("--max-deg and --max-cells must be > 0")
    if not 0 < args.min_overlap <= 1:
        raise CliError(f"--min-overlap must be in (0, 1], got {args.min_overlap}")
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
    print(f"pgvd demo: {args.robots} agents, peer to peer on localhost, log {args.log.name}")
    common = ["--speed", str(args.speed)]
    if args.known_poses:
        for robot, frame in zip(robots, frames, strict=True):
            common.append("--known-pose=" + robot + "=" + ",".join(map(repr, known_pose(frame))))
    t_start = time.time()
    with LocalFleet("demo", out, common) as fleet:
        for robot, seg, frame in zip(robots, segments(args.robots), frames, strict=True):
            spec = f"carmen:{args.log}@{seg[0]}-{seg[1]}"
            fleet.add(robot, spec, ["--frame=" + ",".join(f"{v:.4f}" for v in frame)])
            print(
                f"  {robot}: scans {seg[0]:.2f}-{seg[1]:.2f} of the log, frame {frame[2]:.0f} deg"
            )
        agreed_at = _watch(fleet, args.timeout)
        statuses = fleet.statuses()
        dead = [r for r, a in fleet.agents.items() if not a.alive()]
    report = evaluate(fleet, statuses, agreed_at, t_start, args)
    report["dead_agents"] = dead
    (out / "report.json").write_text(json.dumps(report, indent=1, sort_keys=True))
    _side_by_side(fleet, out / "side_by_side.png")
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


def evaluate(
    fleet: LocalFleet,
    statuses: dict[str, dict | None],
    agreed_at: float | None,
    t_start: float,
    args: argparse.Namespace,
) -> dict:
    """The report: links against the truth, true overlaps linked, agreement, traffic."""
    w2p = {r: np.array(s["source"]["world_to_pixel"]) for r, s in statuses.items() if s is not None}
    updates = [s.get("last_update") or 0.0 for s in statuses.values() if s]
    last_update = max(updates, default=0.0) or None
    grids = {}
    for robot, agent in fleet.agents.items():
        maps, _ = StateDir(agent.state_dir).load_maps()
        if robot in maps:
            grids[robot] = maps[robot].grid
    robots = sorted(fleet.agents)
    overlaps = {}
    for i, a in enumerate(robots):
        for b in robots[i + 1 :]:
            if a in grids and b in grids and a in w2p and b in w2p:
                overlaps[f"{a}-{b}"] = true_overlap(grids[a], grids[b], true_matrix(w2p[a], w2p[b]))
    agents = {}
    false_links: set[str] = set()
    linked: set[str] = set()
    for robot, s in sorted(statuses.items()):
        if s is None:
            agents[robot] = {"status": None}
            continue
        links = []
        for ln in s.get("links", []):
            if not (ln["accepted"] and ln["current"]) or ln["a"] not in w2p or ln["b"] not in w2p:
                continue
            shape_b = grids[ln["b"]].shape if ln["b"] in grids else (1, 1)
            deg, cells = link_error(ln["matrix"], true_matrix(w2p[ln["a"]], w2p[ln["b"]]), shape_b)
            pair = f"{ln['a']}-{ln['b']}"
            linked.add(pair)
            if deg > args.max_deg or cells > args.max_cells:
                false_links.add(pair)
            links.append(
                {
                    "pair": pair,
                    "versions": [ln["version_a"], ln["version_b"]],
                    "score": ln["score"],
                    "error_deg": round(deg, 3),
                    "error_cells": round(cells, 3),
                    "decided_by": ln["decided_by"],
                }
            )
        settled_at = s.get("settled_at")
        agents[robot] = {
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
    must_link = sorted(p for p, f in overlaps.items() if f >= args.min_overlap)
    missing = [p for p in must_link if p not in linked]
    hashes = {a.get("global_hash") for a in agents.values()}
    same = agreed_at is not None and len(hashes) == 1
    return {
        "ok": bool(same and not missing and not false_links),
        "same_global_map": same,
        "true_overlaps": {p: round(f, 3) for p, f in overlaps.items()},
        "overlaps_to_link": must_link,
        "missing_links": missing,
        "false_links": sorted(false_links),
        "agreement_s_after_last_update": None
        if agreed_at is None or last_update is None
        else round(agreed_at - last_update, 3),
        "agreement_s_after_start": None if agreed_at is None else round(agreed_at - t_start, 3),
        "tolerance": {"deg": args.max_deg, "cells": args.max_cells},
        "agents": agents,
    }


def _side_by_side(fleet: LocalFleet, path: Path) -> None:
    """Local maps on the top row, every agent's global map below, gray, 8 px gaps."""
    from pgvd.io import MapFormatError, read_map
    from pgvd.render import grid_image

    top, bottom = [], []
    for robot, agent in sorted(fleet.agents.items()):
        maps, _ = StateDir(agent.state_dir).load_maps()
        if robot in maps:
            top.append(_gray(grid_image(maps[robot].grid.probability())))
        try:
            bottom.append(_gray(grid_image(read_map(agent.out_dir / "global.yaml").probability())))
        except MapFormatError:
            continue
    rows = [r for r in (top, bottom) if r]
    if not rows:
        return
    from pgvd.io import write_png

    write_png(path, _stack([_hstack(r) for r in rows], axis=0))


def _gray(img: np.ndarray) -> np.ndarray:
    img = np.asarray(img)
    return img if img.ndim == 2 else img[..., :3].mean(axis=2).astype(np.uint8)


def _hstack(images: list[np.ndarray]) -> np.ndarray:
    return _stack(images, axis=1)


def _stack(images: list[np.ndarray], axis: int, gap: int = 8) -> np.ndarray:
    """Concatenate along ``axis`` with white gaps, padding the other side to the largest."""
    other = 1 - axis
    size = max(i.shape[other] for i in images)
    parts = []
    for img in images:
        pad = [(0, 0), (0, 0)]
        pad[other] = (0, size - img.shape[other])
        parts.append(np.pad(img, pad, constant_values=255))
        spacer_shape = [size, size]
        spacer_shape[axis] = gap
        parts.append(np.full(spacer_shape, 255, np.uint8))
    return np.concatenate(parts[:-1], axis=axis)


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
        print(
            f"  {robot}: map {str(a['global_hash'])[:12]} of {','.join(a['global_members'] or [])}"
            f"  sent {a['bytes_sent']} B  links: {errs or 'none'}"
        )
    verdict = "OK" if report["ok"] else "FAILED"
    print(
        f"{verdict}: same global map {report['same_global_map']}, "
        f"agreement {report['agreement_s_after_last_update']} s after the last map update, "
        f"missing links {report['missing_links'] or 'none'}, "
        f"false links {report['false_links'] or 'none'}"
    )
