"""protocol.mapsync: a map survives tiling, deltas and any arrival order, exactly."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pgvd.grid import Grid
from protocol import (
    Limits,
    MapReassembler,
    ProtocolError,
    decode,
    dequantise,
    encode_map,
    quantise_grid,
)

KEY = b"another-fleet-key-for-the-tests!"


def random_quantised(rng: np.random.Generator, shape, density: float) -> np.ndarray:
    """Sparse int8 cells in [-127, 127], with blobs so some tiles stay empty."""
    q = np.zeros(shape, np.int8)
    mask = rng.random(shape) < density
    q[mask] = rng.integers(-127, 128, mask.sum())
    return q


def as_grid(q: np.ndarray) -> Grid:
    return Grid(dequantise(q), 0.05, (1.5, -3.0, 0.2))


def mutate(rng: np.random.Generator, q: np.ndarray) -> np.ndarray:
    """A new version: a random rectangle of cells changes, as after a scan."""
    out = q.copy()
    h, w = q.shape
    r0, c0 = rng.integers(0, h), rng.integers(0, w)
    r1, c1 = r0 + rng.integers(1, 12), c0 + rng.integers(1, 12)
    patch = out[r0:r1, c0:c1]
    patch[...] = np.clip(patch.astype(int) + rng.integers(-40, 41, patch.shape), -127, 127)
    return out


def deliver(reasm: MapReassembler, wires: list[bytes], key=None) -> Grid | None:
    last = None
    for wire in wires:
        out = reasm.feed(decode(wire, key))
        if out is not None:
            last = out
    return last


grids = st.tuples(
    st.integers(1, 90), st.integers(1, 90), st.sampled_from([16, 32]),
    st.floats(0.0, 0.3), st.integers(0, 2**32 - 1),
)  # fmt: skip


first_epochs = st.none() | st.integers(0, 2**32 - 1)


@settings(max_examples=60)
@given(spec=grids, order=st.randoms(use_true_random=False), keyed=st.booleans(), first=first_epochs)
def test_full_map_round_trips_in_any_order(spec, order, keyed, first):
    h, w, ts, density, seed = spec
    key = KEY if keyed else None
    q = random_quantised(np.random.default_rng(seed), (h, w), density)
    tiles, manifest = encode_map(
        "f", "r1", 7, as_grid(q), key, max_message_bytes=1500, tile_size=ts, first_epoch=first
    )
    wires = [*tiles, manifest]
    order.shuffle(wires)
    reasm = MapReassembler("r1", "f")
    grid = deliver(reasm, wires, key)
    assert grid is not None and reasm.missing() == []
    assert np.array_equal(quantise_grid(grid), q)
    assert grid.resolution == 0.05 and grid.origin == (1.5, -3.0, 0.2)
    assert reasm.version == 7 and reasm.first_epoch == first


@settings(max_examples=40)
@given(
    spec=grids, order=st.randoms(use_true_random=False), steps=st.integers(1, 5),
    first=first_epochs,
)  # fmt: skip
def test_deltas_rebuild_every_version(spec, order, steps, first):
    """Each version is rebuilt exactly, with its first epoch, and the last with its final
    mark, which delta manifests carry too."""
    h, w, ts, density, seed = spec
    rng = np.random.default_rng(seed)
    q = random_quantised(rng, (h, w), density)
    reasm = MapReassembler("r1")
    tiles, manifest = encode_map(
        "f", "r1", 1, as_grid(q), tile_size=ts, max_message_bytes=1500, first_epoch=first
    )
    deliver(reasm, [*tiles, manifest])
    for version in range(2, 2 + steps):
        new = mutate(rng, q)
        tiles, manifest = encode_map(
            "f", "r1", version, as_grid(new), since=as_grid(q), base_version=version - 1,
            tile_size=ts, max_message_bytes=1500, first_epoch=first, final=version == 1 + steps,
        )  # fmt: skip
        wires = [*tiles, manifest]
        order.shuffle(wires)
        deliver(reasm, wires)
        assert reasm.version == version and reasm.first_epoch == first
        assert reasm.final is (version == 1 + steps)
        assert np.array_equal(reasm.quantised, new)
        q = new


@settings(max_examples=40)
@given(
    spec=grids, order=st.randoms(use_true_random=False), steps=st.integers(2, 5),
    delta_manifests=st.booleans(),
)  # fmt: skip
def test_interleaved_versions_converge_after_fetching_missing_tiles(
    spec, order, steps, delta_manifests
):
    """Messages of several versions mixed and some lost: missing() names what to fetch."""
    h, w, ts, density, seed = spec
    rng = np.random.default_rng(seed)
    versions = [random_quantised(rng, (h, w), max(density, 0.01))]
    for _ in range(steps):
        versions.append(mutate(rng, versions[-1]))
    wires = []
    for v, q in enumerate(versions, start=1):
        since = None if v == 1 else as_grid(versions[v - 2])
        base_version = v - 1 if since is not None and delta_manifests else None
        tiles, manifest = encode_map(
            "f", "r1", v, as_grid(q), since=since, base_version=base_version, tile_size=ts,
            max_message_bytes=1500,
        )  # fmt: skip
        wires += [*tiles, manifest]
    order.shuffle(wires)
    lost = order.randrange(len(wires) + 1)
    reasm = MapReassembler("r1")
    deliver(reasm, wires[:lost] + wires[lost + 1 :])
    latest, newest = versions[-1], len(versions)
    if reasm.version != newest:
        # The agent re-announces its newest manifest, then missing tiles are fetched.
        _, manifest = encode_map("f", "r1", newest, as_grid(latest), tile_size=ts)
        deliver(reasm, [manifest])
        if reasm.version != newest:
            fetched, _ = encode_map(
                "f", "r1", newest, as_grid(latest), tile_size=ts, indices=reasm.missing()
            )
            deliver(reasm, fetched)
    assert reasm.version == newest
    assert np.array_equal(reasm.quantised, latest)


def test_delta_without_its_base_is_reported_missing_and_fetched_in_full():
    rng = np.random.default_rng(3)
    v1 = random_quantised(rng, (100, 100), 0.5)
    v2 = v1.copy()
    v2[5:9, 5:9] += 1  # changes tile 0 only
    reasm = MapReassembler("r1")
    tiles, manifest = encode_map("f", "r1", 2, as_grid(v2), since=as_grid(v1), tile_size=32)
    assert len(tiles) == 1 and decode(tiles[0]).tiles[0].is_delta
    deliver(reasm, [*tiles, manifest])
    assert reasm.version is None
    assert reasm.missing() == list(range(16))
    fetched, _ = encode_map("f", "r1", 2, as_grid(v2), tile_size=32, indices=reasm.missing())
    grid = deliver(reasm, fetched)
    assert grid is not None and np.array_equal(reasm.quantised, v2)


def test_stale_versions_are_ignored_and_unknown_tiles_empty():
    q = np.zeros((64, 64), np.int8)
    q[0, 0] = 5
    reasm = MapReassembler("r1")
    tiles, manifest = encode_map("f", "r1", 5, as_grid(q), tile_size=32)
    assert len(tiles) == 1 and len(decode(tiles[0]).tiles) == 1  # only the tile with knowledge
    deliver(reasm, [manifest, *tiles])
    old_tiles, old_manifest = encode_map("f", "r1", 4, as_grid(q * 0 + 1), tile_size=32)
    assert deliver(reasm, [*old_tiles, old_manifest]) is None
    assert reasm.version == 5 and np.array_equal(reasm.quantised, q)


def test_reassembler_refuses_other_robots_fleets_and_contradictions():
    q = np.ones((40, 40), np.int8)
    _, manifest = encode_map("f", "r1", 1, as_grid(q), tile_size=32)
    with pytest.raises(ProtocolError, match="robot 'r1', expected 'r2'"):
        MapReassembler("r2").feed(decode(manifest))
    with pytest.raises(ProtocolError, match="fleet 'f', expected 'g'"):
        MapReassembler("r1", "g").feed(decode(manifest))
    other_tiles, _ = encode_map("f", "r1", 1, as_grid(q * 2), tile_size=32)
    reasm = MapReassembler("r1")
    reasm.feed(decode(manifest))
    with pytest.raises(ProtocolError, match="tile 0 of version 1 is not the manifest's"):
        reasm.feed(decode(other_tiles[0]))


def test_buffer_of_early_tiles_is_bounded():
    """Tiles ahead of their manifest are held up to the limit; the newest are kept."""
    rng = np.random.default_rng(0)
    reasm = MapReassembler("r1", limits=Limits(max_buffered_cells=4 * 16 * 16))
    for v in range(1, 4):
        q = random_quantised(rng, (64, 64), 0.9)
        tiles, manifest = encode_map("f", "r1", v, as_grid(q), tile_size=16, max_message_bytes=400)
        assert len(tiles) == 16
        deliver(reasm, tiles)
    deliver(reasm, [manifest])
    assert reasm.missing() == list(range(12))


def test_every_tile_message_is_under_the_byte_bound_and_keyed():
    rng = np.random.default_rng(1)
    q = rng.integers(-127, 128, (700, 700)).astype(np.int8)  # incompressible
    tiles, manifest = encode_map("f", "r1", 1, as_grid(q), KEY, max_message_bytes=40_000)
    assert len(tiles) > 10 and all(len(t) < 40_000 for t in tiles)
    with pytest.raises(ProtocolError, match="no MAC but a fleet key"):
        decode(encode_map("f", "r1", 1, as_grid(q))[1], KEY)
    assert np.array_equal(
        deliver(MapReassembler("r1"), [*tiles, manifest], KEY).logodds, dequantise(q)
    )


def test_early_tiles_contradicting_their_manifest_are_dropped_and_counted():
    rng = np.random.default_rng(5)
    q, other = random_quantised(rng, (40, 40), 0.5), random_quantised(rng, (40, 40), 0.5)
    tiles, _ = encode_map("f", "r1", 1, as_grid(other), tile_size=32)
    _, manifest = encode_map("f", "r1", 1, as_grid(q), tile_size=32)
    reasm = MapReassembler("r1")
    deliver(reasm, [*tiles, manifest])
    assert reasm.dropped == 1 and reasm.missing() == [0, 1, 2, 3]
    fetched, _ = encode_map("f", "r1", 1, as_grid(q), tile_size=32, indices=[0, 1, 2, 3, 99])
    assert np.array_equal(deliver(reasm, fetched).logodds, dequantise(q))


def test_requested_tiles_without_knowledge_are_skipped():
    q = np.zeros((64, 64), np.int8)
    q[40, 40] = 9  # only tile 3 of 2x2 holds knowledge
    tiles, _ = encode_map("f", "r1", 1, as_grid(q), tile_size=32, indices=[0, 3])
    assert [t.index for t in decode(tiles[0]).tiles] == [3]
    assert encode_map("f", "r1", 1, as_grid(q), tile_size=32, indices=[0])[0] == []


def test_a_grown_map_is_sent_in_full_and_rebuilt():
    rng = np.random.default_rng(8)
    small = random_quantised(rng, (50, 50), 0.4)
    grown = random_quantised(rng, (70, 60), 0.4)
    grown[:50, :50] = small
    reasm = MapReassembler("r1")
    tiles, manifest = encode_map("f", "r1", 1, as_grid(small), tile_size=32)
    deliver(reasm, [*tiles, manifest])
    tiles, manifest = encode_map("f", "r1", 2, as_grid(grown), since=as_grid(small), tile_size=32)
    assert not any(t.is_delta for w in tiles for t in decode(w).tiles)
    grid = deliver(reasm, [manifest, *tiles])
    assert grid is not None and np.array_equal(reasm.quantised, grown)


def _versions(seed: int, shape=(100, 100), n: int = 3) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    out = [random_quantised(rng, shape, 0.3)]
    while len(out) < n:
        out.append(mutate(rng, out[-1]))
    return out


def _encode(v: int, versions: list[np.ndarray], delta: bool = True, **kw):
    since = as_grid(versions[v - 2]) if delta and v > 1 else None
    base = v - 1 if since is not None else None
    return encode_map("f", "r1", v, as_grid(versions[v - 1]), since=since, base_version=base, **kw)


def _window(i: int) -> tuple[slice, slice]:
    r, c = divmod(i, 2)
    return slice(64 * r, 64 * r + 64), slice(64 * c, 64 * c + 64)


def test_delta_manifest_lists_only_changed_tiles_and_rebuilds_the_full_one():
    v1, v2 = _versions(11, n=2)
    v2 = v2.copy()
    v2[64:, 64:] = 0  # tile 3 of 2x2 loses all knowledge
    versions = [v1, v2]
    _, full = _encode(2, versions, delta=False, tile_size=64)
    tiles, delta = _encode(2, versions, tile_size=64)
    msg = decode(delta)
    assert msg.is_delta and msg.base_version == 1 and not decode(full).is_delta
    changed = {i for i in range(4) if (v1 != v2)[_window(i)].any()}
    assert set(msg.checksums) == changed and 3 in changed and 3 not in decode(full).checksums
    reasm = MapReassembler("r1")
    deliver(reasm, [*_encode(1, versions, tile_size=64)[0], _encode(1, versions, tile_size=64)[1]])
    grid = deliver(reasm, [delta, *tiles])
    assert grid is not None and np.array_equal(reasm.quantised, v2)
    assert reasm.version == 2


def test_delta_manifest_without_its_base_asks_for_everything_then_takes_the_full_map():
    versions = _versions(12)
    reasm = MapReassembler("r1")
    tiles, manifest = _encode(3, versions, tile_size=32)
    deliver(reasm, [*tiles, manifest])
    assert reasm.version is None and reasm.missing() == list(range(16))
    tiles, manifest = _encode(3, versions, delta=False, tile_size=32)  # the queryable's answer
    deliver(reasm, [manifest, *tiles])
    assert reasm.version == 3 and np.array_equal(reasm.quantised, versions[2])


def test_delta_manifest_against_other_content_is_refused():
    versions = _versions(13)
    reasm = MapReassembler("r1")
    tiles, manifest = _encode(1, versions, tile_size=32)
    deliver(reasm, [*tiles, manifest])
    # Version 2 claims base 1 but was computed against other content.
    other = _versions(99, n=2)
    _, manifest = encode_map(
        "f", "r1", 2, as_grid(other[1]), since=as_grid(other[0]), base_version=1, tile_size=32
    )
    with pytest.raises(ProtocolError, match="does not apply to the held version 1"):
        reasm.feed(decode(manifest))


def test_delta_manifest_waits_for_its_base_to_complete():
    versions = _versions(14)
    wires = {v: _encode(v, versions, tile_size=32) for v in (1, 2, 3)}
    reasm = MapReassembler("r1")
    deliver(reasm, [wires[1][1], wires[2][1], wires[3][1], *wires[3][0], *wires[2][0]])
    assert reasm.version is None and reasm.missing() == list(range(16))
    grid = deliver(reasm, wires[1][0])  # v1 completes, v2 expands and completes, then v3
    assert grid is not None and reasm.version == 3
    assert np.array_equal(quantise_grid(grid), versions[2])
