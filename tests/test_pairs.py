"""bench.data.pairs: two robots' maps from two segments of a real log, with their true matrix."""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy import ndimage

from bench.data.pairs import (
    MIN_OVERLAP,
    make_pair,
    make_pairs,
    overlap_fraction,
    painted_pair,
    write_pair,
)
from pgvd.carmen import read_carmen
from pgvd.grid import rigid_matrix
from pgvd.io import read_map


@pytest.fixture(scope="module")
def intel(shared):
    return read_carmen(shared / "logs" / "intel-corrected.log.gz")


@pytest.fixture(scope="module")
def split(intel):
    return make_pair(intel, (0.0, 0.55), (0.45, 1.0), seed=3, name="intel-split")


def _walls_on_walls(a, b, m):
    """Fraction of B's wall cells that land within 1.5 cells of A's walls, where A has seen."""
    rows, cols = np.nonzero(b.logodds > 0)
    x, y = np.rint((m @ np.vstack([cols, rows, np.ones_like(cols)]))[:2]).astype(int)
    inside = (x >= 0) & (x < a.shape[1]) & (y >= 0) & (y < a.shape[0])
    x, y = x[inside], y[inside]
    seen = a.logodds[y, x] != 0
    dist = ndimage.distance_transform_edt(a.logodds <= 0)[y[seen], x[seen]]
    return np.mean(dist <= 1.5)


def test_truth_lays_b_walls_on_a_walls(split):
    assert split.a.shape != split.b.shape or not np.array_equal(split.a.logodds, split.b.logodds)
    assert np.isclose(np.linalg.det(split.truth[:2, :2]), 1.0)  # rigid, eqs. (1)-(2)
    assert _walls_on_walls(split.a, split.b, split.truth) > 0.9
    # A one-degree or three-cell error is clearly visible: the truth is sharp.
    assert _walls_on_walls(split.a, split.b, rigid_matrix(0.0, 3.0, 0.0) @ split.truth) < 0.75
    turned = split.truth @ rigid_matrix(np.radians(1.0), 0.0, 0.0)
    assert _walls_on_walls(split.a, split.b, turned) < 0.5
    assert 0.5 < split.overlap < 1.0


def test_deterministic_from_seed(intel, split):
    again = make_pair(intel, (0.0, 0.55), (0.45, 1.0), seed=3)
    np.testing.assert_array_equal(again.a.logodds, split.a.logodds)
    np.testing.assert_array_equal(again.truth, split.truth)
    other = make_pair(intel, (0.0, 0.55), (0.45, 1.0), seed=4)
    assert not np.allclose(other.truth, split.truth)
    # A different frame changes the pixels, not the overlap of what was seen.
    assert other.overlap == pytest.approx(split.overlap, abs=0.03)


def test_overlap_fraction_bounds(split):
    assert overlap_fraction(split.a, split.a, np.eye(3)) == 1.0
    far = rigid_matrix(0.0, 10_000.0, 0.0) @ split.truth
    assert overlap_fraction(split.a, split.b, far) == 0.0


def test_make_pairs_overlapping_and_disjoint(intel):
    pairs = make_pairs(intel, n_overlap=1, n_disjoint=1, seed=7, name="intel")
    assert [p.name for p in pairs] == ["intel-ov00", "intel-dj00"]
    overlapping, disjoint = pairs
    assert overlapping.overlap >= MIN_OVERLAP
    assert disjoint.overlap == 0.0
    assert (disjoint.a.logodds != 0).sum() > 10_000 and (disjoint.b.logodds != 0).sum() > 10_000
    assert _walls_on_walls(overlapping.a, overlapping.b, overlapping.truth) > 0.85
    again = make_pairs(intel, n_overlap=1, n_disjoint=0, seed=7, name="intel")
    np.testing.assert_array_equal(again[0].truth, overlapping.truth)


def test_write_pair_round_trip(split, tmp_path):
    paths = {k: tmp_path / f"intel_{k}" for k in ("a.yaml", "b.yaml", "truth.json")}
    write_pair(split, *paths.values())
    a = read_map(paths["a.yaml"])
    assert a.shape == split.a.shape and a.origin == pytest.approx(split.a.origin)
    assert np.array_equal(a.logodds > 0, split.a.probability() > 0.65)
    assert read_map(paths["b.yaml"]).shape == split.b.shape
    doc = json.loads(paths["truth.json"].read_text())
    np.testing.assert_allclose(doc["matrix"], split.truth, atol=1e-8)
    assert doc["overlap"] == split.overlap and doc["seg_a"] == ["fraction", 0.0, 0.55]


def test_bundled_examples_reproduce(tmp_path):
    """examples/ is what ``python3 -m bench make_examples`` writes (up to float round-off)."""
    from bench.make_examples import ROOT, main

    assert main(["--out", str(tmp_path)]) == 0
    shipped = ROOT / "examples"
    for name in ("intel_a.yaml", "intel_b.yaml"):
        fresh, old = read_map(tmp_path / name), read_map(shipped / name)
        assert fresh.shape == old.shape and fresh.origin == pytest.approx(old.origin)
        assert np.mean(fresh.logodds != old.logodds) < 1e-4, name
    fresh, old = (json.loads((d / "truth.json").read_text()) for d in (tmp_path, shipped))
    np.testing.assert_allclose(fresh["matrix"], old["matrix"], atol=1e-6)
    assert fresh["overlap"] == pytest.approx(old["overlap"], abs=1e-4)


