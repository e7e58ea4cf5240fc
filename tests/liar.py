"""A keyed fleet member that publishes one false accepted link, then exits.

    python3 tests/liar.py --fleet F --key-file K --connect EP [--connect EP ...] < link.json

``link.json`` is a link record (:meth:`agent.links.LinkRecord.to_json`).  It is published
correctly keyed on the fleet's link key of its pair, three times half a second apart (a
peer that was busy still hears it), and the process prints ``done`` and exits.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import zenoh

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from agent import wire
from agent.keys import FleetKeys
from agent.links import LinkRecord


def main() -> int:
    parser = argparse.ArgumentParser()
    parser.add_argument("--fleet", required=True)
    parser.add_argument("--key-file", type=Path, required=True)
    parser.add_argument("--connect", action="append", default=[])
    args = parser.parse_args()
    rec = LinkRecord.from_json(json.load(sys.stdin))
    data = wire.encode_link(args.fleet, rec, args.key_file.read_bytes().strip())
    config = zenoh.Config()
    settings = {
        "mode": "peer",
        "connect/endpoints": args.connect,
        "scouting/multicast/enabled": False,
        "transport/shared_memory/enabled": False,
    }
    for path, value in settings.items():
        config.insert_json5(path, json.dumps(value))
    with zenoh.open(config) as session:
        time.sleep(1.0)  # let the connections come up
        for _ in range(3):
            session.put(FleetKeys(args.fleet).link(rec.a, rec.b), data)
            time.sleep(0.5)
    print("done", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
