"""The bench's pair sets, per source, cached on disk.

Sets (issue 10):

``standard``  overlap >= 30 %;
``low``       overlap 15-35 %;
``drifted``   overlap >= 30 %, odometry noise :data:`DRIFT` on both robots' scan poses;
``negative``  disjoint parts of one building, look-alike corridors, mirror images
              (per source) and different buildings (across sources);
``gmapping``  the three gmapping runs of fr079_albertB against each other
              (:mod:`bench.gmapping`), standard set of that source.

Every pair is a pure function of its source, the set, the seed and the counts.
"""

from __future__ import annotations

import pickle
import time
from dataclasses import dataclass
from pathlib import Path

from bench.negatives import cross_pairs, lookalike_pairs, mirror_pairs
from bench.pairs import MapPair, make_pairs
from bench.sources import SIM_VERSION, SOURCES, Source, load_run
from pgvd.io import LaserScan

#: Odometry noise of the drifted set: (translation sigma per metre moved, heading sigma
#: per radian turned plus per metre moved), see :func:`pgvd.integrate.perturb_odometry`.
DRIFT = (0.05, 0.0175)
STANDARD_BAND = (0.3, 1.0)
LOW_BAND = (0.15, 0.35)
#: Bump when pair generation changes, so caches are not reused.
PAIRS_VERSION = 1


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


QUICK = Counts(standard=2, low=1, drifted=1, disjoint=1, lookalike=1, mirror=1, cross=4)
FULL = Counts(standard=10, low=6, drifted=6, disjoint=5, lookalike=3, mirror=3, cross=30)


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


def _cached(cache: Path | None, key: str, make):
    """``make()``, pickled under ``cache/key`` (loaded from there when present)."""
    path = None if cache is None else cache / f"{key}-v{PAIRS_VERSION}-s{SIM_VERSION}.pkl"
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

    for set_name, n, band, noise in (
        ("standard", counts.standard, STANDARD_BAND, None),
        ("low", counts.low, LOW_BAND, None),
        ("drifted", counts.drifted, STANDARD_BAND, DRIFT),
    ):
        if n:
            pairs = _cached(
                cache,
                key(set_name, n),
                lambda n=n, band=band, noise=noise, tag=set_name: make_pairs(
                    scans, n, 0, seed, f"{name}-{tag}", odom_noise=noise, overlap_band=band
                ),
            )
            add(set_name, "overlap", pairs)
    if counts.disjoint:
        add(
            "negative",
            "disjoint",
            _cached(
                cache,
                key("disjoint", counts.disjoint),
                lambda: make_pairs(scans, 0, counts.disjoint, seed, name),
            ),
        )
    if counts.lookalike:
        add(
            "negative",
            "lookalike",
            _cached(
                cache,
                key("lookalike", counts.lookalike),
                lambda: lookalike_pairs(scans, counts.lookalike, seed, name),
            ),
        )
    if counts.mirror:
        add(
            "negative",
            "mirror",
            _cached(
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
) -> list[Entry]:
    """All pairs of the bench: every source's sets, then the cross-building negatives."""
    entries: list[Entry] = []
    runs: dict[str, list[LaserScan]] = {}
    for source in sources:
        t0 = time.perf_counter()
        scans = load_run(source, seed, cache)
        _log(f"[pairs] {source.name}: run of {len(scans)} scans ({time.perf_counter() - t0:.1f} s)")
        # One run per building for the cross-building negatives: the first source of it.
        runs.setdefault(source.building, scans)
        entries += source_pairs(source, scans, counts, seed, cache)
    if counts.cross and len(runs) > 1:
        names = "-".join(sorted(runs))
        cross = _cached(
            cache,
            f"cross-{names}-{counts.cross}-{seed}",
            lambda: cross_pairs(runs, counts.cross, seed),
        )
        for p in cross:
            entries.append(Entry(p, "cross-building", "cross", "negative", "cross"))
            _log(f"[pairs]   {p.name}: negative/cross {p.a.shape} {p.b.shape}")
    return entries
