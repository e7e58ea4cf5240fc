"""The agent's adapter over the protocol: versions out, maps and links in."""

from __future__ import annotations

import numpy as np
import pytest

import protocol
from agent import wire
from agent.keys import FleetKeys
from agent.links import LinkRecord
from pgvd.grid import Grid, rigid_matrix
from protocol import SCALE, ProtocolError, decode


def grid(seed: int, shape: tuple[int, int] = (300, 260)) -> Grid:
    rng = np.random.default_rng(seed)
    lo = np.zeros(shape, np.float32)
    lo[40:200, 30:220] = rng.normal(0, 4, (160, 190))
    return Grid(lo, 0.1, (2.0, -1.0, 0.0))


def test_own_map_is_stored_as_peers_decode_it() -> None:
    g = grid(1)
    w = wire.on_the_wire(g)
    assert np.abs(w.logodds - g.logodds).max() <= SCALE * 1.0001  # weak cells round away from 0
    assert not np.array_equal(w.logodds, g.logodds)
    np.testing.assert_array_equal(wire.on_the_wire(w).logodds, w.logodds)


@pytest.mark.parametrize("key", [None, b"fleet secret"])
def test_versions_delta_and_full_reach_a_peer_identically(key: bytes | None) -> None:
    out = wire.Outbound("f", "r1", key)
    inbound = wire.Inbound("f", key)
    v1, v2 = wire.on_the_wire(grid(1)), wire.on_the_wire(grid(2))
    for version, g, prev in ((1, v1, None), (2, v2, (1, v1))):
        tiles, manifest = out.prepare(version, g, prev)
        done = None
        for data in [*tiles, manifest]:
            done = inbound.feed(inbound.decode(data)) or done
        assert done is not None and done[0] == version
        np.testing.assert_array_equal(done[1].logodds, g.logodds)
    # A late joiner gets the full latest version from the queryable's replies.
    late = wire.Inbound("f", key)
    replies = out.latest_replies(FleetKeys("f"))
    assert replies[-1][0] == "pgvd/f/latest/r1/2/m"
    got = [late.feed(late.decode(d)) for _, d in replies]
    np.testing.assert_array_equal(got[-1][1].logodds, v2.logodds)


def test_a_delta_without_its_base_leaves_the_map_incomplete() -> None:
    out = wire.Outbound("f", "r1", None)
    v1, v2 = wire.on_the_wire(grid(1)), wire.on_the_wire(grid(2))
    out.prepare(1, v1, None)
    tiles, manifest = out.prepare(2, v2, (1, v1))
    inbound = wire.Inbound("f", None)
    for data in [*tiles, manifest]:
        assert inbound.feed(inbound.decode(data)) is None
    assert inbound.incomplete("r1")


def test_links_round_trip_and_non_rigid_ones_are_refused() -> None:
    rec = LinkRecord("r1", 3, "r2", 4, True, rigid_matrix(0.2, 5, 6), np.eye(3), 0.9, "r1")
    msg = decode(wire.encode_link("f", rec, None))
    back = wire.link_record(msg)
    assert back.key == rec.key and back.decided_by == "r1"
    np.testing.assert_allclose(back.matrix, rec.matrix)
    bad = LinkRecord("r1", 3, "r2", 4, True, np.diag([2.0, 2.0, 1.0]), np.eye(3), 0.9, "r1")
    with pytest.raises(ValueError, match="rigid"):
        wire.link_record(decode(wire.encode_link("f", bad, None)))


def test_wrong_key_is_a_protocol_error() -> None:
    tiles, _ = wire.Outbound("f", "r1", b"k1").prepare(1, grid(1), None)
    with pytest.raises(ProtocolError):
        wire.Inbound("f", b"k2").decode(tiles[0])


def test_accepted_link_with_a_covariance_that_is_not_psd_is_refused() -> None:
    cov = np.diag([1.0, 1.0, -0.5])
    rec = LinkRecord("r1", 3, "r2", 4, True, rigid_matrix(0.2, 5, 6), cov, 0.9, "r1")
    with pytest.raises(ValueError, match="semi-definite"):
        wire.link_record(decode(wire.encode_link("f", rec, None)))


def test_lost_datagram_tiles_come_back_in_a_fetch_of_only_those_tiles() -> None:
    """Best-effort tiles: a version whose manifest came but some tiles did not is completed by
    a fetch that names the missing tiles, and its answer holds nothing else."""
    out = wire.Outbound("f", "r1", b"k", datagrams=True)
    inbound = wire.Inbound("f", b"k")
    v1, v2 = wire.on_the_wire(grid(1, (600, 560))), wire.on_the_wire(grid(2, (600, 560)))
    for version, g, prev in ((1, v1, None), (2, v2, (1, v1))):
        tiles, manifest = out.prepare(version, g, prev)
        assert len(tiles) > 3
        packed = [t for t in tiles if len(inbound.decode(t).tiles) > 1]
        assert all(len(t) < wire.DATAGRAM_BYTES for t in packed)
        for data in [*tiles[::3], manifest]:  # two tile messages in three are lost
            inbound.feed(inbound.decode(data))
        assert inbound.incomplete("r1")
        pending, missing = inbound.wanted("r1")
        assert pending == version and missing
        params = protocol.fetch_parameters(pending, missing)
        fetch = protocol.parse_fetch(params["v"], params["tiles"])
        replies = out.latest_replies(FleetKeys("f"), fetch)
        sent = {t.index for _, d in replies[:-1] for t in inbound.decode(d).tiles}
        assert sent == set(missing)
        done = [x for _, d in replies if (x := inbound.feed(inbound.decode(d)))]
        assert len(done) == 1 and done[0][0] == version
        np.testing.assert_array_equal(done[0][1].logodds, g.logodds)
    # A fetch for a version the sender has left behind gets the whole latest one.
    stale = out.latest_replies(FleetKeys("f"), protocol.TileFetch(1, frozenset({0})))
    late = wire.Inbound("f", b"k")
    assert [late.feed(late.decode(d)) for _, d in stale][-1][0] == 2


def test_tile_budget_refills_at_its_rate_and_saves_at_most_one_second() -> None:
    t = 1000.0
    budget = wire.TileBudget(100, now=t)
    assert budget.take(100, now=t)
    assert not budget.take(1, now=t)
    assert budget.take(50, now=t + 0.5) and not budget.take(1, now=t + 0.5)
    assert not budget.take(101, now=t + 60.0)  # an idle minute saves one second's worth
    assert budget.take(100, now=t + 60.0)


def test_a_flood_of_tile_fetches_gets_the_prepared_whole_map_once_over_budget() -> None:
    out = wire.Outbound("f", "r1", None, datagrams=True)
    out.fetch_budget = wire.TileBudget(6)  # two fetches of three tiles a second
    out.prepare(1, wire.on_the_wire(grid(1, (600, 560))), None)
    whole = out.latest_replies(FleetKeys("f"))
    held = sorted({t.index for _, d in whole[:-1] for t in decode(d).tiles})
    fetch = protocol.TileFetch(1, frozenset(held[:3]))
    answers = [out.latest_replies(FleetKeys("f"), fetch) for _ in range(4)]
    sent = [{t.index for _, d in a[:-1] for t in decode(d).tiles} for a in answers]
    assert sent[:2] == [set(held[:3])] * 2  # within budget: exactly the named tiles
    assert answers[2:] == [whole, whole]  # then the bytes made in advance, no encoding
