"""The merge pipeline (Fig. 1) on real maps: accuracy, the three fr079 runs, rejection."""

from __future__ import annotations

import re

import numpy as np
import pytest

from bench.mapimages import random_framed as _random_frame
from bench.mapimages import thickened
from pgvd.grid import Grid, relative_matrix, rigid_matrix
from pgvd.inputs import registration_probability
from pgvd.io import read_map
from pgvd.merge import merge
from pgvd.params import MergeParams
from pgvd.result import MergeResult
from pgvd.rotation import estimate_headings
from pgvd.transform import resample

SPLITS = {
    "intel": ("intel_split_gt/intel_partA.yaml", "intel_split_gt/intel_partB.yaml"),
    "fr079": ("fr079_split_gt/fr079_partA.yaml", "fr079_split_gt/fr079_partB.yaml"),
}


def _load(shared, rel: str) -> Grid:
    g = read_map(shared / "maps" / rel)
    return g if np.isclose(g.resolution, 0.05) else resample(g, 0.05)


def _errors(result: MergeResult, truth: np.ndarray, b: Grid) -> tuple[float, float]:
    """(heading error in degrees, mean displacement in cells over B's occupied cells)."""
    r, c = np.nonzero(b.probability() > 0.65)
    pts = np.column_stack([c, r, np.ones(r.size)])
    disp = np.linalg.norm((pts @ (result.matrix - truth).T)[:, :2], axis=1).mean()
    dpsi = np.arctan2(result.matrix[0, 1], result.matrix[0, 0]) - np.arctan2(
        truth[0, 1], truth[0, 0]
    )
    return abs(float(np.degrees(np.angle(np.exp(1j * dpsi))))), float(disp)


@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(SPLITS))
def test_split_gt_recovered_in_random_frames(shared, name):
    a, b = (_load(shared, p) for p in SPLITS[name])
    truth = relative_matrix(a, b)
    rng = np.random.default_rng(2024)
    good = []
    for _ in range(10):
        bn, to_new = _random_frame(b, rng)
        result = merge(a, bn, MergeParams(diagnostics=False))
        dpsi, disp = _errors(result, truth @ np.linalg.inv(to_new), bn)
        good.append(result.accepted and dpsi < 1.0 and disp < 2.0)
    assert sum(good) >= 9, good


@pytest.fixture(scope="module")
def albert(shared):
    maps = {n: _load(shared, f"fr079_albertB/map{n}.yaml") for n in (312, 342, 371)}
    return {(i, j): merge(maps[i], maps[j]) for i, j in ((312, 342), (312, 371), (342, 371))}


def test_fr079_albert_runs_merge_near_identity(albert):
    for pair, r in albert.items():
        assert r.accepted, (pair, r.reason)
        assert r.score > 0.9
        # the three gmapping runs share a start pose: the truth is close to identity
        assert abs(r.rotation_deg) < 2.0, pair
        assert np.hypot(*r.translation_px) < 20.0, pair
    # and the three pairwise transforms are consistent: M(312<-371) = M(312<-342) M(342<-371)
    chained = albert[(312, 342)].matrix @ albert[(342, 371)].matrix
    np.testing.assert_allclose(chained, albert[(312, 371)].matrix, atol=1.5)


def test_result_json_and_diagnostics(albert, shared):
    r = albert[(342, 371)]
    js = r.to_json()
    assert set(js) == {
        "accepted", "matrix", "rotation_deg", "translation_px", "covariance", "score",
        "timings_ms", "reason", "margin", "distortion_px", "candidate",
    }  # fmt: skip
    assert js["margin"] >= MergeParams().min_margin and js["distortion_px"] >= 0
    assert np.array(js["matrix"]).shape == (3, 3) and np.array(js["covariance"]).shape == (3, 3)
    assert js["timings_ms"]["total"] >= max(v for k, v in js["timings_ms"].items() if k != "total")
    assert {"rotation", "pgvd", "graph", "gamma", "verify", "refine"} <= set(js["timings_ms"])
    assert np.all(np.linalg.eigvalsh(r.covariance) > 0)
    d = r.diagnostics
    assert d is not None and d.pgvd_a.shape == d.edges_a.shape == (800, 1184)
    assert d.pgvd_b.shape == d.edges_b.shape == (800, 1184)
    assert d.edges_a.any() and d.edges_b.any() and d.gamma.ndim == 2
    assert d.support >= MergeParams().min_pairs  # several edge pairs agree on the transform
    # B's matched edges, moved by the result, land on A's matched edges
    r_b, c_b = np.nonzero(d.edges_b)
    moved = np.column_stack([c_b, r_b, np.ones(r_b.size)]) @ r.matrix.T
    x, y = np.rint(moved[:, 0]).astype(int), np.rint(moved[:, 1]).astype(int)
    near_a = np.zeros_like(d.edges_a)
    ra, ca = np.nonzero(d.edges_a)
    for dy in range(-4, 5):
        for dx in range(-4, 5):
            near_a[np.clip(ra + dy, 0, 799), np.clip(ca + dx, 0, 1183)] = True
    assert near_a[np.clip(y, 0, 799), np.clip(x, 0, 1183)].mean() > 0.8


