"""Versions of a robot's own map and the shared book of maps."""

from __future__ import annotations

import numpy as np

from agent.book import FleetBook, next_version
from agent.links import EPOCH_SHIFT, LinkCache, LinkRecord, epoch_of, needed_keys, select_links
from pgvd.grid import Grid


def V(epoch: int, minor: int = 0) -> int:
    return epoch << EPOCH_SHIFT | minor


def test_versions_are_epochs_and_minors_and_only_move_forward() -> None:
    first = next_version(None, 1000.7, new_epoch=False)
    assert first == 1000 << EPOCH_SHIFT and epoch_of(first) == 1000
    minor = next_version(first, 1005.0, new_epoch=False)
    assert minor == first + 1 and epoch_of(minor) == 1000
    assert epoch_of(next_version(minor, 1005.0, new_epoch=True)) == 1005
    assert epoch_of(next_version(minor, 900.0, new_epoch=True)) == 1001  # clock behind
    # A restart that lost its state dir starts an epoch newer than all it published.
    assert next_version(None, 1006.0, new_epoch=True) > next_version(minor, 1005.0, True)


def test_book_keeps_only_newer_maps() -> None:
    book = FleetBook()
    g = Grid(np.zeros((3, 3), np.float32))
    assert book.put_map("r1", 5, g) and not book.put_map("r1", 5, g)
    assert not book.put_map("r1", 4, g) and book.version("r1") == 5


def test_the_book_keeps_the_links_used_and_needed_as_a_full_recompute_would() -> None:
    """The book updates only the pairs a map or link touches (:class:`agent.book._Pairs`);
    after every step of a random history, the links it uses, the keys it needs and whether
    it is settled are those :func:`select_links` and :func:`needed_keys` find over a cache
    pruned in full."""
    rng = np.random.default_rng(7)
    robots = ["r1", "r2", "r3", "r4", "r5"]
    states = ["accepted", "rejected", "candidate", "confirmed"]
    book, reference = FleetBook(), LinkCache()
    g = Grid(np.zeros((3, 3), np.float32))
    held: dict[str, int] = {}
    for _ in range(600):
        a, b = sorted(str(r) for r in rng.choice(robots, 2, replace=False))
        op = rng.random()
        if op < 0.3:
            version = V(int(rng.integers(1, 6)), int(rng.integers(0, 3)))
            if book.put_map(a, version, g):
                held[a] = version
                reference.prune(held)
        elif op < 0.33:
            book.forget(a)
            held.pop(a, None)
            reference.forget(a)
        else:
            state = str(rng.choice(states))
            m = np.eye(3)
            m[0, 2] = float(rng.integers(0, 3))
            rec = LinkRecord(
                a, V(int(rng.integers(1, 6)), int(rng.integers(0, 3))),
                b, V(int(rng.integers(1, 6)), int(rng.integers(0, 3))),
                state in ("accepted", "confirmed"), m, np.eye(3), 1.0,
                str(rng.choice(robots)), state, revision=int(rng.integers(0, 2)),
            )  # fmt: skip
            if book.add_link(rec):
                assert reference.add(rec)
            elif rec.key[1] >= epoch_of(held.get(a, 0)) and rec.key[3] >= epoch_of(held.get(b, 0)):
                reference.add(rec)  # stored by the book too, though not the link it uses
        snap = book.snapshot()
        chosen, settled = select_links(held, reference)
        needed = needed_keys(held, reference)
        assert [r.identity for r in snap.links] == [r.identity for r in chosen]
        assert snap.needed == needed
        assert snap.settled == (settled and not needed)
        assert snap.rechecks == {ln.key for ln in chosen} & set(needed)
