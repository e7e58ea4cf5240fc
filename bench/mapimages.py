"""Merging saved map images directly, with walls drawn thin and thick.

The merge bench drives a simulated laser through the development map images,
so its maps have the thin walls a laser draws.  A user with two saved maps
(map_server PGM + YAML, a cleaned map, an inflated one) merges the images as
they are, and many draw walls several cells thick.  For each development map
image (the ``*-sim`` sources of :mod:`bench.data.sources`), two parts of 62 % of
its width (24 % of it shared) are cut, B is put in ``--frames`` random frames,
the walls of both are grown by each of ``--grow`` cells on each side (0, 1,
2: walls as drawn, 2 and 4 cells thicker), and each pair is merged and judged as the
merge bench judges (:func:`bench.merge.evaluate`: accepted, heading within 2
degrees, B's walls within 3 cells on average).

    python3 -m bench mapimages [--frames 3] [--grow 0 1 2] [--unknown free] [--speckle D]
        [--clutter C] [--ablation NAME] [--held-out] [--out bench/results]

``--unknown free`` paints every unknown cell of both parts free, the padding of
B's frame included (:func:`bench.data.pairs.painted_free`): images whose unexplored
area was painted white, as some editors and exports save them.  ``--speckle D``
turns a share ``D`` of each part's free cells, drawn independently, into lone
walls (:func:`bench.data.pairs.speckled`): raw maps saved without cleaning.  ``--clutter C``
draws furniture into each image before its parts are cut, ``C`` filled discs of
0.1-0.35 m radius per square metre of free space (:func:`bench.data.pairs.cluttered`; 0.3 is
an office with a desk, chair or bin every 3 square metres).  ``--ablation
pgvd-as-drawn`` (any name of :data:`bench.merge.ABLATIONS`) merges with that stage
off, ``--ablation pgvd-despeckle`` (or another of :data:`bench.merge.OPTIONS`) with that
option on; the report's name gains its name.  ``--held-out`` cuts the same parts
from the map images the shared data keeps to evaluate the merge on buildings it was
never tuned on (:func:`bench.data.sources.held_out_maps`) and writes to
``bench/results/held-out/``.

Writes ``mapimages.md`` (``mapimages-painted.md`` with ``--unknown free``,
``mapimages-speckle-D.md`` with ``--speckle D``, ``mapimages-clutter-C.md`` with
``--clutter C``) to ``bench/results/``: per
growth, right / accepted pairs and the median and largest mean cell error of the
right ones, and a row per map image.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from bench.data.pairs import MapPair, cluttered, painted_pair, speckled_pair
from bench.data.sources import SHARED, SOURCES, held_out_maps
from bench.merge import VARIANTS, add_output_arguments, evaluate, output_dir
from bench.tables import mark
from pgvd.grid import Grid, rigid_matrix
from pgvd.io import read_map
from pgvd.merge import merge
from pgvd.morphology import grow
from pgvd.params import MergeParams
from pgvd.transform import resample, warp

#: Cell size the maps are merged at (the development logs' and most images').
RESOLUTION = 0.05
#: Each part's share of the map's width; the two share ``2 PART - 1`` of it.
PART = 0.62


def random_framed(g: Grid, rng: np.random.Generator) -> tuple[Grid, np.ndarray]:
    """``g`` turned by a random angle and shifted, on a canvas padded so nothing is cut.

    Returns
    -------
    tuple of (Grid, numpy.ndarray)
        The new grid and the 3x3 matrix from ``g``'s pixels to the new pixels.
    """
    h, w = g.shape
    side = int(np.ceil(np.hypot(h, w))) + 60
    m = rigid_matrix(rng.uniform(0.0, 2 * np.pi), 0.0, 0.0)
    shift = rng.uniform(-25.0, 25.0, size=2)
    m[:2, 2] = (side - 1) / 2.0 + shift - m[:2, :2] @ np.array([(w - 1) / 2.0, (h - 1) / 2.0])
    p = warp(g.probability(), m, (side, side), order=0, cval=0.5)
    return Grid.from_probability(p, g.resolution), m


def thickened(p: np.ndarray, cells: int, occupied: float = 0.65) -> np.ndarray:
    """Probabilities ``p`` with every wall grown by ``cells`` on each side (new walls 0.95)."""
    return np.where(grow(p > occupied, cells), np.maximum(p, 0.95), p) if cells else p


def part_pairs(name: str, p: np.ndarray, frames: int, rng: np.random.Generator) -> list[MapPair]:
    """The left and right parts of ``p`` (probabilities), B in ``frames`` random frames."""
    w = p.shape[1]
    cut_a, cut_b = round(PART * w), round((1 - PART) * w)
    a = Grid.from_probability(p[:, :cut_a], RESOLUTION)
    b = Grid.from_probability(p[:, cut_b:], RESOLUTION)
    truth = rigid_matrix(0.0, float(cut_b), 0.0)
    out = []
    for i in range(frames):
        bn, to_new = random_framed(b, rng)
        out.append(MapPair(a, bn, truth @ np.linalg.inv(to_new), 2 * PART - 1, f"{name}-f{i}"))
    return out


def development_images() -> list[tuple[str, Path]]:
    """(row label, YAML path) of every development map image: the ``*-sim`` sources."""
    return [(s.name, SHARED / s.path) for s in SOURCES if s.simulated]


def held_out_images() -> list[tuple[str, Path]]:
    """(row label, YAML path) of every map image the shared data keeps for evaluation
    (:func:`bench.data.sources.held_out_maps`), labelled ``directory/name``."""
    return [(f"{p.parent.name}/{p.stem}", p) for p in held_out_maps()]


def run(
    images: list[tuple[str, Path]],
    frames: int,
    growths: list[int],
    seed: int,
    painted: bool = False,
    ablation: str = "",
    speckle: float = 0.0,
    clutter: float = 0.0,
) -> list[dict]:
    """Every map image's pairs at every growth, merged; one record each (``images``: row
    label and YAML path of each image; ``painted``: with
    :func:`bench.data.pairs.painted_pair`'s maps; ``speckle``: with that share of free cells
    lone walls, :func:`bench.data.pairs.speckled_pair`; ``clutter``: with that many discs of
    furniture per square metre of free space, :func:`bench.data.pairs.cluttered`;
    ``ablation``: a key of
    :data:`bench.merge.ABLATIONS` or :data:`bench.merge.OPTIONS`, the merge with that
    stage off or that option on)."""
    params = MergeParams(diagnostics=False, **VARIANTS.get(ablation, {}))
    records = []
    for label, path in images:
        grid = read_map(path)
        if not np.isclose(grid.resolution, RESOLUTION):
            grid = resample(grid, RESOLUTION)
        for cells in growths:
            # the same frames at every growth: only the walls differ
            rng = np.random.default_rng(seed)
            p = thickened(grid.probability(), cells)
            p = cluttered(p, clutter, RESOLUTION, seed) if clutter > 0 else p
            for pair in part_pairs(label, p, frames, rng):
                pair = speckled_pair(pair, speckle, seed) if speckle > 0 else pair
                pair = painted_pair(pair) if painted else pair
                result = merge(pair.a, pair.b, params)
                rec = evaluate(pair, result.accepted, result.matrix)
                rec.update(source=label, grow=cells, pair=pair.name)
                records.append(rec)
                outcome = mark(rec["success"], rec["accepted"])
                print(
                    f"[mapimages] grow {cells} {pair.name}: {outcome} "
                    f"{rec['cell_err']:.2f} cells, {rec['heading_deg']:.3f} deg",
                    flush=True,
                )
    return records


def _cell(records: list[dict]) -> str:
    right = [r for r in records if r["success"]]
    errs = [r["cell_err"] for r in right]
    text = f"{len(right)}/{len(records)} right, {sum(r['accepted'] for r in records)} accepted"
    return f"{text}; {np.median(errs):.2f} / {max(errs):.2f}" if errs else text


def report(records: list[dict], command: str) -> str:
    """Markdown: a column per growth, a row per map image and one for all."""
    growths = sorted({r["grow"] for r in records})
    head = " | ".join(f"walls grown by {g}" for g in growths)
    lines = [
        "# Saved map images merged directly, walls thin and thick",
        "",
        f"`{command}`",
        "",
        "Each cell: right / pairs, accepted; median / largest mean cell error of the right ones.",
        "",
        f"| map image | {head} |",
        "|---" * (len(growths) + 1) + "|",
    ]
    for source in [*sorted({r["source"] for r in records}), None]:
        mine = [r for r in records if source is None or r["source"] == source]
        cells = " | ".join(_cell([r for r in mine if r["grow"] == g]) for g in growths)
        lines.append(f"| {source or '**all**'} | {cells} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=3, help="random frames of B per image")
    parser.add_argument("--grow", type=int, nargs="+", default=[0, 1, 2], help="cells")
    parser.add_argument("--seed", type=int, default=21)
    add_output_arguments(parser, "map images")
    parser.add_argument(
        "--unknown",
        choices=("drawn", "free"),
        default="drawn",
        help="free: unknown cells painted free (writes mapimages-painted.md)",
    )
    parser.add_argument(
        "--speckle",
        type=float,
        default=0.0,
        metavar="D",
        help="share of each part's free cells made lone walls (writes mapimages-speckle-D.md)",
    )
    parser.add_argument(
        "--clutter",
        type=float,
        default=0.0,
        metavar="C",
        help="filled discs of furniture per square metre of free space "
        "(writes mapimages-clutter-C.md)",
    )
    parser.add_argument(
        "--ablation",
        choices=sorted(VARIANTS),
        default="",
        help="merge with this stage off, or this option on",
    )
    args = parser.parse_args(argv)
    if args.frames < 1 or min(args.grow) < 0:
        parser.error("--frames must be >= 1 and --grow >= 0")
    if not 0 <= args.speckle < 1:
        parser.error("--speckle must be in [0, 1)")
    if not args.clutter >= 0:
        parser.error("--clutter must be >= 0")
    painted = args.unknown == "free"
    images = held_out_images() if args.held_out else development_images()
    records = run(
        images,
        args.frames,
        args.grow,
        args.seed,
        painted,
        args.ablation,
        args.speckle,
        args.clutter,
    )
    out_dir = output_dir(args)
    out_dir.mkdir(parents=True, exist_ok=True)
    command = "python3 -m bench mapimages " + " ".join(argv if argv is not None else sys.argv[1:])
    name = (
        "mapimages"
        + ("-painted" if painted else "")
        + (f"-speckle-{args.speckle:g}" if args.speckle else "")
        + (f"-clutter-{args.clutter:g}" if args.clutter else "")
        + (f"-{args.ablation}" if args.ablation else "")
    )
    out = out_dir / f"{name}.md"
    out.write_text(report(records, command.strip()))
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
