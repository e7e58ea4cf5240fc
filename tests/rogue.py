"""A hostile process on a fleet's keys, driven line by line on stdin (one attack per line).

    python3 tests/rogue.py --fleet F --key-file K --connect EP [--connect EP ...] [--listen EP]

It joins the fleet's Zenoh network as a peer and records the first genuine map messages
(tiles and manifests) it sees, to replay them later. Then, for each line ``ATTACK [N [SIZE]]``
read from stdin, it publishes on the fleet's real keys and answers ``done ATTACK <count>``:

``random``     random bytes on tiles/manifest/link keys of real and invented robots
``truncated``  genuine (keyed) tile and manifest messages cut short
``oversized``  a correctly keyed manifest claiming a 20000 x 20000 map (an insider's bug)
``nan``        a correctly keyed manifest whose resolution is NaN
``spoofed``    a map of real robot r1, newer version, encoded without the fleet key / a wrong key
``replay``     the genuine messages recorded at start, verbatim (old versions)
``flood``      N messages of SIZE random bytes on a member's tiles key, as fast as possible
``queries``    N malformed tile fetches (``latest`` queries with bad ``v``/``tiles`` parameters)
``status``     answers ``pgvd status`` as robots r8 (malformed JSON) and r9 (a forged status,
               no MAC)
"""

from __future__ import annotations

import argparse
import json
import os
import random
import sys
import threading
import time
from pathlib import Path

import msgpack
import numpy as np
import zenoh

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from pgvd.grid import Grid
from protocol import encode_map
from protocol.auth import seal

ROBOTS = ("r1", "r2", "r3")


