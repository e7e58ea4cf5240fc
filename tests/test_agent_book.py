"""Versions of a robot's own map and the shared book of maps."""

from __future__ import annotations

import numpy as np

from agent.book import FleetBook, next_version
from agent.links import EPOCH_SHIFT, epoch_of
from pgvd.grid import Grid


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
