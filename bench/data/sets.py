"""The bench's pair sets, per source, cached on disk.

Sets:

``standard``  overlap >= 30 % (half of the pairs drawn within 30-75 %);
``low``       overlap 15-35 %;
``drifted``   overlap >= 30 %, odometry noise :data:`DRIFT` on both robots' scan poses;
``negative``  disjoint parts of one building, look-alike corridors, mirror images
              (per source) and different buildings (across sources);
``gmapping``  the three gmapping runs of fr079_albertB against each other
              (:mod:`bench.data.gmapping`), standard set of that source.

Every pair is a pure function of its source, the set, the seed and the counts.
"""

from __future__ import annotations

import json
import pickle
import time
from dataclasses import dataclass
from pathlib import Path

from bench.data.drift import Drift
from bench.data.gmapping import gmapping_pairs
from bench.data.negatives import cross_pairs, lookalike_pairs, mirror_pairs
from bench.data.pairs import MAX_DRAWS, MapPair, make_pairs
from bench.data.sources import SIM_VERSION, SOURCES, Source, load_run
from bench.environment import cache_suffix, digest
from pgvd.carmen import LaserScan

#: Odometry drift of the drifted set (:mod:`bench.data.drift`).
DRIFT = Drift()
STANDARD_BAND = (0.3, 1.0)
MIDDLE_BAND = (0.3, 0.75)
LOW_BAND = (0.15, 0.35)
#: Bump when pair generation changes, so caches are not reused; also when the pairs' classes
#: move, since a pickle names their modules (3: bench.pairs became bench.data.pairs).
PAIRS_VERSION = 3


@dataclass(frozen=True)
class Counts:
    """Pairs per source and set (``cross``: in total, across buildings)."""

    standard: int
    low: int
    drifted: int
    disjoint: int
    lookalike: int
    mirror: int
    cross: int
    gmapping: int


QUICK = Counts(standard=2, low=1, drifted=1, disjoint=1, lookalike=1, mirror=1, cross=4, gmapping=3)
FULL = Counts(
    standard=10, low=6, drifted=6, disjoint=5, lookalike=3, mirror=3, cross=30, gmapping=6
)


@dataclass
class Entry:
    """A pair with where it belongs in the report."""

    pair: MapPair
    source: str
    building: str
    set: str
    kind: str


def _log(msg: str) -> None:
    print(msg, flush=True)


def cached(cache: Path | None, key: str, make):
    """``make()``, pickled under ``cache/key`` (loaded from there when present).

    The file name carries the pair generation's versions and the numerical
    libraries' (:func:`bench.environment.cache_suffix`): the simulated-lidar
    pairs move with those, so pairs made under others are made again.
    """
    name = f"{key}-v{PAIRS_VERSION}-s{SIM_VERSION}{cache_suffix()}.pkl"
    path = None if cache is None else cache / name
    if path is not None and path.exists():
        return pickle.loads(path.read_bytes())
    t0 = time.perf_counter()
    value = make()
    _log(f"[pairs] {key}: made in {time.perf_counter() - t0:.0f} s")
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(pickle.dumps(value))
    return value


