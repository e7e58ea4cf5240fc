"""bench.studies.spectra: the angle spectra and their correlation drawn for a pair, eq. (10)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from bench.data.pairs import MapPair
from bench.studies.spectra import draw, spectra
from pgvd.io import read_map
from pgvd.params import MergeParams

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


def _example() -> MapPair:
    truth = np.asarray(json.loads((EXAMPLES / "truth.json").read_text())["matrix"])
    a, b = read_map(EXAMPLES / "intel_a.yaml"), read_map(EXAMPLES / "intel_b.yaml")
    return MapPair(a, b, truth, 0.78, "intel-example", {})


def test_the_bundled_pairs_true_heading_is_a_candidate_and_a_peak(tmp_path: Path) -> None:
    pair = _example()
    got = spectra(pair, MergeParams())
    # the pair's truth is -69 deg: 111 mod 180
    assert abs(got["truth"] - 111.04) < 0.01
    gaps = np.abs((got["candidates"] - got["truth"] + 90.0) % 180.0 - 90.0)
    assert gaps.min() < 1.0
    corr = got["correlation"]
    at = round(float(got["truth"]) * corr.size / 180.0) % corr.size
    assert corr[at] > 0.9 * corr.max()  # the truth sits on the highest peak
    out = tmp_path / "spectra.png"
    draw([pair], out)
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
