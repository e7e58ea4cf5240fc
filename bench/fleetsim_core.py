"""The agent's core run in simulated time: its clock, its CPU meter and its global-map rebuilds.

:class:`agent.worker.FusionWorker` reads the ``time`` module for its registration and rebuild
durations (they set its timeouts and preview gaps); :func:`simulated_core` gives it a
:class:`SimClock` instead, and wraps :func:`agent.worker.build_components` in
:class:`Rebuilds`, for the length of a simulation, then puts both back.  The core itself is
not changed: this module only wraps it from the bench's side.

CPU is charged as follows (:class:`Meter`): a worker's step costs the real CPU seconds
(``time.thread_time``) the core spent in it, minus what the simulation's stand-ins spent, plus
what those stand-ins charge (a drawn registration's measured cost,
:mod:`bench.fleetsim_merges`; the search gate's, :mod:`bench.fleetsim_gate`; a rebuild's cost),
tallied by kind so that a run tells which term of an agent's cost grows with the fleet.  A
rebuild runs the real :func:`agent.globalmap.build_components` on the robots' real maps, first
with the same pose graph but no fusion (each component's map is its anchor's), which counts
the maps it fuses (the members of its components of two robots or more).  When that count is
at least :data:`SAMPLE_GROWTH` times the largest of the samples so far (the first rebuild
that fuses, then 4, 8, ... maps: the fleet's components as they grow), it runs again with the
real fusion, its measured CPU charged; its fusion CPU (less the pose graph's) per map fused is
kept as a sample.  Any other rebuild is charged the pose graph's real CPU plus, per map it
fuses, the fusion CPU per map of the sample nearest in maps fused.  (Counting every map held
instead, lone ones included, would price a whole fleet's fusion at the first sample's, two
maps fused of sixteen held.)  Any two agents holding the same maps and links get the same
global maps (fleet invariant 2), so a rebuild of inputs seen before returns the same
components at the same charged cost without running again.  :func:`simulated_wire` puts
:mod:`agent.wire`'s fetch-tile budget on simulated time likewise.
"""

from __future__ import annotations

import contextlib
import hashlib
import math
import time
from collections import OrderedDict
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from functools import lru_cache

import agent.sources
import agent.wire
import agent.worker
from agent.globalmap import build_components
from agent.sources import SourceSpec

#: Distinct rebuild inputs remembered (their components hold fused maps).
MEMO_SIZE = 64
#: A rebuild is run with the real fusion when it fuses this many times the maps of the
#: largest sample so far (module docstring).
SAMPLE_GROWTH = 2


class SimClock:
    """Stands in for the ``time`` module in :mod:`agent.worker`: every clock reads ``now``."""

    def __init__(self) -> None:
        self.now = 0.0

    def monotonic(self) -> float:
        return self.now

    thread_time = time = perf_counter = monotonic

    def sleep(self, seconds: float) -> None:
        self.now += seconds


@dataclass
class Meter:
    """Simulated CPU: what stand-ins charged, and the real CPU they spent meanwhile."""

    clock: SimClock
    charged: float = 0.0
    excluded: float = 0.0
    #: Wall seconds per CPU second of the job at hand (> 1 when agents share cores).
    stretch: float = 1.0
    #: ``charged`` by what the stand-in stood for (search, check, gate, rebuild).
    by_kind: dict[str, float] = field(default_factory=dict)

    def charge(self, seconds: float, kind: str) -> None:
        """A stand-in's cost: ``seconds`` of CPU of ``kind``, the worker busy ``stretch``
        times longer."""
        self.charged += seconds
        self.by_kind[kind] = self.by_kind.get(kind, 0.0) + seconds
        self.clock.now += seconds * self.stretch

    @contextlib.contextmanager
    def excluding(self) -> Iterator[None]:
        """Real CPU spent in the block is the simulation's, not the agent's."""
        t0 = time.thread_time()
        try:
            yield
        finally:
            self.excluded += time.thread_time() - t0


def _identity(ln) -> tuple[object, ...]:
    """What tells a link record from another in a simulation: its key and who decided it
    on which versions, with what.  (:func:`agent.links.preference` tells them apart by the
    bits of their matrices too, ten times the cost; a simulated decider reaches one matrix
    for one pair of versions.)"""
    return (*ln.key, ln.revision, ln.decided_by, ln.version_a, ln.version_b, ln.accepted, ln.state)


