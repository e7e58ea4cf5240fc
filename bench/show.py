"""Draw one bench pair as a method left it, and at the truth, from ``merge.json`` and the cache.

    python3 -m bench show PAIR [--json bench/results/merge.json] [--method pgvd] [--out PAIR.png]

A's walls red, B's walls (through the matrix) blue, both black, A's free space grey.
The pair is looked up by name in the generated pairs under ``bench/cache/`` (run the
bench once first).
"""

from __future__ import annotations

import argparse
import json
import pickle
import sys
from pathlib import Path

import numpy as np

from bench.data.pairs import MapPair
from bench.environment import cache_suffix, libraries
from bench.merge import CACHE, RESULTS
from pgvd.transform import warp


def find_pair(name: str, cache: Path = CACHE) -> MapPair:
    """The pair called ``name`` among the cached pairs made under this environment's libraries.

    Raises
    ------
    LookupError
        If no cached file of this environment (:func:`bench.environment.cache_suffix`)
        holds it.
    """
    suffix = cache_suffix()
    for path in sorted(cache.glob(f"*{suffix}.pkl")):
        for pair in pickle.loads(path.read_bytes()):
            if pair.name == name:
                return pair
    raise LookupError(
        f"no pair {name!r} under {cache} made with these libraries ({suffix[1:]}); "
        "run python3 -m bench merge first"
    )


def overlay(pair: MapPair, matrix: np.ndarray) -> np.ndarray:
    """RGB image in A's frame: A free grey, A walls red, B walls blue, both black."""
    wb = warp((pair.b.logodds > 0).astype(np.float32), matrix, pair.a.shape, order=0) > 0.5
    wa = pair.a.logodds > 0
    img = np.ones((*pair.a.shape, 3))
    img[pair.a.logodds < 0] = 0.88
    img[wa] = (1.0, 0.0, 0.0)
    img[wb] = (0.0, 0.0, 1.0)
    img[wa & wb] = 0.0
    return img


def main(argv: list[str] | None = None) -> int:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("pair")
    parser.add_argument("--json", type=Path, default=RESULTS / "merge.json")
    parser.add_argument("--method", default="pgvd")
    parser.add_argument("--cache", type=Path, default=CACHE)
    parser.add_argument("--out", type=Path)
    args = parser.parse_args(argv)
    doc = json.loads(args.json.read_text())
    rec = next(
        (r for r in doc["records"] if r["pair"] == args.pair and r["method"] == args.method), None
    )
    if rec is None:
        print(f"{args.json}: no record of {args.pair} by {args.method}")
        return 1
    # the run's matrix drawn over pairs made again under other libraries may not fit them
    recorded, here = doc.get("environment", {}).get("libraries", {}), libraries()
    moved = sorted(k for k in recorded.keys() & here.keys() if recorded[k] != here[k])
    if moved:
        print(
            f"warning: {args.json} was measured with other versions of {', '.join(moved)} "
            "than this environment's: its pairs may differ from these by a cell",
            file=sys.stderr,
        )
    pair = find_pair(args.pair, args.cache)
    panels = [(f"{args.method}: accepted={rec['accepted']}", np.array(rec["matrix"]))]
    if pair.truth is not None:
        panels.append(("truth", pair.truth))
    fig, axes = plt.subplots(1, len(panels), figsize=(7 * len(panels), 7), squeeze=False)
    for ax, (title, m) in zip(axes[0], panels, strict=True):
        ax.imshow(overlay(pair, m))
        ax.set_title(title)
        ax.set_axis_off()
    reason = rec.get("result", {}).get("reason", "")
    fig.suptitle(
        f"{args.pair} ({rec['set']}/{rec['kind']}, overlap {rec['overlap']:.2f}) {reason}",
        fontsize=10,
    )
    fig.tight_layout()
    out = args.out or Path(f"{args.pair}.png")
    fig.savefig(out, dpi=80)
    plt.close(fig)
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
