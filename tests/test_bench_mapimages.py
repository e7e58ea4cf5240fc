"""bench.mapimages: thickened walls, part pairs whose truth is exact, the report."""

from __future__ import annotations

import numpy as np
import pytest

from bench.data.pairs import cluttered
from bench.mapimages import RESOLUTION, part_pairs, report, thickened
from bench.merge import evaluate
from pgvd.io import read_map
from pgvd.merge import merge


def test_thickened_grows_walls_and_keeps_the_rest():
    p = np.full((9, 9), 0.2)
    p[4, 4] = 0.9
    p[0, 0] = 0.5
    out = thickened(p, 1)
    assert np.array_equal(out > 0.65, np.pad(np.ones((3, 3), bool), 3))
    assert out[0, 0] == 0.5 and out[3, 3] == out[4, 4] == 0.95
    assert thickened(p, 0) is p


def test_part_pairs_truth_puts_b_walls_on_a_walls(shared):
    p = read_map(shared / "maps" / "fr079_albertB" / "map312.yaml").probability()
    pairs = part_pairs("fr079", p, 2, np.random.default_rng(0))
    assert [q.name for q in pairs] == ["fr079-f0", "fr079-f1"]
    for pair in pairs:
        rows, cols = np.nonzero(pair.b.probability() > 0.65)
        x, y = np.rint(pair.truth @ np.vstack([cols, rows, np.ones_like(rows)]))[:2].astype(int)
        inside = (x >= 0) & (x < pair.a.shape[1]) & (y >= 0) & (y < pair.a.shape[0])
        # B's walls in the shared 24 % land on A's walls (nearest warp: a cell at most)
        hits = pair.a.probability()[y[inside], x[inside]] > 0.65
        assert inside.mean() > 0.2 and hits.mean() > 0.9


def test_report_has_a_row_per_image_and_the_errors_of_right_pairs():
    rec = {"accepted": True, "success": True, "cell_err": 0.5, "heading_deg": 0.1}
    records = [
        {**rec, "source": "a-sim", "grow": 0},
        {**rec, "source": "a-sim", "grow": 2, "success": False, "cell_err": 9.0},
        {**rec, "source": "b-sim", "grow": 0, "accepted": False, "success": False},
        {**rec, "source": "b-sim", "grow": 2, "cell_err": 1.5},
    ]
    lines = report(records, "python3 -m bench mapimages").splitlines()
    assert "| a-sim | 1/1 right, 1 accepted; 0.50 / 0.50 | 0/1 right, 1 accepted |" in lines
    both = "| **all** | 1/2 right, 1 accepted; 0.50 / 0.50 | 1/2 right, 2 accepted; 1.50 / 1.50 |"
    assert both in lines


def test_clutter_turns_only_free_cells_into_discs_of_furniture():
    p = np.full((200, 200), 0.1)  # free, as map_saver writes it
    p[:, :50] = 0.5  # unexplored
    p[100, 50:] = 0.9  # a wall
    out = cluttered(p, 2.0, 0.05, seed=3)
    new = (out > 0.65) & (p <= 0.65)
    assert new.any() and (p[new] == 0.1).all()  # only free cells were drawn
    assert np.array_equal(out[p > 0.1], p[p > 0.1])
    assert np.array_equal(out, cluttered(p, 2.0, 0.05, seed=3))
    assert np.array_equal(cluttered(p, 0.0, 0.05, seed=3), p)
    with pytest.raises(ValueError, match="density >= 0"):
        cluttered(p, -1.0, 0.05, seed=3)


def test_a_cluttered_real_image_pair_merges_right(shared):
    # intel's image with a desk, chair or bin every 3 square metres drawn in (filled), both
    # parts cut from it: not every frame of it merges (bench/results/mapimages-clutter-0.3.md)
    p = read_map(shared / "maps" / "intel" / "intel.yaml").probability()
    pair = part_pairs(
        "intel", cluttered(p, 0.3, RESOLUTION, seed=21), 1, np.random.default_rng(21)
    )[0]
    result = merge(pair.a, pair.b)
    assert evaluate(pair, result.accepted, result.matrix)["success"], result.reason
