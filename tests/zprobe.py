"""A tiny Zenoh publisher / subscriber run as a process inside a test namespace.

    python3 tests/zprobe.py sub  --config JSON --count N --timeout S
    python3 tests/zprobe.py pub  --config JSON --count N --size B --interval S [--settle S]

``--config`` is a JSON object of Zenoh config paths to values (``{"mode": "client", ...}``),
inserted one by one with ``Config.insert_json5``. The subscriber prints ``READY`` once declared,
then one JSON line: the sequence numbers received, one-way latencies (same machine clock, so
``time.time()`` is comparable across namespaces) and whether a liveliness token of the publisher
was seen. The publisher declares a liveliness token, waits until a subscriber matches (then
``--settle`` seconds more), and puts ``N`` samples ``[seq:u32][send time:f64][padding]`` reliably
(``CongestionControl.BLOCK``).
"""

from __future__ import annotations

import argparse
import json
import struct
import sys
import threading
import time

import zenoh

KEY = "pgvd/probe/data"
ALIVE = "pgvd/probe/alive"
HEADER = struct.Struct("<Id")


def open_session(config: dict[str, object]) -> zenoh.Session:
    cfg = zenoh.Config()
    for path, value in config.items():
        cfg.insert_json5(path, json.dumps(value))
    return zenoh.open(cfg)


def subscribe(config: dict[str, object], count: int, timeout: float) -> dict[str, object]:
    seqs: list[int] = []
    latencies: list[float] = []
    alive = threading.Event()
    done = threading.Event()

    def on_sample(sample: zenoh.Sample) -> None:
        seq, sent = HEADER.unpack_from(sample.payload.to_bytes())
        latencies.append(time.time() - sent)
        seqs.append(seq)
        if len(seqs) >= count:
            done.set()

    def on_token(sample: zenoh.Sample) -> None:
        if sample.kind == zenoh.SampleKind.PUT:
            alive.set()

    with open_session(config) as session:
        sub = session.declare_subscriber(KEY, on_sample)
        tok = session.liveliness().declare_subscriber(ALIVE + "/**", on_token, history=True)
        print("READY", flush=True)
        start = time.monotonic()
        done.wait(timeout)
        elapsed = time.monotonic() - start
        tok.undeclare()
        sub.undeclare()
    return {"seqs": seqs, "latencies": latencies, "alive": alive.is_set(), "elapsed": elapsed}


def publish(
    config: dict[str, object], count: int, size: int, interval: float, settle: float
) -> dict[str, object]:
    pad = b"\0" * max(0, size - HEADER.size)
    with open_session(config) as session:
        token = session.liveliness().declare_token(ALIVE + "/pub")
        pub = session.declare_publisher(KEY, congestion_control=zenoh.CongestionControl.BLOCK)
        deadline = time.monotonic() + 30
        # open() returns before links are up: early puts would be lost silently.
        while not pub.matching_status.matching and time.monotonic() < deadline:
            time.sleep(0.01)
        matched = pub.matching_status.matching
        # Across two routers, matching only says the declaration reached this client's router;
        # that router's route to the other site can still be in computation, and a put in that
        # window is dropped (zenoh-plugin-ros2dds#30 reports the same transient).
        time.sleep(settle)
        for seq in range(count):
            pub.put(HEADER.pack(seq, time.time()) + pad)
            if interval:
                time.sleep(interval)
        time.sleep(1.0)  # let the last (possibly retransmitted) frames leave before close
        pub.undeclare()
        token.undeclare()
    return {"matched": matched}


def main() -> int:
    parser = argparse.ArgumentParser()
    parser.add_argument("role", choices=("sub", "pub"))
    parser.add_argument("--config", type=json.loads, default={})
    parser.add_argument("--count", type=int, default=100)
    parser.add_argument("--size", type=int, default=64)
    parser.add_argument("--interval", type=float, default=0.0)
    parser.add_argument("--timeout", type=float, default=20.0)
    parser.add_argument("--settle", type=float, default=0.0)
    args = parser.parse_args()
    if args.role == "sub":
        result = subscribe(args.config, args.count, args.timeout)
    else:
        result = publish(args.config, args.count, args.size, args.interval, args.settle)
    print(json.dumps(result), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
