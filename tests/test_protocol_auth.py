"""protocol.auth: the fleet key (HMAC-SHA256) and the replay guard."""

from __future__ import annotations

import numpy as np
from hypothesis import given
from hypothesis import strategies as st
from refusals import refused

from pgvd.grid import Grid
from protocol import (
    Heartbeat,
    Link,
    ProtocolError,
    ReplayGuard,
    Status,
    decode,
    dequantise,
    encode,
    encode_map,
)

KEY = b"k" * 32


def test_wrong_key_is_refused():
    wire = encode(Heartbeat("f", "r1", 1), KEY)
    assert decode(wire, KEY) == Heartbeat("f", "r1", 1)
    with refused("auth", "wrong MAC"):
        decode(wire, b"K" * 32)


def test_missing_mac_is_refused_when_a_key_is_set():
    with refused("auth", "carries no MAC but a fleet key is configured"):
        decode(encode(Heartbeat("f", "r1", 1)), KEY)


def test_mac_without_a_configured_key_is_refused():
    with refused("auth", "carries a MAC but no fleet key is configured"):
        decode(encode(Heartbeat("f", "r1", 1), KEY))


def test_stripping_or_forging_the_mac_is_refused():
    wire = encode(Heartbeat("f", "r1", 1), KEY)
    unflagged = wire[:3] + b"\x00" + wire[4:]
    with refused("auth", "no MAC"):
        decode(unflagged, KEY)
    # Swap the body for another message's while keeping the old MAC.
    other = encode(Heartbeat("f", "r1", 2), KEY)
    with refused("auth", "wrong MAC"):
        decode(other[:-32] + wire[-32:], KEY)


def test_key_must_be_non_empty_bytes():
    for key in (b"", "text", 5):
        with refused("value", "non-empty bytes"):
            encode(Heartbeat("f", "r1", 1), key)


def test_replay_of_an_old_or_equal_version_is_refused():
    guard = ReplayGuard()
    guard.admit(Heartbeat("f", "r1", 5))
    for seq in (5, 4, 0):
        with refused("replay", f"replayed heartbeat from r1: version {seq} "):
            guard.admit(Heartbeat("f", "r1", seq))
    guard.admit(Heartbeat("f", "r1", 6))
    guard.admit(Heartbeat("f", "r2", 1))  # per robot
    guard.admit(Status("f", "r1", 1))  # per kind


def test_replayed_map_messages_are_refused_per_tile():
    q = np.random.default_rng(0).integers(-127, 128, (300, 300)).astype(np.int8)
    grid = Grid(dequantise(q), 0.05)
    guard = ReplayGuard()
    old_tiles, old_manifest = encode_map("f", "r1", 1, grid, KEY, max_message_bytes=40_000)
    new_tiles, new_manifest = encode_map("f", "r1", 2, grid, KEY, max_message_bytes=40_000)
    assert len(new_tiles) > 1  # several messages of one version pass
    for wire in [*new_tiles, new_manifest]:
        guard.admit(decode(wire, KEY))
    for wire in [old_tiles[0], old_manifest, new_tiles[0], new_manifest]:
        with refused("replay", r"replayed (tiles|manifest) from r1"):
            guard.admit(decode(wire, KEY))


def test_full_tile_after_a_delta_of_the_same_version_is_accepted_once():
    a = np.ones((64, 64), np.int8)
    b = a.copy()
    b[0, 0] = 3
    guard = ReplayGuard()
    delta, _ = encode_map("f", "r1", 2, Grid(dequantise(b)), since=Grid(dequantise(a)))
    full, _ = encode_map("f", "r1", 2, Grid(dequantise(b)), indices=[0])
    guard.admit(decode(delta[0]))
    guard.admit(decode(full[0]))
    with refused("replay", "replayed tiles"):
        guard.admit(decode(full[0]))


def test_links_move_forward_in_both_versions():
    def link(va: int, vb: int) -> Link:
        return Link("f", "r1", "r1", "r2", va, vb, True, np.eye(3), np.eye(3), 0.9)

    guard = ReplayGuard()
    guard.admit(link(3, 3))
    guard.admit(link(4, 3))
    for va, vb in [(4, 3), (3, 9), (2, 2)]:
        with refused("replay", f"version {va}/{vb} is not newer than"):
            guard.admit(link(va, vb))
    guard.admit(link(4, 5))


def test_check_records_nothing_and_state_survives_a_restart():
    guard = ReplayGuard()
    guard.check(Heartbeat("f", "r1", 5))
    guard.admit(Heartbeat("f", "r1", 4))
    restarted = ReplayGuard(dict(guard.state))
    with refused("replay", "replayed"):
        restarted.admit(Heartbeat("f", "r1", 4))


@given(st.lists(st.integers(0, 20), max_size=30))
def test_guard_admits_exactly_the_strictly_increasing_sequence(seqs):
    guard, last = ReplayGuard(), None
    for seq in seqs:
        fresh = last is None or seq > last
        try:
            guard.admit(Heartbeat("f", "r1", seq))
        except ProtocolError:
            assert not fresh
        else:
            assert fresh
            last = seq
