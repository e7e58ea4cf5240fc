"""bench.soak's steadiness measure: moves between consecutive global maps, by kind."""

from __future__ import annotations

import numpy as np
import pytest

from bench.soak import anchor_moves, jumps, placement_move
from pgvd.grid import rigid_matrix


def _map(t: float, x: np.ndarray, links: list) -> dict:
    eye = np.eye(3).tolist()
    return {"t": t, "digest": str(t), "members": ["r1", "r2"], "links": links,
            "transforms": {"r1": eye, "r2": x.tolist()}}  # fmt: skip


def test_placement_move_over_the_canvas_corners() -> None:
    cells, deg = placement_move(np.eye(3).tolist(), rigid_matrix(0.0, 3.0, 4.0).tolist(), (10, 10))
    assert cells == pytest.approx(5.0) and deg == pytest.approx(0.0)
    turn = rigid_matrix(np.radians(0.5), 0.0, 0.0)
    cells, deg = placement_move(np.eye(3).tolist(), turn.tolist(), (101, 101))
    assert deg == pytest.approx(0.5) and cells == pytest.approx(
        np.hypot(100, 100) * np.radians(0.5), rel=1e-3
    )


def test_jumps_split_same_links_from_new_links() -> None:
    x = rigid_matrix(0.2, 50.0, 10.0)
    same = [("r1", "r2", "r1", 1, 1)]
    history = {
        "r1": [
            _map(0.0, x, same),
            _map(1.0, x, same),  # a new version, same link: no move
            _map(2.0, rigid_matrix(0.2, 52.0, 10.0), [("r1", "r2", "r1", 2, 1)]),  # new link
        ]
    }
    out = jumps(history, lambda robot: (10, 10))
    assert out["same_links"] == {"cells": 0.0, "deg": 0.0, "pairs": 1}
    assert out["all"]["pairs"] == 2 and out["all"]["cells"] == pytest.approx(2.0)
    history["r1"][1]["members"] = ["r1", "r2", "r3"]  # membership changed: not compared
    assert jumps(history, lambda robot: (10, 10))["all"]["pairs"] == 0


def test_anchor_moves_tell_a_jump_from_a_departure() -> None:
    def seen(anchor: str, members: list[str]) -> dict:
        return {"anchor": anchor, "members": members}

    history = {
        "r2": [
            seen("r1", ["r1", "r2"]),
            seen("r1", ["r1", "r2", "r3"]),  # r3 joins: the frame stays
            seen("r0", ["r0", "r1", "r2", "r3"]),  # r0 joins and takes the frame: a jump
            seen("r1", ["r1", "r2", "r3"]),  # r0 forgotten: the frame follows its departure
        ],
        "r0": [seen("r0", ["r0"]), seen("r1", ["r0", "r1", "r2", "r3"])],  # a lone robot merged
    }
    assert anchor_moves(history) == {"changes": 3, "jumps": 1}
