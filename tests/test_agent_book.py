"""Versions of a robot's own map and the shared book of maps."""

from __future__ import annotations

import numpy as np

from agent.book import FleetBook, next_version
from pgvd.grid import Grid


def test_versions_move_forward_even_after_a_lost_state_dir() -> None:
    assert next_version(None, 1000.0) == 1_000_000
    assert next_version(1_000_000, 1000.0) == 1_000_001  # same millisecond
    assert next_version(5_000_000, 1000.0) == 5_000_001  # clock behind: still forward
    before_crash = next_version(next_version(None, 1000.0), 1001.0)
    assert next_version(None, 1002.0) > before_crash  # fresh start outranks the old maps


def test_book_keeps_only_newer_maps() -> None:
    book = FleetBook()
    g = Grid(np.zeros((3, 3), np.float32))
    assert book.put_map("r1", 5, g) and not book.put_map("r1", 5, g)
    assert not book.put_map("r1", 4, g) and book.version("r1") == 5
