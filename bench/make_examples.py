"""Regenerate ``examples/``: two robots' partial maps of the Intel lab and their true matrix.

Run from the project root: ``python3 -m bench make_examples``.  The maps are a
pure function of the bundled log (``agent/data/intel-corrected.log.gz``) and
the seed below, so the files in git can be checked against a fresh run.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from bench.data.pairs import make_pair, write_pair
from pgvd.carmen import read_carmen

ROOT = Path(__file__).resolve().parents[1]
LOG = ROOT / "agent" / "data" / "intel-corrected.log.gz"
#: The halves of the intel_split_gt renders: robot A drives the first 55 % of the
#: log, robot B the last 55 %; each map gets its own random frame.
SEGMENTS = ((0.0, 0.55), (0.45, 1.0))
SEED = 2026


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=ROOT / "examples", help="output directory")
    args = parser.parse_args(argv)
    scans = read_carmen(LOG)
    pair = make_pair(scans, *SEGMENTS, seed=SEED, name="intel-example")
    out = args.out
    out.mkdir(parents=True, exist_ok=True)
    write_pair(pair, out / "intel_a.yaml", out / "intel_b.yaml", out / "truth.json")
    print(f"wrote {out}/intel_a.yaml {pair.a.shape}, intel_b.yaml {pair.b.shape}, truth.json")
    print(f"overlap {pair.overlap:.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
