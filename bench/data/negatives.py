"""Pairs that must not merge: different buildings, look-alike corridors, a building's mirror image.

(Disjoint parts of one building come from :func:`bench.data.pairs.make_pairs`.)

* ``cross``: a segment of one building against a segment of another.
* ``lookalike``: two straight corridor runs of one building, 8 to 20 m of
  travel each with a path straightness (end-to-end distance over distance
  travelled) of at least 0.85, whose maps share no cell.  Corridors of one
  building are built alike, so these are the hardest negatives a merge meets.
* ``mirror``: a segment against its own mirror image -- the scans reflected
  about the world x axis (poses ``(x, -y, -theta)``, beams in reverse order),
  a building that does not exist.  Segments are long (20 to 50 % of a run).
  A segment that happens to be nearly mirror symmetric is congruent to its
  mirror image, and no test on the maps alone can reject that pair (uos_avz's
  X-shaped hall of four corridors is one); the report counts mirror false
  accepts apart, so they can be looked at (``python3 -m bench show``).

Every map is in its own random frame; the pairs carry ``truth = None`` (no
transform is right), except look-alikes, which keep the true relation of the
two segments (the transform nothing should find).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from bench.data.pairs import MAX_DRAWS, Footprints, MapPair, make_pair, render
from pgvd.carmen import LaserScan
from pgvd.integrate import DEFAULT_MODEL

#: Travel (m) of a look-alike corridor run, and its minimum straightness.
CORRIDOR_TRAVEL = (8.0, 20.0)
CORRIDOR_STRAIGHTNESS = 0.85
#: Segment lengths (fractions of a run) of the mirror and cross-building negatives.
NEGATIVE_LENGTHS = (0.2, 0.5)


def mirror_scans(scans: list[LaserScan]) -> list[LaserScan]:
    """The scans a robot would record in the building's mirror image (reflected about y = 0)."""
    return [
        dataclasses.replace(
            s,
            ranges=s.ranges[::-1].copy(),
            pose=np.array([s.pose[0], -s.pose[1], -s.pose[2]]),
            odom=np.array([s.odom[0], -s.odom[1], -s.odom[2]]),
        )
        for s in scans
    ]


def _draw(rng: np.random.Generator, n: int, lengths: tuple[float, float]) -> slice:
    length = max(2, int(rng.uniform(*lengths) * n))
    start = int(rng.integers(0, n - length + 1))
    return slice(start, start + length)


def unrelated_pair(
    part_a: list[LaserScan],
    part_b: list[LaserScan],
    seed: int,
    name: str,
    info: dict,
    resolution: float = 0.05,
) -> MapPair:
    """Two maps that show no common place, each in a random frame; truth None, overlap 0."""
    rng = np.random.default_rng(seed)
    a, _ = render(part_a, rng, resolution)
    b, _ = render(part_b, rng, resolution)
    return MapPair(a, b, None, 0.0, name, {**info, "seed": seed, "resolution": resolution})


def mirror_pairs(
    scans: list[LaserScan], n: int, seed: int, name: str, resolution: float = 0.05
) -> list[MapPair]:
    """``n`` segments of a run, each against its own mirror image."""
    rng = np.random.default_rng(seed)
    out = []
    for i in range(n):
        seg = _draw(rng, len(scans), NEGATIVE_LENGTHS)
        part = scans[seg]
        info = {"kind": "mirror", "seg": ["scans", seg.start, seg.stop]}
        out.append(
            unrelated_pair(
                part, mirror_scans(part), seed * 100 + i, f"{name}-mi{i:02d}", info, resolution
            )
        )
    return out


def cross_pairs(
    runs: dict[str, list[LaserScan]], n: int, seed: int, resolution: float = 0.05
) -> list[MapPair]:
    """``n`` pairs of segments of two different buildings (keys of ``runs`` name the buildings)."""
    rng = np.random.default_rng(seed)
    names = sorted(runs)
    out = []
    for i in range(n):
        ia, ib = rng.choice(len(names), 2, replace=False)
        a, b = names[ia], names[ib]
        seg_a = _draw(rng, len(runs[a]), NEGATIVE_LENGTHS)
        seg_b = _draw(rng, len(runs[b]), NEGATIVE_LENGTHS)
        info = {
            "kind": "cross",
            "building_a": a,
            "building_b": b,
            "seg_a": ["scans", seg_a.start, seg_a.stop],
            "seg_b": ["scans", seg_b.start, seg_b.stop],
        }
        out.append(
            unrelated_pair(
                runs[a][seg_a],
                runs[b][seg_b],
                seed * 100 + i,
                f"cross-{a}-{b}-{i:02d}",
                info,
                resolution,
            )
        )
    return out


def corridor_run(scans: list[LaserScan], rng: np.random.Generator) -> slice | None:
    """A random straight stretch of 8-20 m travel (see the module docstring), or None."""
    xy = np.array([s.pose[:2] for s in scans])
    travel = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(xy, axis=0).T))])
    start = int(rng.integers(0, len(scans)))
    stop = int(np.searchsorted(travel, travel[start] + rng.uniform(*CORRIDOR_TRAVEL)))
    if stop >= len(scans):
        return None
    straight = np.hypot(*(xy[stop] - xy[start])) / max(travel[stop] - travel[start], 1e-9)
    return slice(start, stop + 1) if straight >= CORRIDOR_STRAIGHTNESS else None


def lookalike_pairs(
    scans: list[LaserScan], n: int, seed: int, name: str, resolution: float = 0.05
) -> list[MapPair]:
    """Up to ``n`` pairs of straight corridor runs of one building whose maps share no cell.

    Fewer come back when ``MAX_DRAWS`` draws do not find them: a building made of
    one long corridor (freiburg-079) has no two corridors out of each other's sight.
    """
    rng = np.random.default_rng(seed)
    footprints = Footprints(scans, DEFAULT_MODEL) if n else None
    out: list[MapPair] = []
    draws = 0
    while len(out) < n and draws < MAX_DRAWS:
        draws += 1
        seg_a, seg_b = corridor_run(scans, rng), corridor_run(scans, rng)
        if seg_a is None or seg_b is None or not footprints.disjoint(seg_a, seg_b):
            continue
        pair = make_pair(
            scans, seg_a, seg_b, seed * 1000 + draws, resolution, name=f"{name}-la{len(out):02d}"
        )
        if pair.overlap == 0.0:
            pair.info["kind"] = "lookalike"
            out.append(pair)
    return out
