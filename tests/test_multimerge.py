"""Offline merge of many maps: real maps, the agents' registration and global map."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from agent.multimerge import merge_many
from agent.worker import Registration, merge_registration
from pgvd.grid import Grid, relative_matrix, rigid_matrix
from pgvd.io import read_map
from pgvd.transform import resample

CORNERS = np.array([[0, 1000, 0, 1000], [0, 0, 800, 800], [1, 1, 1, 1]])


def corner_gap(m: np.ndarray, n: object) -> float:
    """Largest distance (px) between where two matrices send a map's corners."""
    return float(np.abs((np.asarray(m) - np.asarray(n)) @ CORNERS).max())


@pytest.fixture(scope="module")
def albert(shared: Path) -> tuple[list[str], dict]:
    files = [str(shared / "maps" / "fr079_albertB" / f"map{n}.yaml") for n in (312, 342, 371)]
    doc = merge_many([read_map(f) for f in files]).report(files)
    return files, json.loads(json.dumps(doc, allow_nan=False))


def test_three_runs_of_one_building_merge_into_one_frame(albert: tuple) -> None:
    files, doc = albert
    assert [m["file"] for m in doc["maps"]] == files
    assert [m["component"] for m in doc["maps"]] == [0, 0, 0]
    assert [(ln["a"], ln["b"], ln["accepted"], ln["used"]) for ln in doc["links"]] == [
        (0, 1, True, True),
        (0, 2, True, True),
        (1, 2, True, True),
    ]
    maps = [np.array(m["matrix"]) for m in doc["maps"]]
    np.testing.assert_array_equal(maps[0], np.eye(3))
    # The joint placement agrees with every pairwise link to about a pixel.
    for ln in doc["links"]:
        predicted = np.linalg.inv(maps[ln["a"]]) @ maps[ln["b"]]
        assert corner_gap(predicted, ln["matrix"]) < 2.0
    assert all(np.linalg.eigvalsh(np.array(m["covariance"])).min() >= -1e-12 for m in doc["maps"])


@pytest.fixture(scope="module")
def intel(shared: Path) -> tuple[Grid, Grid]:
    d = shared / "maps" / "intel_split_gt"
    return (
        resample(read_map(d / "intel_partA.yaml"), 0.1),
        resample(read_map(d / "intel_partB.yaml"), 0.1),
    )


def test_a_map_that_overlaps_nothing_is_a_component_of_its_own(shared: Path, intel: tuple) -> None:
    a, b = intel
    other = resample(read_map(shared / "maps" / "uos_avz" / "avz.yaml"), 0.1)
    lines: list[str] = []
    res = merge_many([other, a, b], progress=lines.append)
    assert res.merged
    # the progress says why each rejected pair was rejected, in the merge's words
    assert [ln.split(",")[0] for ln in lines] == [
        "maps 0 and 1: rejected",
        "maps 0 and 2: rejected",
        "maps 1 and 2: accepted",
    ]
    assert all(ln.endswith(")") and "(" in ln.split("score")[1] for ln in lines[:2]), lines
    assert "(" not in lines[2], lines
    doc = res.report(["avz", "A", "B"])
    assert [m["component"] for m in doc["maps"]] == [0, 1, 1]
    assert [(ln["accepted"], ln["used"]) for ln in doc["links"]] == [
        (False, False),
        (False, False),
        (True, True),
    ]
    # B in the frame of A, the first input of its component, as its true offset.
    assert corner_gap(doc["maps"][2]["matrix"], relative_matrix(a, b)) < 3.0
    assert res.largest().members == ("m1", "m2")


def test_matrices_map_pixels_of_the_files_as_read(intel: tuple) -> None:
    """B at half the resolution is resampled to A's; its matrix includes the scale.

    A scale left out would put the corners hundreds of pixels off.  B's walls,
    0.2 m blocks after the round trip, leave a few pixels of error at the
    corners of this 100 m box: over random frames of the intel and freiburg-079
    halves treated so, 0.5-1.6 px (median 1.0), and 2.5 px on the intel link
    here (0.14 degrees, 7 cm across the map), so the bound is 6 px.
    """
    a, b = intel
    coarse = resample(b, 0.2)
    doc = merge_many([a, coarse, a]).report(["A", "B coarse", "A again"])
    assert [m["component"] for m in doc["maps"]] == [0, 0, 0]
    assert corner_gap(doc["maps"][1]["matrix"], relative_matrix(a, coarse)) < 6.0
    assert corner_gap(doc["maps"][2]["matrix"], np.eye(3)) < 1.0
    link_ab = doc["links"][0]
    assert corner_gap(link_ab["matrix"], relative_matrix(a, coarse)) < 6.0


def test_a_false_link_is_reported_unused(intel: tuple) -> None:
    """Four real maps, every pair registered for real; one pair's result is replaced by
    a plausible false link (3 m and 12 deg off): the joint solution drops it."""
    a, b = intel
    c = Grid(np.roll(a.logodds, (4, 7), axis=(0, 1)), a.resolution, a.origin)
    d = Grid(np.roll(b.logodds, (3, -6), axis=(0, 1)), b.resolution, b.origin)
    real = merge_registration()
    calls = []

    def register(x: Grid, y: Grid) -> Registration:
        res = real(x, y)
        calls.append(res)
        if len(calls) == 4:  # the pair (B, C)
            return replace(res, matrix=rigid_matrix(np.radians(12.0), 30.0, 0.0) @ res.matrix)
        return res

    doc = merge_many([a, b, c, d], register=register).report(["A", "B", "C", "D"])
    assert all(r.accepted for r in calls)
    assert [(ln["a"], ln["b"]) for ln in doc["links"] if not ln["used"]] == [(1, 2)]
    assert [m["component"] for m in doc["maps"]] == [0, 0, 0, 0]
    assert corner_gap(doc["maps"][2]["matrix"], rigid_matrix(0.0, -7.0, -4.0)) < 2.0


def test_fewer_than_two_maps_is_an_error(intel: tuple) -> None:
    with pytest.raises(ValueError, match="two or more"):
        merge_many([intel[0]])
