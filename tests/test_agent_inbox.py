"""agent.inbox: the receive queue is bounded by count and by bytes and never blocks a producer."""

from __future__ import annotations

import threading
from pathlib import Path

import numpy as np
import pytest

from agent.counters import Counters
from agent.inbox import ITEM_OVERHEAD, Inbox, MapTag, held_already, map_tag, offer_or_drop
from agent.keys import FleetKeys
from agent.wire import Inbound
from pgvd.grid import Grid
from pgvd.io import read_map
from protocol import encode_map


def item(size: int, key: str = "pgvd/t/tiles/r1") -> tuple[str, str, bytes]:
    return ("tiles", key, bytes(size))


def test_a_flood_of_big_messages_is_bounded_by_bytes() -> None:
    """64 KB messages: the byte bound refuses long before the count bound would."""
    inbox = Inbox(max_items=20_000, max_bytes=1 << 20)
    accepted = sum(inbox.offer(item(65_536)) for _ in range(1_000))
    cost = Inbox.cost(item(65_536))
    assert accepted == (1 << 20) // cost == 15
    assert inbox.queued_bytes == accepted * cost <= inbox.max_bytes
    # A small message still fits in what is left; draining makes room again.
    assert inbox.offer(item(100))
    assert inbox.get(0.0) == item(65_536)
    assert inbox.offer(item(65_536))
    assert not inbox.offer(item(65_536))


def test_a_flood_of_tiny_messages_is_bounded_by_count() -> None:
    inbox = Inbox(max_items=100, max_bytes=1 << 20)
    assert sum(inbox.offer(item(10)) for _ in range(1_000)) == 100
    assert len(inbox) == 100
    assert inbox.queued_bytes == 100 * (len("tiles") + len("pgvd/t/tiles/r1") + 10 + ITEM_OVERHEAD)


def test_fifo_and_accounting_return_to_zero() -> None:
    inbox = Inbox()
    sent = [item(n, f"pgvd/t/tiles/r{n}") for n in (0, 5, 70_000)]
    assert all(inbox.offer(x) for x in sent)
    assert [inbox.get(0.0) for _ in sent] == sent
    assert inbox.get(0.0) is None
    assert (len(inbox), inbox.queued_bytes) == (0, 0)


def test_a_message_bigger_than_the_whole_bound_is_refused() -> None:
    inbox = Inbox(max_bytes=1_000)
    assert not inbox.offer(item(1_000))
    assert (len(inbox), inbox.queued_bytes) == (0, 0)


def test_producers_never_block_while_the_consumer_is_stalled() -> None:
    """Four producer threads (as Zenoh's callbacks) offer 40 MB to a stalled consumer."""
    inbox = Inbox(max_bytes=4 << 20)
    refused = [0] * 4

    def produce(i: int) -> None:
        for _ in range(250):
            refused[i] += not inbox.offer(item(40_000))

    threads = [threading.Thread(target=produce, args=(i,)) for i in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=30)
    assert not any(t.is_alive() for t in threads)  # nobody waited for room
    assert len(inbox) + sum(refused) == 1_000
    assert inbox.queued_bytes <= 4 << 20 and len(inbox) == (4 << 20) // Inbox.cost(item(40_000))


def test_get_waits_for_a_producer_and_times_out() -> None:
    inbox = Inbox()
    assert inbox.get(0.05) is None
    threading.Timer(0.05, inbox.offer, args=(item(1),)).start()
    assert inbox.get(5.0) == item(1)


def test_bounds_must_leave_room() -> None:
    with pytest.raises(ValueError, match="at least one item"):
        Inbox(max_items=0)


def test_the_agent_counts_what_does_not_fit_as_overload() -> None:
    """offer_or_drop, as the agent's Zenoh callbacks call it: no session needed, nothing blocks."""
    inbox, counters = Inbox(max_bytes=100_000), Counters()
    assert [offer_or_drop(inbox, item(40_000), counters) for _ in range(5)] == [True] * 2 + [
        False
    ] * 3
    assert len(inbox) == 2
    assert counters.snapshot()["drops"] == {"overload": 3}


# ------------------------------------------------------------- superseded versions

KEY = b"the lab's fleet key"
V1, V2 = 5 << 31, (5 << 31) + 1


@pytest.fixture(scope="module")
def versions(shared: Path) -> tuple[tuple[list[bytes], bytes], tuple[list[bytes], bytes]]:
    """r2's map (the Intel lab's first half, 604 x 605) as v1 in datagram-sized tile messages,
    then v2 as a delta: a wall added."""
    v1 = read_map(shared / "maps" / "intel_split_gt" / "intel_partA.yaml")
    changed = v1.logodds.copy()
    changed[40:200, 100:104] = 3.0
    v2 = Grid(changed, v1.resolution, v1.origin)
    first = encode_map("lab", "r2", V1, v1, KEY, max_message_bytes=1_200, tile_size=64)
    return first, encode_map("lab", "r2", V2, v2, KEY, since=v1, base_version=V1)