@dataclass
class Rebuilds:
    """:func:`agent.globalmap.build_components` with sampling and memo (module docstring).

    Previews (``blur=False``: the maps placed without eq. (8)'s blur) and settled maps are
    sampled and priced apart: a preview's fusion costs a fraction of a settled one's.
    """

    meter: Meter
    #: (blurred, maps fused, fusion CPU s) of each rebuild run with the real fusion.
    samples: list[tuple[bool, int, float]] = field(default_factory=list)
    #: charged CPU s of every rebuild asked for, by every agent.
    charged: list[float] = field(default_factory=list)

    def __post_init__(self) -> None:
        self._memo: OrderedDict[bytes, tuple[list, float]] = OrderedDict()

    def per_map(self, blur: bool = True) -> float:
        """Fusion CPU seconds per map fused, over every sample of settled maps (``blur``)
        or of previews (0 before any)."""
        kind = [(n, s) for b, n, s in self.samples if b == blur]
        maps = sum(n for n, _ in kind)
        return sum(s for _, s in kind) / maps if maps else 0.0

    def fusion_cost(self, fused: int, blur: bool = True) -> float:
        """The fusion CPU of a rebuild that fuses ``fused`` maps: per map fused as in the
        sample of its kind nearest in maps fused (in ratio, the larger on a tie)."""
        kind = [(n, s) for b, n, s in self.samples if b == blur]
        if not kind or not fused:
            return 0.0
        n, cpu = min(kind, key=lambda s: (abs(math.log(s[0] / fused)), -s[0]))
        return cpu / n * fused

    def __call__(self, maps, links, params=None, sound=None, layers=None, firsts=None, blur=True):
        with self.meter.excluding():
            signature = hashlib.sha256(
                repr(
                    (
                        sorted((r, v) for r, (v, _) in maps.items()),
                        sorted(_identity(ln) for ln in links),
                        sorted((firsts or {}).items()),
                        blur,
                    )
                ).encode()
            ).digest()
            held = self._memo.get(signature)
            if held is None:
                held = self._build(maps, links, params, sound, layers, firsts, blur)
        self._memo[signature] = held
        self._memo.move_to_end(signature)
        while len(self._memo) > MEMO_SIZE:
            self._memo.popitem(last=False)
        self.charged.append(held[1])
        self.meter.charge(held[1], "rebuild")
        return held[0]

    def _build(self, maps, links, params, sound, layers, firsts, blur) -> tuple[list, float]:
        t0 = time.thread_time()
        comps = build_components(maps, links, params, sound, firsts=firsts, fuse=False)
        graph = time.thread_time() - t0
        fused = sum(len(c.members) for c in comps if len(c.members) > 1)
        largest = max((n for b, n, _ in self.samples if b == blur), default=0)
        if not fused or fused < SAMPLE_GROWTH * largest:
            return comps, graph + self.fusion_cost(fused, blur)
        # A sampled rebuild runs with the asking agent's layer cache, so its CPU is a warm
        # rebuild's where the agent's own last build left layers to reuse.
        t0 = time.thread_time()
        comps = build_components(
            maps, links, params, sound, layers=layers, firsts=firsts, blur=blur
        )
        cpu = time.thread_time() - t0
        self.samples.append((blur, fused, max(cpu - graph, 0.0)))
        return comps, cpu


def _shared_scans(load):
    """``load`` (:func:`agent.sources.load_scans`), read once per run whatever the segment."""

    @lru_cache(maxsize=4)
    def whole(kind, path, topic):
        return load(SourceSpec(kind, path, topic=topic))

    return lambda spec: whole(spec.kind, spec.path, spec.topic)


@contextlib.contextmanager
def simulated_core(rebuilds: Rebuilds) -> Iterator[None]:
    """Run :mod:`agent.worker` on ``rebuilds.meter``'s clock with ``rebuilds``, and read each
    log once for all robots (:func:`agent.sources.load_scans`, memoised)."""
    saved = (agent.worker.time, agent.worker.build_components, agent.sources.load_scans)
    agent.worker.time = rebuilds.meter.clock
    agent.worker.build_components = rebuilds
    agent.sources.load_scans = _shared_scans(saved[2])
    try:
        yield
    finally:
        agent.worker.time, agent.worker.build_components, agent.sources.load_scans = saved


@dataclass
class LoopClock:
    """Stands in for the ``time`` module in :mod:`agent.wire`: ``monotonic`` reads ``now()``."""

    now: Callable[[], float]

    def monotonic(self) -> float:
        return self.now()


@contextlib.contextmanager
def simulated_wire(now: Callable[[], float]) -> Iterator[None]:
    """Run :mod:`agent.wire` on simulated time ``now()``: the ``latest`` queryable's tile
    budget (:class:`agent.wire.TileBudget`, tiles per second) read the real clock, so a
    simulation's fetch replies, and its counts, depended on how fast the simulating machine
    ran."""
    saved = agent.wire.time
    agent.wire.time = LoopClock(now)
    try:
        yield
    finally:
        agent.wire.time = saved
