"""agent.inbox: the receive queue is bounded by count and by bytes and never blocks a producer."""

from __future__ import annotations

import threading

import pytest

from agent.counters import Counters
from agent.inbox import ITEM_OVERHEAD, Inbox, offer_or_drop


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
