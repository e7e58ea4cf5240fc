"""``pgvd status``: ask every agent of a fleet for its status over Zenoh and print it."""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import zenoh

from agent.cli.common import EXIT_FAILED, EXIT_OK, CliError, read_fleet_key
from agent.keys import FleetKeys
from agent.links import EPOCH_SHIFT, epoch_of
from agent.status_reply import read_status
from agent.zenoh_config import ZenohOptions, build_config


def configure(p: argparse.ArgumentParser) -> None:
    """Add the arguments of ``pgvd status`` to its parser."""
    p.add_argument("--fleet", default="default", help="fleet name")
    p.add_argument(
        "--connect",
        action="append",
        default=[],
        metavar="EP",
        help="an agent's endpoint, e.g. tcp/127.0.0.1:7447 (none: multicast scouting)",
    )
    p.add_argument("--zenoh-config", type=Path, help="Zenoh JSON5 config file")
    p.add_argument(
        "--key-file", type=Path, help="fleet key file: only replies with its MAC are shown"
    )
    p.add_argument(
        "--timeout", type=float, default=3.0, help="seconds to wait for answers (default 3)"
    )
    p.add_argument("--json", action="store_true", help="print one JSON object {robot: status}")
    p.set_defaults(func=run)


def collect(
    keys: FleetKeys,
    opts: ZenohOptions,
    timeout: float,
    settle: float = 0.5,
    key: bytes | None = None,
) -> tuple[dict[str, dict], list[str]]:
    """Status of every agent that answers within ``timeout``, by robot id, and one line per
    reply refused (no or a wrong fleet MAC with ``key``, not JSON, a field of the wrong type).
    """
    out: dict[str, dict] = {}
    refused: list[str] = []
    with zenoh.open(build_config(opts)) as session:
        # zenoh.open() returns before any link is up: wait for a peer, then give gossip a
        # moment to link the rest.
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline and not _neighbours(session):
            time.sleep(0.02)
        time.sleep(settle)
        replies = session.get(
            keys.status(), consolidation=zenoh.ConsolidationMode.NONE, timeout=timeout
        )
        for reply in replies:
            if reply.ok is None:
                continue
            where = str(reply.ok.key_expr)
            robot = keys.robot_of(where, "status")
            attachment = reply.ok.attachment
            try:
                status = read_status(
                    reply.ok.payload.to_bytes(),
                    None if attachment is None else attachment.to_bytes(),
                    key,
                )
            except ValueError as exc:
                refused.append(f"ignored the reply on {where[:120]}: {exc}")
                continue
            if robot is not None:
                out[robot] = status
    return out, refused


def _neighbours(session: zenoh.Session) -> bool:
    info = session.info
    return bool(list(info.peers_zid()) or list(info.routers_zid()))


def _v(version: int | None) -> str:
    """A version as ``epoch.minor`` (:func:`agent.book.next_version`)."""
    if version is None:
        return "-"
    return f"{epoch_of(version)}.{version - (epoch_of(version) << EPOCH_SHIFT)}"


def _state(link: dict) -> str:
    """A link's lifecycle state; an older agent's status has only ``accepted``."""
    return link.get("state") or ("accepted" if link["accepted"] else "rejected")


def _states(links: list[dict]) -> str:
    """How many links of the current epochs are in each state, those in the map first."""
    order = ("accepted", "confirmed", "candidate", "withdrawn", "rejected")
    current = [ln for ln in links if ln.get("current", True)]
    counts = {state: sum(_state(ln) == state for ln in current) for state in order}
    return ", ".join(f"{n} {state}" for state, n in counts.items() if n) or "none"


def _why(link: dict) -> str:
    """The margin and the reason of a link, when its agent says them."""
    margin = link.get("margin")
    out = "" if margin is None else f" margin {margin:.2f}"
    return out + (f": {link['reason']}" if link.get("reason") else "")


def format_table(statuses: dict[str, dict]) -> str:
    """Human-readable summary: one block per agent."""
    if not statuses:
        return "no agent answered"
    lines = []
    for robot in sorted(statuses):
        s = statuses[robot]
        glob = s.get("global") or {}
        lines.append(
            f"{robot}: own v{_v(s.get('own_version'))}  global {str(glob.get('digest', '-'))[:12]} "
            f"anchor {glob.get('anchor', '-')} members {','.join(glob.get('members', []))}  "
            f"{'settled' if s.get('settled') else 'converging'}"
        )
        robots = s.get("robots", {})
        seen = " ".join(
            f"{r}:v{_v(v.get('version'))}{'' if v.get('alive') else '(gone)'}"
            for r, v in sorted(robots.items())
        )
        lines.append(f"  robots  {seen}")
        links = s.get("links", [])
        lines.append("  links   " + _states(links))
        for ln in links:
            lines.append(
                f"  link    {ln['a']} v{_v(ln['version_a'])} - {ln['b']} v{_v(ln['version_b'])}: "
                f"{_state(ln)} score {ln['score']:.3f} "
                f"rot {ln['rotation_deg']:.1f} deg (by {ln['decided_by']}){_why(ln)}"
            )
        lines.append(
            f"  traffic sent {s.get('bytes_sent', 0)} B, received {s.get('bytes_received', 0)} B"
            f", merges {s.get('merges', 0)}"
        )
        # Dropped messages by reason: framing, auth, schema, limit, value (what a decoder
        # refused), stale_version, overload, foreign_fleet, ... (the agent's own rules).
        drops = sorted(s.get("drops", {}).items(), key=lambda kv: (-kv[1], kv[0]))
        lines.append("  drops   " + (", ".join(f"{k}={v}" for k, v in drops) or "none"))
        source = s.get("source", {})
        if source.get("read_errors"):  # a map file the source could not load
            now = source.get("last_error")
            lines.append(
                f"  source  {source['read_errors']} read errors, "
                + (f"last: {now}" if now else "reads again")
            )
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    """Print the fleet's statuses; exit 1 when no agent answered (a script can tell)."""
    if not args.timeout > 0:
        raise CliError(f"--timeout must be > 0, got {args.timeout}")
    try:
        keys = FleetKeys(args.fleet)
        opts = ZenohOptions(
            connect=tuple(args.connect),
            multicast=not args.connect and args.zenoh_config is None,
            config_file=args.zenoh_config,
        )
        build_config(opts)
    except ValueError as exc:
        raise CliError(str(exc)) from None
    statuses, refused = collect(keys, opts, args.timeout, key=read_fleet_key(args.key_file))
    for line in refused:
        print(f"pgvd status: {line}", file=sys.stderr)
    if args.json:
        print(json.dumps(statuses, indent=1, sort_keys=True))
    else:
        print(format_table(statuses))
    return EXIT_OK if statuses else EXIT_FAILED