@pytest.mark.parametrize(
    "pair",
    [
        ("intel_split_gt/intel_partA.yaml", "fr079_split_gt/fr079_partB.yaml"),
        ("intel_split_gt/intel_partB.yaml", "willow/willow-2010-02-18-0.10.yaml"),
        ("fr079_split_gt/fr079_partA.yaml", "uos_avz/avz.yaml"),
    ],
)
def test_maps_of_different_buildings_rejected(shared, pair):
    a, b = (_load(shared, p) for p in pair)
    bn, _ = _random_frame(b, np.random.default_rng(7))
    r = merge(a, bn, MergeParams(diagnostics=False))
    assert not r.accepted, r.to_json()
    # each is turned away by the margin, and the reason says what its best rival was
    rival = r"none|the pose shifted [\d.]+ m|another pose [\d.]+ m and \d+ deg away"
    assert re.fullmatch(
        rf"the best pose does not stand out: margin -?[\d.]+ < [\d.]+ "
        rf"\(evidence -?\d+, best rival -?(\d+|inf): ({rival})\)",
        r.reason,
    ), r.reason


@pytest.mark.parametrize("name", ["intel/intel.yaml", "uos_avz/avz.yaml"])
def test_overlapping_parts_of_one_map_recovered(shared, name):
    """Two 62 % wide parts of one real map (24 % of the width shared), each in its own frame."""
    p = _load(shared, name).probability()
    w = p.shape[1]
    cut_a, cut_b = round(0.62 * w), round(0.38 * w)
    a = Grid.from_probability(p[:, :cut_a], 0.05)
    b = Grid.from_probability(p[:, cut_b:], 0.05)
    truth = rigid_matrix(0.0, float(cut_b), 0.0)
    rng = np.random.default_rng(5)
    for _ in range(2):
        bn, to_new = _random_frame(b, rng)
        result = merge(a, bn, MergeParams(diagnostics=False))
        dpsi, disp = _errors(result, truth @ np.linalg.inv(to_new), bn)
        assert result.accepted and dpsi < 1.0 and disp < 2.0, (result.reason, dpsi, disp)


@pytest.mark.parametrize(
    "name",
    [
        "intel/intel.yaml",
        "fr079_albertB/map312.yaml",
        # long look-alike corridors: the hardest false overlays seen (agreement up to 0.89)
        "mit_stata_basement/stata_basement.yaml",
    ],
)
def test_disjoint_halves_of_one_building_rejected(shared, name):
    p = _load(shared, name).probability()
    mid = p.shape[1] // 2
    left = Grid.from_probability(p[:, : mid - 30], 0.05)  # a 60-cell (3 m) gap between them
    right = Grid.from_probability(p[:, mid + 30 :], 0.05)
    rng = np.random.default_rng(11)
    for _ in range(2):
        r = merge(_random_frame(left, rng)[0], _random_frame(right, rng)[0])
        assert not r.accepted, r.to_json()


def test_bad_inputs_raise_clear_errors():
    p = np.full((40, 40), 0.1)
    p[5, 5:35] = 0.9
    a = Grid.from_probability(p, 0.05)
    with pytest.raises(ValueError, match="resolution"):
        merge(a, Grid.from_probability(p, 0.1))
    with pytest.raises(ValueError, match="no occupied"):
        merge(a, Grid.from_probability(np.full((40, 40), 0.1), 0.05))
    with pytest.raises(TypeError, match=r"map B must be a pgvd\.Grid .* got ndarray"):
        merge(a, p)


@pytest.mark.parametrize("name", ["intel/intel.yaml", "fr079_albertB/map312.yaml"])
def test_thick_walls_align_to_the_cell(shared, name):
    """A map drawn with 5-cell walls (as many map images are) against a crop of itself.

    Inside a thick wall every cell has a wall at distance 0, so a refinement
    on all wall cells stopped wherever it entered: this pair came out 1.7 px
    off; on the walls' faces it lands on the exact shift.
    """
    p = thickened(_load(shared, name).probability(), 2)
    cut = p.shape[1] // 4
    a = Grid.from_probability(p, 0.05)
    b = Grid.from_probability(p[:, cut:], 0.05)
    result = merge(a, b, MergeParams(diagnostics=False))
    dpsi, disp = _errors(result, rigid_matrix(0.0, float(cut), 0.0), b)
    assert result.accepted and dpsi < 0.05 and disp < 0.25, (result.reason, dpsi, disp)


def test_heading_offset_turns_every_searched_heading(shared):
    # the bench's measure of how much a merge hangs on its heading estimate
    # (pgvd-turned+0.1): every heading the search went through is a candidate of (10)
    # turned by the offset
    a, b = (_load(shared, p) for p in SPLITS["intel"])
    params = MergeParams(diagnostics=False, heading_offset=0.5)
    candidates = estimate_headings(
        registration_probability(a, params),
        registration_probability(b, params),
        params.max_candidates,
    )
    searched = merge(a, b, params).headings_deg
    assert searched
    for deg in searched:
        turns = [np.angle(np.exp(1j * np.radians(deg - np.degrees(c.psi)))) for c in candidates]
        assert min(abs(np.degrees(t) - 0.5) for t in turns) < 1e-6, deg