class Rogue:
    def __init__(self, session: zenoh.Session, fleet: str, key: bytes) -> None:
        self.s, self.fleet, self.key = session, fleet, key
        self.root = f"pgvd/{fleet}"
        self.recorded: list[tuple[str, bytes]] = []
        self._lock = threading.Lock()
        self.rng = random.Random(6)
        self.queryables: list[zenoh.Queryable] = []

    def record(self, sample: zenoh.Sample) -> None:
        with self._lock:
            if len(self.recorded) < 64:
                self.recorded.append((str(sample.key_expr), sample.payload.to_bytes()))

    def put(self, key: str, data: bytes) -> None:
        self.s.put(key, data, congestion_control=zenoh.CongestionControl.BLOCK)

    def random(self, n: int = 300, size: int = 2000) -> int:
        kinds = ("tiles", "manifest")
        for i in range(n):
            robot = self.rng.choice([*ROBOTS, "x" + str(i % 50)])
            key = f"{self.root}/{self.rng.choice(kinds)}/{robot}"
            if i % 10 == 0:
                key = f"{self.root}/link/r1/{robot}"
            self.put(key, self.rng.randbytes(self.rng.randint(0, size)))
        return n

    def truncated(self, n: int = 0, size: int = 0) -> int:
        count = 0
        for key, data in self.genuine():
            for cut in (1, 4, len(data) // 2, len(data) - 1):
                self.put(key, data[:cut])
                count += 1
        return count

    def genuine(self) -> list[tuple[str, bytes]]:
        with self._lock:
            return list(self.recorded)

    def forged_manifest(self, robot: str, edit) -> bytes:
        """A correctly keyed manifest of ``robot`` whose msgpack body ``edit`` changed."""
        _, manifest = encode_map(self.fleet, robot, 10_000, self.grid(), self.key)
        head, body = manifest[:4], msgpack.unpackb(manifest[4:-32], raw=False)
        edit(body)
        packed = head + msgpack.packb(body, use_bin_type=True)
        return packed + seal(packed, self.key)

    def grid(self) -> Grid:
        cells = np.zeros((200, 200), np.float32)
        cells[50:150, 100] = 3.0
        return Grid(cells, 0.05, (0.0, 0.0, 0.0))

    def _geometry(self, body: dict) -> list:
        fields = body.values() if isinstance(body, dict) else body  # schema 2: positional
        return next(v for v in fields if isinstance(v, list) and len(v) == 7)

    def oversized(self, n: int = 5, size: int = 0) -> int:
        def huge(body: dict) -> None:
            geometry = self._geometry(body)
            geometry[0] = geometry[1] = 20_000

        for robot in ("r1", "x-big"):
            for _ in range(n):
                self.put(f"{self.root}/manifest/{robot}", self.forged_manifest(robot, huge))
        return 2 * n

    def nan(self, n: int = 5, size: int = 0) -> int:
        def not_a_number(body: dict) -> None:
            self._geometry(body)[2] = float("nan")

        for _ in range(n):
            self.put(f"{self.root}/manifest/r1", self.forged_manifest("r1", not_a_number))
        return n

    def spoofed(self, n: int = 0, size: int = 0) -> int:
        count = 0
        for key in (None, b"not the fleet key"):
            tiles, manifest = encode_map(self.fleet, "r1", 10_000, self.grid(), key)
            for data in tiles:
                self.put(f"{self.root}/tiles/r1", data)
            self.put(f"{self.root}/manifest/r1", manifest)
            count += len(tiles) + 1
        return count

    def replay(self, n: int = 0, size: int = 0) -> int:
        recorded = self.genuine()
        for key, data in recorded:
            self.put(key, data)
        return len(recorded)

    def queries(self, n: int = 40, size: int = 0) -> int:
        """Malformed fetches at every member's ``latest`` queryable; the count of map replies."""
        bad = ("v=x1;tiles=1", "tiles=1,2", "v=1;tiles=1,,2", "v=-3;tiles=4")
        answered = 0
        for i in range(n):
            selector = f"{self.root}/latest/*/**?{bad[i % len(bad)]}"
            answered += sum(r.ok is not None for r in self.s.get(selector, timeout=2.0))
        print(f"malformed fetches answered: {answered}", file=sys.stderr, flush=True)
        return n

    def status(self, n: int = 0, size: int = 0) -> int:
        """Forged status replies; they stay declared until the rogue exits."""
        forged = {"own_version": 1, "settled": True, "robots": {"r9": {"alive": True}}}
        answers = {"r8": b'{"links": [{}]}', "r9": json.dumps(forged).encode()}
        for robot, data in answers.items():
            key = f"{self.root}/status/{robot}"
            self.queryables.append(
                self.s.declare_queryable(key, lambda q, k=key, d=data: q.reply(k, d))
            )
        return len(answers)

    def flood(self, n: int = 20_000, size: int = 1000) -> int:
        payload = os.urandom(size)
        for i in range(n):
            # A fresh prefix per message: the same bytes again would be cheap to spot.
            self.s.put(f"{self.root}/tiles/r{1 + i % 3}", i.to_bytes(4, "big") + payload)
        return n


def main() -> int:
    parser = argparse.ArgumentParser()
    parser.add_argument("--fleet", required=True)
    parser.add_argument("--key-file", type=Path, required=True)
    parser.add_argument("--connect", action="append", default=[])
    parser.add_argument("--listen", action="append", default=[])
    args = parser.parse_args()
    config = zenoh.Config()
    settings = {
        "mode": "peer",
        "connect/endpoints": args.connect,
        "listen/endpoints": args.listen,
        "scouting/multicast/enabled": False,
        "scouting/delay": 0,
        "transport/shared_memory/enabled": False,
    }
    for path, value in settings.items():
        config.insert_json5(path, json.dumps(value))
    with zenoh.open(config) as session:
        rogue = Rogue(session, args.fleet, args.key_file.read_bytes().strip())
        subs = [
            session.declare_subscriber(f"pgvd/{args.fleet}/{kind}/*", rogue.record)
            for kind in ("tiles", "manifest")
        ]
        print("READY", flush=True)
        for line in sys.stdin:
            name, *numbers = line.split()
            start = time.monotonic()
            count = getattr(rogue, name)(*map(int, numbers))
            print(f"done {name} {count} {time.monotonic() - start:.3f}", flush=True)
        for entity in [*subs, *rogue.queryables]:
            entity.undeclare()
    return 0


if __name__ == "__main__":
    sys.exit(main())
