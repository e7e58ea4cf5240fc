"""protocol on real data: building maps and a laser-log replay survive the wire exactly."""

from __future__ import annotations

import random

import msgpack
import numpy as np
import pytest

from pgvd.carmen import read_carmen
from pgvd.integrate import frame_for, integrate_scan
from pgvd.io import read_map
from protocol import (
    MapReassembler,
    ProtocolError,
    ReplayGuard,
    decode,
    encode_map,
    quantise_grid,
)
from protocol.compress import ARITH

KEY = b"real-maps-fleet-key-0123456789ab"
MAPS = [
    "intel/intel.yaml",
    "fr079_albertB/map312.yaml",
    "willow/willow-2010-02-18-0.10.yaml",
    "ritsumeikan_cc4f/cc4.1.yaml",
    "mit_stata_basement/stata_basement.yaml",
    "uos_avz/avz.yaml",
    "intel_split_gt/intel_partB.yaml",
    "fr079_split_gt/fr079_partB.yaml",
]


def receive(reasm: MapReassembler, wires: list[bytes], guard: ReplayGuard, key=None):
    out = None
    for wire in wires:
        msg = decode(wire, key)
        guard.admit(msg)
        out = reasm.feed(msg) or out
    return out


@pytest.mark.parametrize("rel", MAPS)
def test_building_map_round_trips_exactly_in_any_order(shared, rel):
    grid = read_map(shared / "maps" / rel)
    tiles, manifest = encode_map("lab", "r1", 1, grid, KEY, max_message_bytes=20_000)
    wires = [*tiles, manifest]
    assert all(len(w) < 20_000 for w in wires)
    # Far below a ROS OccupancyGrid, which costs one byte per cell.
    assert sum(map(len, wires)) < grid.logodds.size // 10
    random.Random(rel).shuffle(wires)
    out = receive(MapReassembler("r1", "lab"), wires, ReplayGuard(), KEY)
    assert out is not None
    assert np.array_equal(quantise_grid(out), quantise_grid(grid))
    assert (out.resolution, out.origin) == (grid.resolution, tuple(grid.origin))


def test_intel_log_replay_stages_and_one_scan_deltas(shared):
    """Maps at 25/50/75/100% of the intel log, sent as deltas, and one scan's delta."""
    scans = read_carmen(shared / "logs" / "intel-corrected.log.gz")
    frame = frame_for(scans)
    logodds = frame.empty()
    reasm, guard = MapReassembler("r1"), ReplayGuard()
    stages = [len(scans) * k // 4 for k in (1, 2, 3, 4)]
    previous, done = None, 0
    for version, stop in enumerate(stages, start=1):
        for scan in scans[done : stop - 1]:
            integrate_scan(logodds, scan, frame)
        done = stop - 1
        before = frame.grid(logodds.copy())
        tiles, manifest = encode_map("f", "r1", 2 * version - 1, before, since=previous)
        wires = [*tiles, manifest]
        random.Random(version).shuffle(wires)
        receive(reasm, wires, guard)
        assert reasm.version == 2 * version - 1
        assert np.array_equal(reasm.quantised, quantise_grid(before))

        # One more scan: the delta holds only tiles inside the scan's touched box.
        rows, cols = integrate_scan(logodds, scans[done], frame)
        done += 1
        after = frame.grid(logodds.copy())
        tiles, manifest = encode_map(
            "f", "r1", 2 * version, after, since=before, base_version=2 * version - 1
        )
        assert decode(manifest).is_delta
        # A scan's few hundred changed cells take the arithmetic coder (protocol.arith).
        assert [msgpack.unpackb(w[4:-4])[7] for w in tiles] == [ARITH] * len(tiles)
        touched = set()
        for msg in map(decode, tiles):
            touched |= {t.index for t in msg.tiles}
            assert all(t.is_delta or not quantise_grid(before)[_window(msg, t)].any()
                       for t in msg.tiles)  # fmt: skip
        t = 128
        ncols = -(-frame.shape[1] // t)
        box = {
            r * ncols + c
            for r in range(rows.start // t, (rows.stop - 1) // t + 1)
            for c in range(cols.start // t, (cols.stop - 1) // t + 1)
        }
        assert touched and touched <= box
        receive(reasm, [manifest, *tiles], guard)
        assert np.array_equal(reasm.quantised, quantise_grid(after))
        previous = after


def _window(msg, tile):
    return msg.geometry.tile_window(tile.index)


# Limits below the largest 64x64 tile of each map, so that the lone case happens.
@pytest.mark.parametrize(
    ("rel", "limit"), [("intel/intel.yaml", 600), ("fr079_albertB/map312.yaml", 400)]
)
def test_datagram_packing_keeps_tiles_under_an_mtu_and_the_map_exact(shared, rel, limit):
    """Best-effort tiles ride single UDP datagrams: only a tile too big alone may exceed them."""
    grid = read_map(shared / "maps" / rel)
    with pytest.raises(ProtocolError, match=f"does not fit in {limit}-byte messages"):
        encode_map("lab", "r1", 1, grid, KEY, max_message_bytes=limit, tile_size=64)
    tiles, manifest = encode_map(
        "lab", "r1", 1, grid, KEY, max_message_bytes=limit, tile_size=64, lone_oversize=True
    )
    counts = [len(decode(w, KEY).tiles) for w in tiles]
    assert max(counts) > 1 and any(len(w) >= limit for w in tiles)
    assert all(len(w) < limit for w, n in zip(tiles, counts, strict=True) if n > 1)
    out = receive(MapReassembler("r1", "lab"), [*tiles, manifest], ReplayGuard(), KEY)
    assert out is not None and np.array_equal(quantise_grid(out), quantise_grid(grid))
