"""bench.mapimages: thickened walls, part pairs whose truth is exact, the report."""

from __future__ import annotations

import numpy as np

from bench.mapimages import part_pairs, report, thickened
from pgvd.io import read_map


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
    lines = report(records, "python3 -m bench.mapimages").splitlines()
    assert "| a-sim | 1/1 right, 1 accepted; 0.50 / 0.50 | 0/1 right, 1 accepted |" in lines
    both = "| **all** | 1/2 right, 1 accepted; 0.50 / 0.50 | 1/2 right, 2 accepted; 1.50 / 1.50 |"
    assert both in lines