def tag(key: str, data: bytes) -> MapTag | None:
    return map_tag(Inbound("lab", KEY), FleetKeys("lab"), key, data)


def offer(inbox: Inbox, counters: Counters, key: str, data: bytes) -> bool:
    """As the agent's Zenoh callbacks queue a payload that came on ``key``."""
    return offer_or_drop(inbox, ("message", key, data), counters, tag(key, data))


def test_queued_tiles_of_a_superseded_version_dropped(versions) -> None:
    """Tiles of v1 still queued leave when v2 arrives; a late v1 tile is refused; r2's v1
    manifest and another robot's tiles stay. Each tile message dropped counts once."""
    (tiles1, manifest1), (tiles2, _) = versions
    assert len(tiles1) > 3 and tiles2
    inbox, counters = Inbox(), Counters()
    other = encode_map("lab", "r3", 1, Grid(np.full((64, 64), 2.0, np.float32), 0.05), KEY)[0]
    queued = [("pgvd/lab/tiles/r2", t) for t in tiles1[:-1]]
    queued += [("pgvd/lab/manifest/r2", manifest1), ("pgvd/lab/tiles/r3", other[0])]
    assert all(offer(inbox, counters, key, data) for key, data in queued)
    assert offer(inbox, counters, "pgvd/lab/tiles/r2", tiles2[0])
    assert counters.snapshot()["drops"] == {"superseded": len(tiles1) - 1}
    assert not offer(inbox, counters, "pgvd/lab/tiles/r2", tiles1[-1])
    assert counters.snapshot()["drops"] == {"superseded": len(tiles1)}
    left = [inbox.get(0.0) for _ in range(len(inbox))]
    assert [data for _, _, data in left] == [manifest1, other[0], tiles2[0]]
    assert inbox.queued_bytes == 0


def test_a_reply_of_the_newer_version_supersedes_pushed_tiles(versions) -> None:
    """A fetch's reply (``latest/<robot>/<version>/...``) tags like a pushed message."""
    (tiles1, _), (_, manifest2) = versions
    inbox, counters = Inbox(), Counters()
    assert all(offer(inbox, counters, "pgvd/lab/tiles/r2", t) for t in tiles1)
    reply = f"pgvd/lab/latest/r2/{V2}/m"
    assert tag(reply, manifest2) == MapTag("r2", V2, tiles=False)
    assert offer(inbox, counters, reply, manifest2)
    assert len(inbox) == 1 and counters.snapshot()["drops"] == {"superseded": len(tiles1)}


def test_only_an_authentic_message_under_its_own_robots_key_supersedes(versions) -> None:
    """A forged newer version (wrong key), or r3 publishing r2's version, removes nothing."""
    (tiles1, _), (tiles2, _) = versions
    forged = encode_map("lab", "r2", V2 + 7, Grid(np.ones((64, 64), np.float32), 0.05), b"x")[0]
    assert tag("pgvd/lab/tiles/r2", forged[0]) is None
    assert tag("pgvd/lab/tiles/r3", tiles2[0]) is None
    assert tag("pgvd/lab/tiles/r2", b"PG\x02\x01" + bytes(40)) is None
    inbox, counters = Inbox(), Counters()
    assert offer(inbox, counters, "pgvd/lab/tiles/r2", tiles1[0])
    for key, data in (("pgvd/lab/tiles/r2", forged[0]), ("pgvd/lab/tiles/r3", tiles2[0])):
        assert offer(inbox, counters, key, data)
    assert len(inbox) == 3 and counters.snapshot()["drops"] == {}


def test_only_a_peers_message_of_the_version_held_is_left_undecoded(versions) -> None:
    """r2's re-announced v2 manifest, taken with its tag, is of the version held; a v1 tile
    is older (the core counts it stale), and neither r2 as this robot nor an untagged
    payload is skipped."""
    (tiles1, _), (_, manifest2) = versions
    inbox, counters = Inbox(), Counters()
    assert offer(inbox, counters, "pgvd/lab/manifest/r2", manifest2)
    assert inbox.offer(("message", "pgvd/lab/link/r2", b"not a map"))
    (_, manifest), (_, untagged) = (inbox.get_tagged(0.0) for _ in range(2))
    older = tag("pgvd/lab/tiles/r2", tiles1[0])
    holding = {"r2": V2}.get
    assert [held_already(t, "r1", holding) for t in (manifest, older, untagged)] == [
        True,
        False,
        False,
    ]
    assert not held_already(manifest, "r2", holding)
    assert not held_already(manifest, "r1", {}.get)