def test_drifted_pair_truth_is_the_best_rigid_placement(intel, split):
    noisy = make_pair(intel, (0.0, 0.55), (0.45, 1.0), seed=3, odom_noise=(0.01, 0.002))
    assert not np.array_equal(noisy.b.logodds, split.b.logodds)
    # Drifted walls are blurred, yet the fitted truth still lays most of them on A's walls.
    fitted = _walls_on_walls(noisy.a, noisy.b, noisy.truth)
    assert 0.5 < fitted < _walls_on_walls(split.a, split.b, split.truth)
    # ...and shifting it by three cells makes that clearly worse.
    assert _walls_on_walls(noisy.a, noisy.b, rigid_matrix(0.0, 3.0, 0.0) @ noisy.truth) < fitted


@pytest.fixture(scope="module")
def avz_run(shared):
    from bench.data.sources import SOURCES, simulate

    return simulate(next(s for s in SOURCES if s.name == "avz-sim"), seed=1, shared=shared)


def test_simulated_pair_truth_reproduces_the_overlap(avz_run):
    """The overlap seen through the true matrix equals the overlap of the two segments'
    maps rendered in one shared world frame, where no matrix is involved."""
    from pgvd.integrate import frame_for, integrate, select_segment

    pair = make_pair(avz_run, (0.0, 0.4), (0.25, 0.7), seed=11, name="avz")
    shared_frame = frame_for(avz_run, 0.05)
    a, b = (
        integrate(select_segment(avz_run, s), shared_frame).logodds != 0
        for s in ((0.0, 0.4), (0.25, 0.7))
    )
    direct = (a & b).sum() / min(a.sum(), b.sum())
    assert 0.2 < pair.overlap < 0.95
    assert pair.overlap == pytest.approx(direct, abs=0.03)
    assert _walls_on_walls(pair.a, pair.b, pair.truth) > 0.9


def test_mirror_scans_reflect_every_hit(avz_run):
    from bench.data.negatives import mirror_scans

    part = avz_run[100:110]
    mirrored = mirror_scans(part)
    for s, m in zip(part, mirrored, strict=True):
        hit = s.ranges < 80
        ang, ang_m = s.beam_angles()[hit], m.beam_angles()[m.ranges < 80]
        r = s.ranges[hit]
        ends = s.pose[:2] + np.column_stack([r * np.cos(ang), r * np.sin(ang)])
        r_m = m.ranges[m.ranges < 80]
        ends_m = m.pose[:2] + np.column_stack([r_m * np.cos(ang_m), r_m * np.sin(ang_m)])
        # Beam order is reversed, so the hits come back in reverse order, reflected in y.
        np.testing.assert_allclose(ends_m[::-1], ends * [1.0, -1.0], atol=1e-5)
    assert mirror_scans(mirrored)[3].pose == pytest.approx(part[3].pose)


def test_drifted_pair_truth_is_the_fit_on_the_overlap(intel):
    from bench.data.drift import Drift

    segments = ((0.0, 0.2), (0.1, 0.3))
    clean = make_pair(intel, *segments, seed=3)
    # Without noise the fit on the overlap is exact: the truth of the clean pair.
    still = make_pair(intel, *segments, seed=3, odom_noise=Drift(0.0, 0.0, 0.0))
    np.testing.assert_allclose(still.truth, clean.truth, atol=1e-6)
    assert still.info["drift_rms_m"] < 1e-6 and still.info["drift_fit_points"] > 1000
    noisy = make_pair(intel, *segments, seed=3, odom_noise=Drift())
    assert 0.01 < noisy.info["drift_rms_m"] < 1.0
    # The drift moves the overlap by a little, not by a different pose.
    turn = np.degrees(np.arctan2(noisy.truth[0, 1], noisy.truth[0, 0]))
    clean_turn = np.degrees(np.arctan2(clean.truth[0, 1], clean.truth[0, 0]))
    assert abs((turn - clean_turn + 180) % 360 - 180) < 5.0
    assert noisy.overlap == pytest.approx(clean.overlap, abs=0.15)


def test_gmapping_runs_meet_at_their_common_origin(shared):
    from bench.data.gmapping import gmapping_pairs

    pairs = gmapping_pairs(6, seed=2, shared=shared)
    assert len({(p.info["a"], p.info["b"]) for p in pairs}) == 6
    for p in pairs:
        assert p.overlap > 0.9  # three maps of one building
        fitted = _walls_on_walls(p.a, p.b, p.truth)
        assert fitted > 0.6, p.name
        turned = p.truth @ rigid_matrix(np.radians(2.0), 0.0, 0.0)
        assert _walls_on_walls(p.a, p.b, turned) < fitted


def test_painted_pair_reads_free_where_a_saved_map_draws_unknown(split):
    from pgvd.map_shades import FREE_THRESH, OCCUPIED_THRESH, P_FREE

    painted = painted_pair(split)
    for before, after in ((split.a, painted.a), (split.b, painted.b)):
        p, q = before.probability(), after.probability()
        unknown = (p >= FREE_THRESH) & (p <= OCCUPIED_THRESH)
        assert unknown.mean() > 0.3  # a robot's partial map is mostly unknown
        assert np.allclose(q[unknown], P_FREE, atol=1e-6)
        assert np.allclose(q[~unknown], p[~unknown], atol=1e-6)
    assert painted.truth is split.truth and painted.name == split.name
