"""Why a heading is missed: the two maps' angle spectra and their correlation, eq. (10).

    python3 -m bench spectra PAIR [PAIR ...] [--cache bench/cache] [--out heading-spectra.png]

For each bench pair (looked up in the generated pairs under ``bench/cache/``, as
:mod:`bench.show` does), the left panel draws A's angle spectrum and B's turned by the true
heading: where B's wall families lie on A's, the true heading is a peak of the correlation.
The right panel draws the correlation :func:`pgvd.rotation.spectrum_correlation` over
180 degrees, the true heading (mod 180) and the candidates
:func:`pgvd.rotation.estimate_headings` returns.  A bent building whose two parts hold
different wall families (ritsumeikan_cc4f) or a drifted map whose walls turn along it puts
the truth on a slope of the correlation, not at a peak.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from bench.data.pairs import MapPair
from bench.merge import CACHE, RESULTS
from bench.show import find_pair
from pgvd.grid import heading
from pgvd.inputs import registration_probability
from pgvd.params import MergeParams
from pgvd.rotation import angle_spectrum, estimate_headings, spectrum_correlation


def spectra(pair: MapPair, params: MergeParams) -> dict[str, np.ndarray | float]:
    """A's and B's angle spectra as registration reads the maps, their correlation, the
    candidate headings and the true one (degrees mod 180, NaN without a truth)."""
    pa, pb = (registration_probability(g, params) for g in (pair.a, pair.b))
    s_a, s_b = angle_spectrum(pa), angle_spectrum(pb)
    cands = estimate_headings(pa, pb, params.max_candidates)
    truth = float("nan") if pair.truth is None else float(np.degrees(heading(pair.truth)) % 180.0)
    return {
        "a": s_a,
        "b": s_b,
        "correlation": spectrum_correlation(s_a, s_b),
        "candidates": np.array([np.degrees(c.psi) % 180.0 for c in cands]),
        "truth": truth,
    }


def draw(pairs: list[MapPair], out: Path, params: MergeParams | None = None) -> None:
    """One row per pair: the spectra (B turned by the truth) and the correlation."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    params = params or MergeParams()
    fig, axes = plt.subplots(len(pairs), 2, figsize=(13, 3.2 * len(pairs)), squeeze=False)
    for (left, right), pair in zip(axes, pairs, strict=True):
        got = spectra(pair, params)
        theta = np.arange(got["a"].size) * 180.0 / got["a"].size
        left.plot(theta, got["a"] / got["a"].max(), label="A")
        if np.isfinite(got["truth"]):
            left.plot(
                (theta - got["truth"]) % 180.0,
                got["b"] / got["b"].max(),
                ".",
                ms=2,
                label="B turned by the true heading",
            )
        left.set_title(f"{pair.name}: angle spectra (wall normals, deg)")
        left.legend(loc="upper right", fontsize=8)
        right.plot(theta, got["correlation"], "k-", lw=1)
        for c in got["candidates"]:
            right.axvline(c, color="tab:blue", ls=":", lw=1)
        if np.isfinite(got["truth"]):
            right.axvline(got["truth"], color="tab:red", lw=1.5)
        right.set_title("correlation (10): candidates dotted, truth red (deg mod 180)")
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=90)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("pairs", nargs="+", metavar="PAIR")
    parser.add_argument("--cache", type=Path, default=CACHE)
    parser.add_argument("--out", type=Path, default=RESULTS / "heading-spectra.png")
    args = parser.parse_args(argv)
    try:
        pairs = [find_pair(name, args.cache) for name in args.pairs]
    except LookupError as e:
        parser.error(str(e))
    draw(pairs, args.out)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