def source_pairs(
    source: Source, scans: list[LaserScan], counts: Counts, seed: int, cache: Path | None
) -> list[Entry]:
    """Every set's pairs of one source."""
    out: list[Entry] = []
    name = source.name

    def add(set_name: str, kind: str, pairs: list[MapPair]) -> None:
        for p in pairs:
            out.append(Entry(p, name, source.building, set_name, kind))
            _log(
                f"[pairs]   {p.name}: {set_name}/{kind} {p.a.shape} {p.b.shape} ov {p.overlap:.2f}"
            )

    def key(what: str, n: int) -> str:
        return f"{name}-{what}-{n}-{seed}"

    # Segments drawn freely mostly nest (overlap ~1): half the standard pairs are drawn
    # from the middle band so that partial overlaps are well represented.
    half = counts.standard // 2
    # Each set draws its segments from a seed of its own: with one seed, bands that
    # overlap would take the same first pairs, and the bench would hold duplicates.
    for k, (set_name, tag, n, band, noise) in enumerate(
        (
            ("standard", "partial", half, MIDDLE_BAND, None),
            ("standard", "standard", counts.standard - half, STANDARD_BAND, None),
            ("low", "low", counts.low, LOW_BAND, None),
            ("drifted", "drifted", counts.drifted, STANDARD_BAND, DRIFT),
        ),
        start=1,
    ):
        if n:
            own_seed = seed * 100 + k
            what = tag if noise is None else f"{tag}-{digest({**noise.json(), 'truth': 2})}"
            pairs = cached(
                cache,
                f"{name}-{what}-{n}-{own_seed}",
                lambda n=n, band=band, noise=noise, tag=tag, own_seed=own_seed: make_pairs(
                    scans, n, 0, own_seed, f"{name}-{tag}", odom_noise=noise, overlap_band=band
                ),
            )
            add(set_name, "overlap", pairs)
    if counts.disjoint:
        add(
            "negative",
            "disjoint",
            cached(
                cache,
                key("disjoint", counts.disjoint),
                lambda: make_pairs(scans, 0, counts.disjoint, seed, name, max_draws=4 * MAX_DRAWS),
            ),
        )
    if counts.lookalike:
        add(
            "negative",
            "lookalike",
            cached(
                cache,
                key("lookalike", counts.lookalike),
                lambda: lookalike_pairs(scans, counts.lookalike, seed, name),
            ),
        )
    if counts.mirror:
        add(
            "negative",
            "mirror",
            cached(
                cache,
                key("mirror", counts.mirror),
                lambda: mirror_pairs(scans, counts.mirror, seed, name),
            ),
        )
    return out


def build(
    counts: Counts,
    seed: int,
    cache: Path | None,
    sources: tuple[Source, ...] = SOURCES,
    gmapping: bool = True,
) -> list[Entry]:
    """All pairs of the bench: every source's sets, the gmapping runs, then the cross-building
    negatives (every source of ``sources`` when ``gmapping`` is True)."""
    entries: list[Entry] = []
    runs: dict[str, list[LaserScan]] = {}
    for source in sources:
        t0 = time.perf_counter()
        scans = load_run(source, seed, cache)
        _log(f"[pairs] {source.name}: run of {len(scans)} scans ({time.perf_counter() - t0:.1f} s)")
        # One run per building for the cross-building negatives: the first source of it.
        runs.setdefault(source.building, scans)
        entries += source_pairs(source, scans, counts, seed, cache)
    if gmapping and counts.gmapping:
        for p in cached(
            cache,
            f"gmapping-{counts.gmapping}-{seed}",
            lambda: gmapping_pairs(counts.gmapping, seed),
        ):
            entries.append(Entry(p, "fr079-gmapping", "fr079", "standard", "gmapping"))
            _log(
                f"[pairs]   {p.name}: standard/gmapping {p.a.shape} {p.b.shape} ov {p.overlap:.2f}"
            )
    if counts.cross and len(runs) > 1:
        names = "-".join(sorted(runs))
        cross = cached(
            cache,
            f"cross-{names}-{counts.cross}-{seed}",
            lambda: cross_pairs(runs, counts.cross, seed),
        )
        for p in cross:
            entries.append(Entry(p, "cross-building", "cross", "negative", "cross"))
            _log(f"[pairs]   {p.name}: negative/cross {p.a.shape} {p.b.shape}")
    check_distinct(entries)
    return entries


def check_distinct(entries: list[Entry]) -> None:
    """Raise if two pairs of one source were cut from the same segments (a duplicate).

    Raises
    ------
    ValueError
        Naming the two pairs.
    """
    seen: dict[str, str] = {}
    for e in entries:
        info = e.pair.info
        what = json.dumps(
            [
                e.source,
                e.kind,
                info.get("seg_a"),
                info.get("seg_b"),
                info.get("seg"),
                info.get("a"),
                info.get("b"),
                info.get("odom_noise"),
                info.get("seed"),
            ],
            default=str,
        )
        if what in seen:
            raise ValueError(f"pairs {seen[what]} and {e.pair.name} are the same pair")
        seen[what] = e.pair.name
