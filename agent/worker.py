"""The fusion worker: pairwise registration and global-map rebuilds on a thread of their own.

Zenoh callbacks only enqueue (Zenoh runs a subscriber's callbacks one at a time, so a slow one
delays every later sample), and the receiving thread only reassembles and stores maps;
everything that takes CPU time, the merge (Sec. IV) and the fusion (33)-(37), runs here, one
job at a time:

1. if some pair lacks a link of its latest versions and it is this agent's turn
   (:meth:`agent.links.Turns.due`), register it, cache and publish the link, loop;
2. otherwise, if the maps or the chosen links changed, rebuild the global maps.

Verify before you search: when the accepted links already place both robots of a pair in one
component (the robust pose graph's placements, :func:`predict`), that prediction is checked
first (:func:`verify_check`: a local refinement and the merge's own acceptance test, about
0.05 s) and the full search of the merge (Fig. 1, seconds) runs only where the check is
inconclusive.  A prediction under which the two maps share too few walls, or disagree once
refined within the basin, is a decided rejection -- a search could only find a transform the
chain contradicts -- but only for a pair a search already rejected in an earlier epoch, or
whose robots the chain joins over links on triangles only (:func:`_rejection_stands`): were the
chain wrong on a bridge or a long lone cycle, a first search is what finds the true link that
exposes it around a short cycle.  Nor is every pair of a component checked: a prediction that
places the two maps' known cells more than a few metres apart (:mod:`agent.footprints`) is the
check's no-overlap rejection without reading the maps, so checks grow with the pairs that
overlap, not with the pairs.  Searches go by waves (:func:`agent.links.open_keys`):
neighbours on the circle of robots first, a pair further apart only once the nearer ones are
decided, and by then most pairs are checks.  A search that a new epoch of either map
superseded while it ran is checked on the new maps (:meth:`FusionWorker._carry_forward`)
rather than searched again.  So full searches grow with the robots (each joins its component
once, plus the pairs whose chain is off), not with the pairs -- within one connected fleet:
pairs between groups no link joins are searched in each new epoch of either map, (N/2)^2 for
two groups of N/2.

Nor is a pair searched whose map A the merge rejects on its own (:data:`GateFn`,
:func:`pgvd.merge.a_side_rejection`: a robot's first maps, a few metres across, have no GVD
edge long enough to match): the gate's verdict, asked once per map version, is the search's
own rejection, recorded with a reason that says it was not searched.  Such a pair keeps the
later waves closed for a while (:data:`GATE_HOLD_S`): its maps are about to grow, and the link
they then give may turn the later waves' searches into checks.

Known initial poses (``--known-pose``, :mod:`agent.priors`) are checked the same way, and
before a chain's prediction: a pair whose two poses are known is checked at their prior
transform, and the check can only confirm it.  A prior that fails the check decides nothing --
a wrong prior is never accepted as it stands, nor does it reject the pair -- and the pair goes
on to the chain's check or the full search.  Which way a link was decided does not enter the
global map, which stays a function of the maps and the links (fleet invariant 2).
"""

from __future__ import annotations

import logging
import threading
import time
from bisect import insort
from collections.abc import Callable, Collection, Mapping
from dataclasses import dataclass, replace
from functools import partial
from typing import TYPE_CHECKING

import numpy as np

from agent.book import FleetBook, Snapshot
from agent.counters import Counters
from agent.footprints import MARGIN_M, FootprintCache
from agent.fusecache import LayerCache
from agent.globalmap import Component, Soundness, build_components, usable_links
from agent.greycycle import on_cycle_candidate
from agent.links import (
    GATED,
    LinkKey,
    LinkRecord,
    Turns,
    Waves,
    epoch_of,
    stale_candidate,
    version_text,
)
from agent.memory import release_free_memory
from agent.priors import Pose, pair_prior
from agent.profiling import profiled
from agent.trust import (
    CANDIDATE,
    CONFIRMED,
    IN_MAP,
    QUIET_S,
    Verdict,
    carried_verdict,
    carries,
    clean_reason,
    corner_spread,
    cycle_verdict,
    first_verdict,
    holds,
    in_grey_zone,
    link_strength,
    pose_change,
    provisional,
    recheck_verdict,
    settled_verdict,
    standing_accept,
)
from pgvd.grid import Grid
from pgvd.posegraph import Solution, components, link_problem, solve, triangle_groups

if TYPE_CHECKING:  # the merge loads scipy; the worker imports it only when it runs
    from pgvd.params import MergeParams
    from pgvd.result import MergeResult
    from pgvd.verify import PooledMaps

log = logging.getLogger("pgvd.agent")


@dataclass(frozen=True)
class Registration:
    """What a pairwise registration decided; ``matrix`` maps B pixels to A pixels.

    ``reason`` says why, in the merge's words (:attr:`pgvd.result.MergeResult.reason`): an
    operator reading the agent's log sees why two robots' maps were not linked.
    """

    accepted: bool
    matrix: np.ndarray
    covariance: np.ndarray
    score: float
    reason: str = ""
    #: the acceptance statistic at ``matrix`` (:mod:`pgvd.decision`); None when unscored
    margin: float | None = None

    @property
    def rejection(self) -> str:
        """Why the link was rejected; empty when it was accepted or no reason was given."""
        return "" if self.accepted else self.reason


RegisterFn = Callable[[Grid, Grid], Registration]
#: ``check(a, b, predicted)``: a :class:`Registration` when the prediction decides the pair
#: (confirmed, or the maps do not overlap under it), None when a full search must decide.
CheckFn = Callable[[Grid, Grid, np.ndarray], Registration | None]

#: ``gate(a)``: why the search rejects any pair whose map A is ``a`` whatever map B
#: (:func:`pgvd.merge.a_side_rejection`), None when a search may pass.
GateFn = Callable[[Grid], str | None]

#: Seconds a pair whose search the gate skipped (:data:`GateFn`) keeps later waves of
#: searches closed (:func:`agent.links.open_keys`): a robot's first maps are a few metres
#: across and soon grow into a new epoch, whose pair is then searched before any further
#: one; a map that stays too small (a robot that stopped) holds the waves no longer.
GATE_HOLD_S = 10.0

#: Seconds a solution of the pose graph keeps serving predictions once newer accepted links
#: arrived (:meth:`FusionWorker._solved_for`).
RESOLVE_AFTER = 2.0
#: :class:`Chains` with provisional accepts taken as links kept at once
#: (:meth:`FusionWorker._provisional_chains`): a round's first tries and re-checks each
#: leave out their own pair.
PROVISIONAL_CACHE = 8
#: Largest share of the wall time an agent spends on previews (unsettled global maps).
PREVIEW_SHARE = 0.05
#: The share while a round of registrations only re-places the maps of the last rebuild (no
#: map changed since), or every pair still needed is a check: the settled map is that close.
CHECKS_PREVIEW_SHARE = PREVIEW_SHARE / 4
#: What a rejection without a pose records: finite for the wire.
_REJECTED = (np.eye(3), np.zeros((3, 3)))
#: Why a pair whose known cells the prediction places apart is rejected
#: (:meth:`FusionWorker._apart`).
APART = f"the predicted pose puts the known cells more than {MARGIN_M:g} m apart"


@dataclass(frozen=True)
class _Clock:
    """When a job started, on the wall clock and in this thread's CPU time."""

    wall: float
    cpu: float

    @classmethod
    def start(cls) -> _Clock:
        return cls(time.monotonic(), time.thread_time())

    def elapsed(self) -> tuple[float, float]:
        """Wall and CPU seconds since :meth:`start` (on a shared machine they differ)."""
        return time.monotonic() - self.wall, time.thread_time() - self.cpu


class _Unproven:
    """A check's rejection that may not stand without a search (:meth:`FusionWorker._checked`)."""


def _merge_params(min_agreement: float | None) -> MergeParams:
    """The merge's parameters for a fleet, ``min_agreement`` overridden unless None."""
    from pgvd.params import MergeParams

    params = MergeParams(diagnostics=False)
    return params if min_agreement is None else replace(params, min_agreement=min_agreement)


def _registration(
    accepted: bool,
    matrix: np.ndarray,
    cov: np.ndarray,
    score: float,
    reason: str = "",
    margin: float | None = None,
) -> Registration:
    """A merge or check result as a :class:`Registration`, finite whatever happened.

    A rejection keeps its best pose (and a covariance, if finite): a grey-zone candidate
    (:mod:`agent.trust`) is checked again there, and the log says where it was.
    """
    matrix = np.asarray(matrix, dtype=np.float64)
    cov = np.asarray(cov, dtype=np.float64)
    score = float(score) if np.isfinite(score) else 0.0
    margin = float(margin) if margin is not None and np.isfinite(margin) else None
    has_pose = np.isfinite(matrix).all()
    if not (accepted and has_pose and np.isfinite(cov).all()):
        why = reason if reason and not accepted else "no finite pose or covariance"
        pose = matrix if has_pose else _REJECTED[0]
        known = cov if np.isfinite(cov).all() else _REJECTED[1]
        return Registration(False, pose, known, score, why, margin)
    return Registration(True, matrix, cov, score, reason, margin)


def _grey_covariance(
    a: Grid, b: Grid, matrix: np.ndarray, params: MergeParams, maps: PooledMaps | None = None
) -> np.ndarray:
    """The covariance (3) a grey-zone pose would have had, were it accepted
    (:func:`pgvd.inflation.inflated_covariance`, as the merge reports it): a candidate that
    is confirmed later enters the pose graph with it."""
    from pgvd.inflation import inflated_covariance
    from pgvd.pooling import covariance_from_pooled, to_pooled
    from pgvd.verify import pooled_maps

    maps = maps or pooled_maps(a, b, params)
    pooled = to_pooled(matrix, maps.pool)
    cov = inflated_covariance(maps.a, maps.b, pooled, maps.cell)
    return covariance_from_pooled(cov, pooled, maps.pool)


def _usable_margin(res: MergeResult, params: MergeParams) -> float:
    """The margin of a merge or check result as the lifecycle reads it (:mod:`agent.trust`):
    NaN for a rejected pose whose overlay disagrees (agreement below ``min_agreement``), which
    no later version may confirm however it stands out."""
    if not res.accepted and res.score < params.min_agreement:
        return float("nan")
    return res.margin


def _with_grey_covariance(
    res: Registration, a: Grid, b: Grid, params: MergeParams, maps: PooledMaps | None = None
) -> Registration:
    """``res``, with :func:`_grey_covariance` when it is a rejection in the grey zone."""
    if res.accepted or not in_grey_zone(res.margin, params.min_margin):
        return res
    return replace(res, covariance=_grey_covariance(a, b, res.matrix, params, maps))


def merge_registration(min_agreement: float | None = None) -> RegisterFn:
    """:func:`pgvd.merge.merge` as a :data:`RegisterFn` (rho test (32) plus global check).

    ``min_agreement`` overrides the merge's acceptance threshold on the overlay agreement
    (None keeps the merge's own): a fleet may want it stricter than a one-off merge,
    because a false link corrupts the global map of every agent, not one output file.
    """
    from pgvd.merge import merge

    params = _merge_params(min_agreement)

    def register(a: Grid, b: Grid) -> Registration:
        res = merge(a, b, params)
        margin = _usable_margin(res, params)
        out = _registration(res.accepted, res.matrix, res.covariance, res.score, res.reason, margin)
        return _with_grey_covariance(out, a, b, params)

    return register


def merge_gate(min_agreement: float | None = None) -> GateFn:
    """:func:`pgvd.merge.a_side_rejection` as a :data:`GateFn`, with the parameters of
    :func:`merge_registration`: a pair it rejects is one that registration rejects."""
    from pgvd.merge import a_side_rejection

    params = _merge_params(min_agreement)

    def gate(a: Grid) -> str | None:
        return a_side_rejection(a, params)

    return gate


def verify_check(min_agreement: float | None = None) -> CheckFn:
    """:func:`pgvd.verify.verify` as a :data:`CheckFn`, with the merge's thresholds.

    Confirmed: the refined transform is the link.  Rejected (a verdict the worker takes only
    for a pair a search rejected before, or joined by a chain over cycles) when, at the place
    the chain puts the maps, they cannot pass the merge's tests: fewer than ``min_overlap``
    metres of walls of either map on the other's known space (agreeing or not) at the
    *predicted* transform, or the pose refined within the basin
    (:data:`pgvd.verify.BASIN_M`, ``BASIN_DEG``) still fails the merge's tests (it does not
    stand out from itself shifted, or the overlay disagrees).  A search there could
    only find a transform the chain contradicts.  A correction beyond the basin is
    inconclusive: the chain may be off, the search decides.
    """
    from pgvd.verify import BASIN_DEG, BASIN_M, pooled_maps, predicted_overlap, verify

    params = _merge_params(min_agreement)

    def check(a: Grid, b: Grid, predicted: np.ndarray) -> Registration | None:
        # the maps are read once for both questions: on fine maps reading is most of the cost
        maps = pooled_maps(a, b, params)
        res = verify(a, b, predicted, params, maps)
        if res.accepted:
            return _registration(True, res.matrix, res.covariance, res.score, margin=res.margin)
        seen = predicted_overlap(a, b, predicted, res.matrix, params, maps)
        if seen.overlap_m < params.min_overlap:
            why = (
                f"the predicted pose overlaps {seen.overlap_m:.1f} m of walls "
                f"< {params.min_overlap} m"
            )
            return Registration(False, np.asarray(predicted, np.float64), _REJECTED[1], 0.0, why)
        # NaN (B without walls) fails both comparisons: inconclusive
        if seen.shift_m <= BASIN_M and seen.turn_deg <= BASIN_DEG:
            margin = _usable_margin(res, params)
            out = _registration(False, res.matrix, res.covariance, res.score, res.reason, margin)
            return _with_grey_covariance(out, a, b, params, maps)
        return None

    return check


def _taken_as_accepted(ln: LinkRecord, pair: tuple[str, str], bar: float) -> bool:
    """Whether ``ln`` is a link in the map once the provisional accepts (above ``bar``, the
    merge's ``min_margin``) of pairs other than ``pair`` count as links
    (:meth:`FusionWorker._as_accepted`)."""
    return ln.accepted or (ln.pair != pair and provisional(ln.state, ln.margin, bar))


def _rejected_before(links: list[LinkRecord], a: str, b: str) -> bool:
    """Whether the link standing in for ``(a, b)`` (an earlier epoch's) is a rejection."""
    held = next((ln for ln in links if ln.pair == (a, b)), None)
    return held is not None and not held.accepted


def _current_chain(snap: Snapshot, group: Collection[str]) -> bool:
    """Whether every accepted link within ``group`` is of its robots' current epochs.

    A link of an older epoch stands in while the current one is computed
    (:func:`agent.links.select_links`), but its matrix maps the pixels of the maps of its
    epochs: a robot whose SLAM grew its canvas starts an epoch whose pixels are not those,
    and a prediction through such a link can be metres off.
    """
    versions = {r: v for r, (v, _) in snap.maps.items()}
    return all(
        ln.current(versions) for ln in snap.links if ln.accepted and ln.a in group and ln.b in group
    )


def cycle_pose(snap: Snapshot, held: LinkRecord, versions: dict[str, int]) -> np.ndarray | None:
    """The pose of ``held``'s pair that the links in the map and the other pairs' cycle
    candidates (:func:`agent.greycycle.on_cycle_candidate`) predict, all of current epochs
    (``versions``, those of ``snap.maps``); None when they do not join its robots so."""
    links = [
        replace(ln, accepted=True, state=CONFIRMED)
        if ln.pair != held.pair and on_cycle_candidate(ln, versions)
        else ln
        for ln in snap.links
    ]
    chains = Chains(snap.maps, links)
    a, b = held.pair
    group = next((g for g in chains.groups if a in g and b in g), None)
    if group is None or not _current_chain(replace(snap, links=links), group):
        return None
    return predict(chains.solved()[0], a, b)


@dataclass(frozen=True)
class CycleLinks:
    """All :func:`cycle_pose` reads of a snapshot but the pair it predicts: the robots and
    their epochs (the links' ``current``), the accepted links and the cycle candidates
    (:func:`agent.greycycle.on_cycle_candidate`), each named by its
    :attr:`~agent.links.LinkRecord.identity`, which holds every field the pose graph and
    :func:`_current_chain` read.  The links neither accepted nor candidates are not read.
    """

    generation: int | None
    epochs: tuple[tuple[str, int], ...]
    accepted: tuple[tuple[object, ...], ...]
    candidates: tuple[tuple[tuple[str, str], tuple[object, ...]], ...]
    #: The pairs of ``candidates``.
    pairs: frozenset[tuple[str, str]]

    @classmethod
    def empty(cls) -> CycleLinks:
        return cls(None, (), (), (), frozenset())

    def of(self, snap: Snapshot, versions: dict[str, int]) -> CycleLinks:
        """These links if ``snap`` is of the same book generation, else those of ``snap``
        (``versions``: of its maps)."""
        if snap.generation is not None and snap.generation == self.generation:
            return self
        candidates = tuple(
            (ln.pair, ln.identity) for ln in snap.links if on_cycle_candidate(ln, versions)
        )
        return CycleLinks(
            snap.generation,
            tuple(sorted((r, epoch_of(v)) for r, v in versions.items())),
            tuple(ln.identity for ln in snap.links if ln.accepted),
            candidates,
            frozenset(p for p, _ in candidates),
        )

    def signature(self, pair: tuple[str, str]) -> tuple[object, ...]:
        """What :func:`cycle_pose` reads to predict ``pair``: the other pairs' candidates
        count as links, not its own."""
        return (pair, self.epochs, self.accepted, tuple(i for p, i in self.candidates if p != pair))


#: Robots joined by links of current epochs: over triangles only, and at all
#: (:meth:`FusionWorker._current_groups`).
Joins = tuple[list[tuple[str, ...]], list[tuple[str, ...]]]


def _current_pairs(snap: Snapshot, kept: list[LinkRecord]) -> tuple[tuple[str, str], ...]:
    """The pairs of the links ``kept`` that ``snap`` still holds, of its current epochs."""
    versions = {r: v for r, (v, _) in snap.maps.items()}
    held = {id(ln) for ln in snap.links}
    return tuple(ln.pair for ln in kept if id(ln) in held and ln.current(versions))


def _joins(pairs: tuple[tuple[str, str], ...]) -> Joins:
    """The triangle groups (:func:`pgvd.posegraph.triangle_groups`) and the components of
    ``pairs``."""
    nodes = sorted({r for pair in pairs for r in pair})
    return triangle_groups(nodes, pairs), components(nodes, pairs)


def _rejection_stands(joins: Joins, links: list[LinkRecord], a: str, b: str) -> bool:
    """Whether a check's rejection of ``(a, b)`` may stand without a search, given how the
    links kept of current epochs join robots (``joins``, :func:`_joins`).

    Only over links of the current epochs (:func:`_current_chain`): a link of older epochs
    maps the pixels of its epochs, and a robot whose SLAM grew its canvas is placed metres
    off through it.  Over those, the rejection stands when the chain from ``a`` to ``b``
    runs over links on triangles only: were it wrong (a false link on a bridge, or on a
    long cycle alone, where its error spreads thin), skipping the search would lose the
    true link that closes a short cycle around the false one and lets the pose graph reject
    it.  For a pair a search rejected before (among ``links``), any chain of current links
    will do.  Links of older epochs elsewhere in the component do not matter: a robot whose
    links are of an older epoch moves only itself, and in a large fleet some robot always
    is in a new epoch.
    """
    triangles, joined = joins
    if any(a in g and b in g for g in triangles):
        return True
    return any(a in g and b in g for g in joined) and _rejected_before(links, a, b)


def placements(maps: dict[str, tuple[int, Grid]], links: list[LinkRecord]) -> Solution:
    """The robust pose graph (:func:`pgvd.posegraph.solve`, GNC-TLS) of the accepted links.

    A link inconsistent around a cycle is not kept, so it does not enter a prediction; of a
    lone inconsistent cycle, the link of lowest margin leaves (:func:`agent.trust.link_strength`),
    as in the global map.
    """
    return solve(maps, usable_links(maps, links), strength=link_strength)


class Chains:
    """What the accepted links say about the pairs still to decide, solved only if asked.

    ``groups`` (connected components of the usable accepted links, before the robust
    solution drops any) is cheap and tells which pairs a check may decide
    (:func:`agent.links.open_keys`); the pose graph itself (:meth:`solved`, tens to
    hundreds of milliseconds at 16 robots) is solved only for a pair being registered.
    """

    def __init__(
        self,
        maps: dict[str, tuple[int, Grid]],
        links: list[LinkRecord],
        sound: Soundness | None = None,
    ) -> None:
        usable = usable_links(maps, links, sound)
        groups = components(maps, [ln.pair for ln in usable])
        self._set(maps, usable, groups, links)

    def _set(
        self,
        maps: dict[str, tuple[int, Grid]],
        usable: list[LinkRecord],
        groups: list[tuple[str, ...]],
        links: Collection[LinkRecord],
    ) -> None:
        """Hold ``usable`` (of ``links``) and their ``groups`` over the robots of ``maps``."""
        self.maps = maps
        self.usable = usable
        self.groups = groups
        #: The index in ``groups`` of each robot's group: a worker asks :meth:`linked` of
        #: every pair still needed at each step.
        self._group_of = {r: i for i, g in enumerate(self.groups) for r in g}
        #: The links these chains were made of, by ``id`` (held, so no id is reused).
        self._made_of = dict(zip(map(id, links), links, strict=True))
        self._solved: tuple[Solution, list[LinkRecord]] | None = None

    def grown(
        self,
        maps: dict[str, tuple[int, Grid]],
        links: Collection[LinkRecord],
        sound: Soundness | None = None,
    ) -> Chains:
        """``Chains(maps, links, sound)``, the same usable links and groups, made from these
        chains' when ``links`` only adds links to those they were made of over the same
        robots: the groups the new links join are merged (a union-find over the groups),
        not found anew over every link.

        A worker makes chains anew at each accepted link of the fleet (some thousands at 64
        robots), nearly always one link more than the last.
        """
        now = dict(zip(map(id, links), links, strict=True))
        if sorted(maps) != sorted(self.maps) or not self._made_of.keys() <= now.keys():
            return Chains(maps, list(links), sound)
        added = usable_links(maps, [now[i] for i in now.keys() - self._made_of.keys()], sound)
        usable = list(self.usable)
        for ln in added:
            insort(usable, ln, key=_pair)
        grown = Chains.__new__(Chains)
        grown._set(maps, usable, self._joined([ln.pair for ln in added]), links)
        return grown

    def _joined(self, pairs: list[tuple[str, str]]) -> list[tuple[str, ...]]:
        """``groups`` with those ``pairs`` join merged, as :func:`pgvd.posegraph.components`
        gives them: each sorted (the lowest id anchors), in the order of their anchors."""
        parent = list(range(len(self.groups)))

        def root(i: int) -> int:
            while parent[i] != i:
                i = parent[i]
            return i

        for a, b in pairs:
            i, j = root(self._group_of[a]), root(self._group_of[b])
            parent[max(i, j)] = min(i, j)
        members: dict[int, list[str]] = {}
        for i, group in enumerate(self.groups):
            members.setdefault(root(i), []).extend(group)
        return sorted(tuple(sorted(m)) for m in members.values())

    def linked(self, a: str, b: str) -> bool:
        """Whether accepted links join ``a`` and ``b`` (a prediction is likely)."""
        group = self._group_of.get(a)
        return group is not None and group == self._group_of.get(b)

    def regrouped(self, before: Chains | None) -> set[str] | None:
        """The robots whose group is not the one they had in ``before``: :meth:`linked`
        answers as in ``before`` for any pair of other robots.  None: no ``before``."""
        if before is None:
            return None
        mine, theirs = set(self.groups), set(before.groups)
        return {r for g in mine ^ theirs for r in g}

    def solved(self) -> tuple[Solution, list[LinkRecord]]:
        """:func:`placements`, and the links it kept (:func:`_rejection_stands` reads on
        which of them a rejection may rest)."""
        if self._solved is None:
            clock = _Clock.start()
            sol = solve(self.maps, self.usable, strength=link_strength)
            kept = [ln for ln, u in zip(self.usable, sol.used, strict=True) if u]
            self._solved = (sol, kept)
            log.debug("solved %d links: %.2f s, %.2f s CPU", len(self.usable), *clock.elapsed())
        return self._solved


def _pair(ln: LinkRecord) -> tuple[str, str]:
    return ln.pair


def predict(sol: Solution, a: str, b: str) -> np.ndarray | None:
    """The B-pixel -> A-pixel matrix the placements imply for ``(a, b)``; None when the
    links kept do not put ``a`` and ``b`` in one component."""
    if not any(a in c and b in c for c in sol.components):
        return None
    return np.linalg.inv(sol.transforms[a]) @ sol.transforms[b]


@dataclass(frozen=True)
class GlobalState:
    """The last rebuild: its components, and whether every pair had its latest link."""

    components: list[Component]
    settled: bool
    built_at: float


class FusionWorker:
    """Runs registrations and rebuilds until :meth:`stop`.

    Parameters
    ----------
    me : this agent's robot id (decides whose turn a pair is).
    book : the shared :class:`FleetBook`.
    register : pairwise registration, deterministic in its inputs.
    on_link : called with each link this worker decided (to publish and persist it).
    on_global : called with each new :class:`GlobalState`.
    link_timeout : seconds to wait for the lower robot's agent before registering.
    check : checks a pair's predicted transform before a full search (:data:`CheckFn`);
        None always searches.
    counters : where ``searches``, ``checks``, ``checks_confirmed``, ``checks_rejected``,
        ``checks_skipped`` (pairs placed apart, :meth:`_apart`), ``prior_checks``,
        ``prior_confirmed`` and ``prior_failed`` are counted (the status shows them).
    gate : skips the search of a pair whose map A the merge rejects on its own
        (:data:`GateFn`, ``searches_gated``); None searches every pair it must.
    poses : known initial poses, robot -> ``(x, y, yaw)`` of its map frame in the world frame
        (:func:`agent.priors.parse_known_pose`); a pair with both is checked at their prior
        first (with ``check``).
    """

    def __init__(
        self,
        me: str,
        book: FleetBook,
        register: RegisterFn,
        on_link: Callable[[LinkRecord], None],
        on_global: Callable[[GlobalState], None],
        link_timeout: float = 4.0,
        check: CheckFn | None = None,
        counters: Counters | None = None,
        poses: Mapping[str, Pose] | None = None,
        gate: GateFn | None = None,
    ) -> None:
        self.me = me
        self.book = book
        self.register = register
        self.on_link = on_link
        self.on_global = on_global
        self.link_timeout = link_timeout
        self.check = check
        self.counters = counters or Counters()
        self.poses = dict(poses or {})
        self.gate = gate
        #: The gate's verdict on each (robot, version) of the maps held (:meth:`_gated`).
        self._gate_verdicts: dict[tuple[str, int], str | None] = {}
        #: When this worker first saw each gated rejection that holds the waves (:meth:`_holding`).
        self._held_since: dict[tuple[object, ...], float] = {}
        #: The gated rejections of the book's generation, identity -> pair (:meth:`_holding`).
        self._gated_links: tuple[int | None, dict[tuple[object, ...], tuple[str, str]]] = (
            None,
            {},
        )
        #: What :meth:`_open` made last, with what it was made of.
        self._opened: tuple[tuple[object, ...], set[LinkKey], list[LinkKey]] | None = None
        #: The keys open, kept from one change of the book to the next (:meth:`_open`), and
        #: the :class:`Chains` they were last placed by.
        self._waves = Waves()
        self._turns = Turns()
        self._waves_chains: Chains | None = None
        #: :class:`Chains` of the links held, with the signature of what they depend on.
        self._chains: tuple[object, Chains | None] = (None, None)
        #: :meth:`_provisional_chains` by signature, the oldest first.
        self._provisional: dict[tuple[object, ...], tuple[list[LinkRecord], Chains]] = {}
        #: Which link records held are sound (:data:`Soundness`).
        self._sound: Soundness = {}
        #: The warped maps of the last rebuild, for the next (:class:`LayerCache`).
        self._layers = LayerCache()
        #: The :class:`Chains` whose solution predicts, and the step time it was solved at.
        self._solution: tuple[Chains | None, float] = (None, -np.inf)
        #: The time of the current :meth:`step`.
        self._now = 0.0
        #: When each needed key's turn came (:func:`agent.links.open_keys`).
        self._opened_at: dict[LinkKey, float] = {}
        #: The pairs of current links kept and how they join robots (:meth:`_current_groups`).
        self._joins: tuple[tuple[tuple[str, str], ...] | None, Joins] = (None, ([], []))
        #: Known-cell footprints of the maps held (:meth:`_apart`).
        self._footprints = FootprintCache()
        #: Due keys whose check rejected the pair where a rejection needs a search; they wait
        #: for the other checks of the round (:meth:`_register`).
        self._deferred: set[LinkKey] = set()
        #: This agent's newest decision of each pair that the book refused, its epochs
        #: superseded while it was decided: still the newer epoch's word (:meth:`_previous`).
        self._unheld: dict[tuple[str, str], LinkRecord] = {}
        #: What :func:`cycle_pose` counts as links, and its last answer per candidate pair
        #: with the signature of what it read (:meth:`_cycle_pose`).
        self._cycle_links = CycleLinks.empty()
        self._cycle_poses: dict[tuple[str, str], tuple[tuple[object, ...], np.ndarray | None]] = {}
        self.merges = 0
        self.merge_seconds = 0.0
        self._stop = threading.Event()
        self._wake = threading.Event()
        self._built: tuple[object, ...] | None = None
        self._rebuilt_at = -np.inf
        #: Seconds between rebuilds of a global map still waiting for links, at least.
        self.preview_interval = 3.0
        #: Seconds a provisional accept of this agent's waits on unchanged maps (:meth:`_quiet`).
        self.quiet_s = QUIET_S
        #: When each of this agent's provisional accepts on the maps held was first seen.
        self._quiet_since: dict[tuple[object, ...], float] = {}
        #: Whether one of them may yet enter the map (:meth:`_quiet`): not settled.
        self._quiet_waiting = False
        #: The link ids of the book, and this agent's candidates already tried against a
        #: cycle under them (:meth:`_cycled`).
        self._cycle_tried: tuple[tuple[object, ...], set[tuple[object, ...]]] = ((), set())
        #: :func:`corner_spread` of each candidate :meth:`_cycled` tried, by its identity and
        #: map B's shape and resolution.
        self._spreads: dict[tuple[object, ...], float] = {}
        #: Wall seconds the last rebuild took (:meth:`preview_gap`).
        self._rebuild_seconds = 0.0
        self._thread = threading.Thread(
            target=profiled, args=(me, "fusion", self._run), name="pgvd-fusion", daemon=True
        )

    def start(self) -> None:
        self._thread.start()

    def wake(self) -> None:
        """The book moved forward: look for work now rather than at the next poll."""
        self._wake.set()

    def stop(self, timeout: float = 1.0) -> None:
        self._stop.set()
        self._wake.set()
        self._thread.join(timeout)

    def _run(self) -> None:
        while not self._stop.is_set():
            self._wake.wait(0.2)  # also polls: a pair's turn comes with time alone
            self._wake.clear()
            try:
                while not self._stop.is_set():
                    more = self.step()
                    # After every job, not only when idle: under continuous updates the worker
                    # is rarely idle, and a soak then showed RSS at merge high-water marks
                    # (growth 14 % against 7 %). Faulting pages back in costs ~5 % of a merge.
                    release_free_memory()
                    if not more:
                        break
            except Exception:  # a bug here must not kill the agent silently
                log.exception("fusion worker step failed")
                time.sleep(0.5)

    def step(self, now: float | None = None) -> bool:
        """Do one job; True if there may be more to do right away."""
        now = time.monotonic() if now is None else now
        self._now = now
        snap = self.book.snapshot()
        self._footprints.forget_except(set(snap.maps))
        if self._unheld:
            self._unheld = {p: r for p, r in self._unheld.items() if set(p) <= snap.maps.keys()}
        # The circle of robots whose turns and waves the fleet shares: every robot whose agent
        # is up, not only those whose maps arrived here, so that agents that heard different
        # maps so far still agree whose turn a pair is and do not both search it.
        robots = sorted(set(snap.maps) | (snap.alive or frozenset()))
        # Without checks every pair is a search anyway: no wave to wait for.
        checkable: Collection[LinkKey] = set()
        opened = snap.needed
        if self.check is not None:
            checkable, opened = self._open(snap, robots, now)
        # A pair's turn (and the timeouts of the agents stepping in) counts from when its
        # wave opened, not from when it was first needed: else every agent of a late wave
        # would be past its timeout at once and search it too.
        self._opened_at = {k: self._opened_at.get(k, now) for k in opened}
        self._deferred &= set(opened)
        due = self._turns.due(
            self.me,
            opened,
            self._opened_at,
            now,
            self.effective_timeout(len(snap.maps)),
            robots,
            snap.alive,
        )
        # A preview that places another robot with this agent's own is what its user
        # waits for: on replayed logs such a link waited 3-17 s, behind the preview gap
        # and behind the registrations of robots that keep mapping, to be shown.  It comes
        # first, after ``preview_interval`` at most (a robot joins the group once).
        own = self._own_group(snap)
        regrouped = self._built is not None and own != self._built[2]
        show_first = regrouped and now - self._rebuilt_at >= self.preview_interval
        if due and not show_first:
            # Checks first: they take tens of milliseconds, and each link they add may
            # turn a pair waiting for a full search into one more check.  Deferred checks
            # last among them: the links the others add may let their rejection stand.
            due.sort(key=lambda k: (k not in checkable, k in self._deferred))
            others = any(k in checkable and k not in self._deferred for k in due[1:])
            self._register(snap, due[0], may_defer=others)
            return True
        if not due and (self._quiet(snap, now) or self._cycled(snap)):
            return True
        # an own provisional accept still waiting on final or quiet maps may yet enter the map
        settled = snap.settled and not self._quiet_waiting
        signature = (
            tuple(sorted((r, v, snap.firsts.get(r)) for r, (v, _) in snap.maps.items())),
            # the candidate used, not only its key: a preferred candidate arriving for a
            # key (another agent's, or a liar's) changes the global map
            snap.link_ids,
            own,
            settled,  # a preview is fused without eq. (8)'s blur (:meth:`_rebuild`)
        )
        # An unsettled map is only a preview: rebuilding it on every link of a round
        # would take CPU from the registrations the settled map waits for.
        checks_only = bool(snap.needed) and all(k in checkable for k in snap.needed)
        maps_moved = self._built is None or signature[0] != self._built[0]
        gap = self.preview_interval if regrouped else self.preview_gap(checks_only, maps_moved)
        if (
            snap.maps
            and signature != self._built
            and (snap.settled or now - self._rebuilt_at >= gap)
        ):
            self._built = signature  # a failing rebuild is not retried until inputs change
            self._rebuilt_at = now
            clock = _Clock.start()
            try:
                self._rebuild(snap, settled)
            finally:
                self._rebuild_seconds, cpu = clock.elapsed()
                log.debug(
                    "rebuilt %d maps, %d links (%s): %.2f s, %.2f s CPU",
                    len(snap.maps), len(snap.links), "settled" if settled else "preview",
                    self._rebuild_seconds, cpu,
                )  # fmt: skip
        return bool(due)  # registrations put off for the preview

    def _open(
        self, snap: Snapshot, robots: list[str], now: float
    ) -> tuple[set[LinkKey], list[LinkKey]]:
        """The keys needed that a check may decide, and the keys open
        (:func:`agent.links.open_keys`); made anew only when the book, the robots, the
        chains or the pairs holding the waves changed, and then only for the keys that
        changed or whose robots' groups did (:class:`agent.links.Waves`).

        A worker steps at every wake and every poll, and at 128 robots some thousands of
        keys are needed: going over them all at each idle poll cost as much as the work.
        """
        chains = self._chains_of(snap)
        holding = self._holding(snap, now)
        key = (snap.generation, tuple(robots), chains, tuple(holding))
        held = self._opened
        if snap.generation is None or held is None or held[0] != key:
            checkable, opened = self._waves.update(
                snap.needed,
                snap.rechecks,
                robots,
                holding,
                partial(self._checkable, chains),
                chains.regrouped(self._waves_chains),
            )
            self._waves_chains = chains
            held = self._opened = (key, checkable, opened)
        return held[1], held[2]

    def _quiet(self, snap: Snapshot, now: float) -> bool:
        """Decide one of this agent's provisional accepts whose maps will not change: both
        final at once, else once unchanged for :attr:`quiet_s`
        (:func:`agent.trust.settled_verdict`, :meth:`_settled_verdict`); True if one was.

        Only the agent that decided the accept confirms it, so the fleet publishes one
        record for it; the record, not the clock, is what every agent's global map follows.
        An accept that the links in the map contradict is recorded once as a candidate
        saying so, and waits no more while they do: its record is the decision.
        """
        versions = {r: v for r, (v, _) in snap.maps.items()}
        standing = {
            (ln.a, ln.version_a, ln.b, ln.version_b): ln
            for ln in snap.links
            if ln.decided_by == self.me
            and standing_accept(ln.state, ln.margin, ln.first_margin, self.min_margin)
            and (ln.version_a, ln.version_b) == (versions.get(ln.a), versions.get(ln.b))
        }
        # by versions, not by record: a refusal recorded keeps the time its accept was ripe
        self._quiet_since = {k: self._quiet_since.get(k, now) for k in standing}
        ripe = [
            (ln, self._settled_verdict(snap, ln))
            for k, ln in standing.items()
            if self._final(snap, ln) or now - self._quiet_since[k] >= self.quiet_s
        ]
        # a refusal on record: the accept stays a candidate, as its record already says
        refused = sum(
            v is not None and (v.state, v.reason) == (CANDIDATE, ln.reason) for ln, v in ripe
        )
        new = [(ln, v) for ln, v in ripe if v is not None and v.reason != ln.reason]
        self._quiet_waiting = len(standing) > refused
        if not new:
            return False
        held, verdict = min(new, key=lambda r: r[0].pair)
        res = Registration(True, held.matrix, held.covariance, held.score, "", held.margin)
        base = replace(held, revision=held.revision + 1)
        how = "final" if self._final(snap, held) else "quiet"
        self._record(base, res, verdict, how, _Clock.start())
        return True

    def _cycled(self, snap: Snapshot) -> bool:
        """Confirm one of this agent's candidates that the other pairs' candidates and the
        links in the map place where its pose does (:mod:`agent.greycycle`), if its own
        covariance pins map B (:func:`agent.trust.cycle_verdict`); True if one was.

        Each candidate is tried once per set of links held: on final maps no newer decision
        comes, and the cycle may close only after the candidate was decided.
        """
        if self.check is None:
            return False
        versions = {r: v for r, (v, _) in snap.maps.items()}
        if self._cycle_tried[0] != snap.link_ids:
            self._cycle_tried = (snap.link_ids, set())
        tried = self._cycle_tried[1]
        todo = sorted(
            (
                ln
                for ln in snap.links
                if ln.decided_by == self.me
                and ln.identity not in tried
                and on_cycle_candidate(ln, versions)
            ),
            key=lambda ln: ln.pair,
        )
        for ln in todo:
            tried.add(ln.identity)
            grid_b = snap.maps[ln.b][1]
            # The verdict reads the candidate alone: one its covariance keeps from the map
            # needs no pose graph (at 32 robots 93 % of the tries, 99 % of their CPU).
            spread = self._spread(snap, ln, grid_b)
            verdict = cycle_verdict(ln.margin, spread, "consistent cycle of candidates")
            if verdict is None:  # its record stays; the next epoch decides
                continue
            predicted = self._cycle_pose(snap, ln, versions)
            if predicted is None or not holds(predicted, ln.matrix, grid_b):
                continue
            res = Registration(True, ln.matrix, ln.covariance, ln.score, "", ln.margin)
            base = replace(ln, revision=ln.revision + 1)
            self._record(base, res, verdict, "cycle", _Clock.start())
            return True
        return False

    def _spread(self, snap: Snapshot, ln: LinkRecord, grid_b: Grid) -> float:
        """:func:`corner_spread` of ``ln`` on ``grid_b``, kept: a record never changes, and
        :meth:`_cycled` tries each candidate again at every change of the links held (at 64
        robots the spreads, worked out again each time, were a twentieth of the worker's
        CPU).  Those of links no longer held go once the kept outnumber the held twice."""
        key = (ln.identity, grid_b.shape, grid_b.resolution)
        spread = self._spreads.get(key)
        if spread is None:
            if len(self._spreads) > 2 * len(snap.links) + 64:
                held = {x.identity for x in snap.links}
                self._spreads = {k: v for k, v in self._spreads.items() if k[0] in held}
            spread = self._spreads[key] = corner_spread(ln.matrix, ln.covariance, grid_b)
        return spread

    def _cycle_pose(
        self, snap: Snapshot, held: LinkRecord, versions: dict[str, int]
    ) -> np.ndarray | None:
        """:func:`cycle_pose` of ``held``, kept per pair while all it reads stands
        (:class:`CycleLinks`): the robots, their epochs, and the links it counts as accepted.

        A worker tries each of its candidates again at every change of the links held, and
        most changes are rejections, which close no cycle: at 32 robots a third of the
        tries read what the pair's last try read, a fifth of those that solve the pose
        graph of the candidate's whole component, the largest share of a worker's own CPU.
        """
        counted = self._cycle_links = self._cycle_links.of(snap, versions)
        self._cycle_poses = {p: k for p, k in self._cycle_poses.items() if p in counted.pairs}
        signature = counted.signature(held.pair)
        kept = self._cycle_poses.get(held.pair)
        if kept is None or kept[0] != signature:
            kept = self._cycle_poses[held.pair] = (signature, cycle_pose(snap, held, versions))
        return None if kept[1] is None else kept[1].copy()

    @staticmethod
    def _final(snap: Snapshot, ln: LinkRecord) -> bool:
        """Whether both maps of ``ln`` held are their robots' last versions."""
        return ln.a in snap.finals and ln.b in snap.finals

    def _settled_verdict(self, snap: Snapshot, ln: LinkRecord) -> Verdict | None:
        """:func:`agent.trust.settled_verdict` of the provisional accept ``ln`` on maps that
        will not change, against the pose the accepted links predict for its pair
        (:meth:`_chain_pose`); None while links of older epochs join its robots."""
        a, b = ln.pair
        current, predicted = self._chain_pose(snap, a, b)
        if not current:
            return None
        off = None if predicted is None else pose_change(predicted, ln.matrix, snap.maps[b][1])
        return settled_verdict(ln.margin, None if self._final(snap, ln) else self.quiet_s, off)

    def _own_group(self, snap: Snapshot) -> tuple[str, ...]:
        """The robots the accepted links place with this agent's own.

        A worker asks at every step, nearly every step sees a new book, and the components
        of every accepted link were a tenth of its own work at 32 robots: when every
        accepted link of the book's is usable, they are the groups of :meth:`_chains_of`.
        """
        accepted = snap.accepted()
        chains = None if snap.generation is None else self._chains_of(snap)
        if chains is not None and len(chains.usable) == len(accepted):
            groups = chains.groups
        else:
            groups = components(snap.maps, [ln.pair for ln in accepted])
        return next((g for g in groups if self.me in g), ())

    def preview_gap(self, checks_only: bool = False, maps_moved: bool = True) -> float:
        """Seconds between two previews: ``preview_interval``, or more if rebuilds are slow.

        A preview may take at most :data:`PREVIEW_SHARE` of the wall time.  A rebuild fuses
        every map (33)-(37); at 16 robots on 2 cores it took ~0.6 s of CPU and, with every
        agent previewing every 3 s, the previews alone asked for more than the 2 cores: the
        registrations the settled map waits for starved.  Wall time grows with the load, so
        on a crowded machine previews thin out by themselves: with N agents on one host a
        preview's wall time is about N / cores times its CPU time, and the previews of the
        whole fleet take about ``cores * PREVIEW_SHARE`` of the host whatever N.  At 0.1,
        the round after the robots' last maps at 16 robots rebuilt 28 previews beside the
        16 settled maps, ~16 % of that round's CPU.  An agent alone on its computer
        (~0.2 s a rebuild at 16 robots) still previews every few seconds.

        ``checks_only``: every pair still needed is a check (tens of milliseconds each), so
        the settled map is seconds away; a preview may take :data:`CHECKS_PREVIEW_SHARE`.
        At 16 robots the previews rebuilt in the last round of checks (~0.35 s of CPU each,
        seconds of wall time on a loaded machine) delayed the checks the settled map waited
        for.  Not none at all: a fleet whose robots open new epochs faster than a round of
        checks settles still sees its map move.

        ``maps_moved``: some robot's map is not the one the last rebuild fused.  When only
        links changed, a preview shows the same maps re-placed by the links of a round in
        progress, which the settled map replaces once the round ends; it waits as long as
        in a round of checks.  Measured at 16 robots, it spared few previews (28 -> 23-26
        in the round after the last maps): the final versions reach the peers over seconds,
        so most previews of that round still had a new map to show.
        """
        share = PREVIEW_SHARE if maps_moved and not checks_only else CHECKS_PREVIEW_SHARE
        return max(self.preview_interval, self._rebuild_seconds / share)

    def effective_timeout(self, n_robots: int) -> float:
        """``link_timeout`` plus the time a peer needs for its share of a round of pairs.

        When every map changes at once, the first registrar of a pair has about
        ``(n - 1) / 2`` pairs queued; stepping in before it could finish them only
        duplicates work on a busy machine.  This agent's own mean registration time
        stands in for the peers'.
        """
        mean = self.merge_seconds / self.merges if self.merges else 0.0
        return self.link_timeout + mean * max(n_robots - 1, 0) / 2.0

    def _register(self, snap: Snapshot, key: LinkKey, may_defer: bool = False) -> None:
        """Decide ``key``: at the known poses' prior, by the check, or by a full search; a
        candidate of older versions (:mod:`agent.trust`) is checked again at its pose.

        With ``may_defer``, a check's rejection that may not stand yet (:meth:`_checked`)
        puts the key back once, after the other checks due: the links those add may put
        the pair on triangles, and the rejection then stands without a search (a search
        takes seconds at 16 robots, a check tens of milliseconds).
        """
        a, _, b, _ = key  # epochs; the link records the versions it was computed on
        va, vb = snap.maps[a][0], snap.maps[b][0]
        held = next((ln for ln in snap.links if ln.key == key), None)
        if held is not None and stale_candidate(held, {a: va, b: vb}):
            self._recheck(snap, held)
            return
        clock = _Clock.start()
        how = "prior"
        try:
            res = self._at_prior(snap, a, b)
            if res is None:
                how, res = "checked", self._checked(snap, a, b, fresh=key in self._deferred)
            if isinstance(res, _Unproven):
                if may_defer and key not in self._deferred:
                    self._deferred.add(key)
                    self.counters.add("checks_deferred")
                    log.debug("check %s - %s deferred: %.2f s, %.2f s CPU", a, b, *clock.elapsed())
                    return
                res = None
            if res is None:
                how, res = "gated", self._gated(snap, a)
            if res is None:
                how = "searched"
                self.counters.add("searches")
                res = self.register(snap.maps[a][1], snap.maps[b][1])
        except Exception as exc:  # bad maps are an outcome (rejected), not a crash
            log.warning("registration of %s v%d / %s v%d failed: %s", a, va, b, vb, exc)
            res = Registration(False, *_REJECTED, 0.0, f"registration failed: {exc}")
        self.merges += 1
        self.merge_seconds += clock.elapsed()[0]
        verdict = self._first_verdict(snap, a, b, res, searched=how == "searched")
        base = LinkRecord(a, va, b, vb, False, res.matrix, res.covariance, res.score, self.me)
        self._record(base, res, verdict, how, clock)
        if how == "searched" and res.accepted:
            self._carry_forward(a, va, b, vb, res)

    @property
    def min_margin(self) -> float:
        """The merge's own bar ``min_margin`` (below :data:`agent.trust.HIGH_BAR`)."""
        from pgvd.params import DecisionParams

        return DecisionParams.min_margin

    def _first_verdict(
        self, snap: Snapshot, a: str, b: str, res: Registration, searched: bool = False
    ) -> Verdict:
        """The state of a pair's first decision in its epochs (:func:`agent.trust.first_verdict`;
        ``searched``: by a full search, whose accept below the high bar is provisional, and
        confirms a standing accept it finds again only if its covariance pins map B,
        :func:`agent.trust.corner_spread`), confirmed at once when it closes a cycle with
        the accepted links and its covariance pins map B (:meth:`_confirmed_on_cycle`)."""
        previous = self._previous(snap, (a, b))
        grid_b = snap.maps[b][1]
        verdict = first_verdict(
            res.accepted,
            res.margin,
            res.margin is not None,
            res.reason,
            self.min_margin,
            None if previous is None else previous.state,
            previous is not None and holds(previous.matrix, res.matrix, grid_b),
            searched,
            previous is not None
            and standing_accept(
                previous.state, previous.margin, previous.first_margin, self.min_margin
            ),
            corner_spread(res.matrix, res.covariance, grid_b) if res.accepted else 0.0,
        )
        return self._confirmed_on_cycle(snap, a, b, res, verdict)

    def _previous(self, snap: Snapshot, pair: tuple[str, str]) -> LinkRecord | None:
        """The pair's newest decision known here, which a first decision of newer epochs
        follows (:func:`agent.trust.first_verdict`): the link standing in for it in ``snap``
        (:func:`agent.links.select_links`), or this agent's decision of newer epochs that the
        book refused, superseded while it was decided (:meth:`_record`).

        A grey-zone decision or a rejection of a newer epoch ends a provisional accept's
        standing even when the maps moved on before it was recorded: else the next epoch's
        accept at the older pose confirmed it, the grey decision unseen (in the fleet
        bench, a look-alike searched at 0.64, 0.42 and 0.58 was confirmed so).
        """
        held = next((ln for ln in snap.links if ln.pair == pair), None)
        lost = self._unheld.get(pair)
        return lost if lost is not None and (held is None or lost.key > held.key) else held

    def _confirmed_on_cycle(
        self, snap: Snapshot, a: str, b: str, res: Registration, verdict: Verdict
    ) -> Verdict:
        """``verdict`` on ``res``, confirmed if it is a candidate that closes a cycle with the
        accepted links (:meth:`_on_cycle`) and whose own covariance pins map B within the
        hold (:func:`agent.trust.cycle_verdict`).

        The covariance first: it reads the candidate alone, and keeps most candidates out
        without the pose graph a cycle needs.
        """
        if verdict.state != CANDIDATE:
            return verdict
        spread = corner_spread(res.matrix, res.covariance, snap.maps[b][1])
        on_cycle = cycle_verdict(res.margin, spread, "cycle of accepted links")
        if on_cycle is None or not self._on_cycle(
            snap, a, b, res.matrix, provisional(verdict.state, res.margin, self.min_margin)
        ):
            return verdict
        return replace(on_cycle, holds=verdict.holds)

    def _on_cycle(
        self, snap: Snapshot, a: str, b: str, matrix: np.ndarray, provisional: bool = False
    ) -> bool:
        """Whether accepted links of the current epochs already place ``b`` on ``a`` where
        ``matrix`` does (:func:`agent.trust.holds`): the pose closes a consistent cycle.

        ``provisional``: the pose is a search's provisional accept, and the other pairs'
        provisional accepts count as links too: two or more searches that each cleared the
        merge's bar and agree around a cycle are unlikely to be wrong alike.
        """
        if self.check is None:
            return False
        _, predicted = self._chain_pose(snap, a, b, provisional)
        return predicted is not None and holds(predicted, matrix, snap.maps[b][1])

    def _chain_pose(
        self, snap: Snapshot, a: str, b: str, provisional: bool = False
    ) -> tuple[bool, np.ndarray | None]:
        """What the accepted links say of ``(a, b)``: whether those joining the two are all
        of current epochs (:func:`_current_chain`; False: no prediction to trust yet), and
        the pose they predict (:func:`predict`), None when they do not place the two
        together.  ``provisional``: the other pairs' provisional accepts count as links
        (:meth:`_on_cycle`)."""
        chains = self._chains_of(snap)
        if provisional:
            links, chains = self._provisional_chains(snap, (a, b))
            snap = replace(snap, links=links)
        group = next((g for g in chains.groups if a in g and b in g), None)
        if group is None:
            return True, None
        if not _current_chain(snap, group):
            return False, None
        return True, predict(chains.solved()[0], a, b)

    def _provisional_chains(
        self, snap: Snapshot, pair: tuple[str, str]
    ) -> tuple[list[LinkRecord], Chains]:
        """The links of ``snap`` with the other pairs' provisional accepts as links
        (:meth:`_as_accepted`), and their :class:`Chains`, made anew only when the robots or
        the links that count as accepted changed.

        Every provisional first try and re-check asks for them, and a fresh pose graph of
        every accepted link each time was a third of an agent's CPU at 16 robots; the
        signature holds all a :class:`Chains` reads (the robots, and the identity of each
        link taken as accepted, which names its content), so a cached one is the one a
        fresh build gives.
        """
        bar = self.min_margin
        signature = (
            tuple(sorted(snap.maps)),
            tuple(ln.identity for ln in snap.links if _taken_as_accepted(ln, pair, bar)),
        )
        held = self._provisional.get(signature)
        if held is None:
            links = [self._as_accepted(ln, pair) for ln in snap.links]
            held = (links, Chains(snap.maps, links))
            if len(self._provisional) >= PROVISIONAL_CACHE:
                del self._provisional[next(iter(self._provisional))]  # the oldest
            self._provisional[signature] = held
        return held

    def _as_accepted(self, ln: LinkRecord, pair: tuple[str, str]) -> LinkRecord:
        """``ln`` as a link in the map if it is a provisional accept of another pair than
        ``pair`` (:func:`agent.trust.provisional`), else ``ln``."""
        if ln.pair == pair or not provisional(ln.state, ln.margin, self.min_margin):
            return ln
        return replace(ln, accepted=True, state=CONFIRMED)

    def _recheck(self, snap: Snapshot, held: LinkRecord) -> None:
        """Check a candidate again at its pose on the newer versions of its maps, of its
        epochs (:func:`agent.trust.recheck_verdict`: kept or dropped, confirmed only on a
        consistent cycle, :meth:`_confirmed_on_cycle`), with :func:`pgvd.verify.verify`
        (~0.05 s)."""
        a, b = held.pair
        (va, grid_a), (vb, grid_b) = snap.maps[a], snap.maps[b]
        clock = _Clock.start()
        self.counters.add("rechecks")
        why = "the pose left the check's basin"
        try:
            if self.check is None:  # an agent without checks cannot keep a candidate
                res, why = None, "no check to re-check it with"
            else:
                res = self.check(grid_a, grid_b, held.matrix)
        except Exception as exc:  # bad maps: the candidate cannot hold
            res, why = None, f"re-check failed: {exc}"
        if res is None:
            res = Registration(False, held.matrix, _REJECTED[1], 0.0, why)
        verdict = recheck_verdict(
            held.holds,
            held.margin,
            held.first_margin,
            res.accepted,
            res.margin,
            holds(held.matrix, res.matrix, grid_b),
            res.reason,
        )
        verdict = self._confirmed_on_cycle(snap, a, b, res, verdict)
        revision = held.revision + 1
        base = replace(held, version_a=va, version_b=vb, decided_by=self.me, revision=revision)
        self._record(base, res, verdict, "rechecked", clock)

    def _record(
        self, base: LinkRecord, res: Registration, verdict: Verdict, how: str, clock: _Clock
    ) -> None:
        """Log the decision, cache it and publish it if it is the link of its epochs; one
        the book refuses is kept as the pair's newest word if newer (:meth:`_previous`).

        ``base`` names the pair, its versions and its lifecycle so far; ``res`` and
        ``verdict`` give its new pose and state.  A pose without a sound covariance cannot
        enter the pose graph: such a link stays a candidate.
        """
        cov = res.covariance
        if verdict.state in IN_MAP and link_problem(replace(base, covariance=cov), base.pair):
            verdict = Verdict(CANDIDATE, f"no sound covariance: {verdict.reason}", verdict.holds)
        rec = replace(
            base,
            accepted=verdict.state in IN_MAP,
            matrix=res.matrix,
            covariance=cov,
            score=res.score,
            state=verdict.state,
            margin=res.margin,
            # a first decision's margin is the one its candidate's growth counts from
            first_margin=base.first_margin if base.revision else res.margin,
            reason=clean_reason(verdict.reason),
            holds=verdict.holds,
        )
        taken = self.book.add_link(rec)
        # "superseded": the book refused it (its epochs were replaced while it was decided);
        # an operator, or a bench reading the log, must not count it as the pair's state
        log.info(
            "%s how=%s seconds=%.2f book=%s",
            rec.logfmt(), how, clock.elapsed()[0], "taken" if taken else "superseded",
        )  # fmt: skip
        if taken:
            self.on_link(rec)
        elif rec.pair not in self._unheld or rec.key >= self._unheld[rec.pair].key:
            self._unheld[rec.pair] = rec

    def _carry_forward(self, a: str, va: int, b: str, vb: int, found: Registration) -> None:
        """Check a search's accepted transform on the maps that superseded its inputs
        meanwhile.

        While robots map, a search (seconds on a loaded machine) often ends after either
        map started a new epoch: its link is of no use any more, and the pair would be
        searched again from scratch.  The robots' pixel frames stay the same within a
        source's canvas, so the transform found is a prediction for the new maps as good
        as a chain's, and a check (tens of milliseconds) may confirm it.  Only a
        confirmation is taken; anything else leaves the pair to its next turn.  A search's
        provisional accept (below :data:`agent.trust.HIGH_BAR`) is not carried
        (:func:`agent.trust.carries`): a check from its own pose is no evidence for it.
        """
        held_a, held_b = self.book.map_of(a), self.book.map_of(b)
        if self.check is None or held_a is None or held_b is None:
            return
        if not carries(found.margin, self.min_margin):
            return
        (na, grid_a), (nb, grid_b) = held_a, held_b
        key = (a, epoch_of(na), b, epoch_of(nb))
        if key == (a, epoch_of(va), b, epoch_of(vb)) or key not in self.book.snapshot().needed:
            return  # not superseded, or decided already
        clock = _Clock.start()
        self.counters.add("checks")
        try:
            res = self.check(grid_a, grid_b, found.matrix)
        except Exception as exc:  # as in _register: the pair's next turn will search it
            log.warning("check of %s v%d / %s v%d failed: %s", a, na, b, nb, exc)
            return
        if res is None:
            return
        verdict = carried_verdict(res.accepted, res.margin, self.min_margin)
        if verdict is None:
            return
        self.counters.add("checks_confirmed")
        base = LinkRecord(a, na, b, nb, False, res.matrix, res.covariance, res.score, self.me)
        self._record(base, res, verdict, "carried forward", clock)

    def _gated(self, snap: Snapshot, a: str) -> Registration | None:
        """The merge's rejection of any pair whose map A is ``a``'s map held
        (:data:`GateFn`), without the search; None when a search must decide.

        The gate's verdict is kept per (robot, version): it reads one map, and a fleet asks
        it of each pair of that map.  Its reason names what the merge says and the map.
        """
        if self.gate is None:
            return None
        version, grid = snap.maps[a]
        held = {(r, v) for r, (v, _) in snap.maps.items()}
        self._gate_verdicts = {k: w for k, w in self._gate_verdicts.items() if k in held}
        if (a, version) not in self._gate_verdicts:
            self._gate_verdicts[(a, version)] = self.gate(grid)
        why = self._gate_verdicts[(a, version)]
        if why is None:
            return None
        self.counters.add("searches_gated")
        reason = f"{GATED}{why} ({a} v{version_text(version)})"
        return Registration(False, *_REJECTED, 0.0, reason)

    def _holding(self, snap: Snapshot, now: float) -> list[tuple[str, str]]:
        """The pairs whose gated rejection (:meth:`_gated`, any agent's) of their current
        epochs keeps later waves of searches closed: for :data:`GATE_HOLD_S` after this
        worker first saw it.

        A rejection for want of a map, unlike a search's, says nothing of the pair: were it
        to open the next wave, every pair of a fleet of small maps would be searched in
        turn (N(N-1)/2), each searched again as its maps grow.
        """
        if snap.generation is None or snap.generation != self._gated_links[0]:
            versions = {r: v for r, (v, _) in snap.maps.items()}
            found = {ln.identity: ln.pair for ln in snap.gated() if ln.current(versions)}
            self._gated_links = (snap.generation, found)
        gated = self._gated_links[1]
        self._held_since = {k: self._held_since.get(k, now) for k in gated}
        return [p for k, p in gated.items() if now - self._held_since[k] < GATE_HOLD_S]

    def _checkable(self, chains: Chains, a: str, b: str) -> bool:
        """Whether a check may decide ``(a, b)``: both poses known, or accepted links join
        them (:class:`Chains`)."""
        return (a in self.poses and b in self.poses) or chains.linked(a, b)

    def _at_prior(self, snap: Snapshot, a: str, b: str) -> Registration | None:
        """The link confirmed at the known poses' prior for ``(a, b)``, or None.

        None when a pose is unknown, and when the check does not confirm the prior: it
        neither accepts a wrong prior as it stands nor rejects the pair (the true link may be
        far from a wrong prior), so the chain's check or the full search decides.
        """
        if self.check is None:
            return None
        (_, grid_a), (_, grid_b) = snap.maps[a], snap.maps[b]
        prior = pair_prior(self.poses, a, grid_a, b, grid_b)
        if prior is None:
            return None
        self.counters.add("prior_checks")
        res = self.check(grid_a, grid_b, prior)
        if res is None or not res.accepted:
            self.counters.add("prior_failed")
            return None
        self.counters.add("prior_confirmed")
        return res

    def _checked(
        self, snap: Snapshot, a: str, b: str, fresh: bool = False
    ) -> Registration | _Unproven | None:
        """The check of the links' prediction for ``(a, b)``, or None: search instead.

        :class:`_Unproven`: the check rejected the pair, but that rejection may not stand
        without a search over these links (yet).  ``fresh``: predict from all the accepted
        links held, not from a recent solution (a deferred check waited for new links).
        """
        if self.check is None:
            return None
        solved = self._solved_for(snap, a, b, fresh)
        predicted = None if solved is None else predict(solved[0], a, b)
        if solved is None or predicted is None:
            why = "no accepted link joins them" if solved is None else "the placements part them"
            log.debug("no prediction for %s - %s: %s", a, b, why)
            return None
        res = self._apart(snap, a, b, predicted)
        if res is None:
            self.counters.add("checks")
            res = self.check(snap.maps[a][1], snap.maps[b][1], predicted)
            if res is None:
                log.debug("check %s - %s inconclusive: the pose left the basin", a, b)
        rejected = res is not None and not res.accepted
        if rejected and not _rejection_stands(
            self._current_groups(snap, solved[1]), snap.links, a, b
        ):
            # A recent solution may lack links that arrived meanwhile and put the pair on
            # triangles: those are worth a second check (~0.1 s with the solve) before a
            # search (seconds).
            if not fresh and self._solution[0] is not self._chains_of(snap):
                return self._checked(snap, a, b, fresh=True)
            return _Unproven()
        if res is not None and res.reason != APART:
            self.counters.add("checks_confirmed" if res.accepted else "checks_rejected")
        return res

    def _current_groups(self, snap: Snapshot, kept: list[LinkRecord]) -> Joins:
        """:func:`_joins` of the links ``kept`` of current epochs, made anew only when those
        changed: at 128 robots, some 6000 links, they take ~0.1 s, and a round of checks
        asks for them at every rejection."""
        pairs = _current_pairs(snap, kept)
        if self._joins[0] != pairs:
            self._joins = (pairs, _joins(pairs))
        return self._joins[1]

    def _apart(self, snap: Snapshot, a: str, b: str, predicted: np.ndarray) -> Registration | None:
        """The check's rejection without the check when ``predicted`` places the known cells
        of ``a`` and ``b`` farther apart than :data:`agent.footprints.MARGIN_M`
        (:mod:`agent.footprints`): no wall of either map lies on the other's known space, so
        the check could only find no overlap.  None when they come near: check them."""
        (va, grid_a), (vb, grid_b) = snap.maps[a], snap.maps[b]
        near = self._footprints.get(a, va, grid_a)
        if near.comes_near(self._footprints.get(b, vb, grid_b), predicted):
            return None
        self.counters.add("checks_skipped")
        log.debug("check %s - %s skipped: %s", a, b, APART)
        return Registration(False, np.asarray(predicted, np.float64), _REJECTED[1], 0.0, APART)

    def _chains_of(self, snap: Snapshot) -> Chains:
        """:class:`Chains` of ``snap``, made anew only when the robots or the accepted links
        changed: rejections and new minor versions leave the placements as they were."""
        signature = (
            tuple(sorted(snap.maps)),
            snap.accepted_ids,
        )
        held = self._chains
        if held[0] != signature or held[1] is None:
            accepted, sound = snap.accepted(), self._soundness(snap)
            # a snapshot not the book's may hold two links of a pair: built as given
            if held[1] is None or snap.generation is None:
                chains = Chains(snap.maps, list(accepted), sound)
            else:
                chains = held[1].grown(snap.maps, accepted, sound)
            held = self._chains = (signature, chains)
        return held[1]

    def _soundness(self, snap: Snapshot) -> Soundness:
        """The soundness memo of the link records of ``snap``, those of records no longer
        held dropped: it does not grow with every link ever seen."""
        # only accepted links are judged (:func:`agent.globalmap.usable_links`)
        held_now = {id(ln) for ln in snap.accepted()}
        self._sound = {k: v for k, v in self._sound.items() if k in held_now}
        return self._sound

    def _solved_for(
        self, snap: Snapshot, a: str, b: str, fresh: bool = False
    ) -> tuple[Solution, list[LinkRecord]] | None:
        """Placements that join ``a`` and ``b`` and the links they kept
        (:meth:`Chains.solved`); None at once when no accepted link joins them.

        In a round of checks nearly every registration adds an accepted link, and solving
        the pose graph anew for each (~0.1 s at 16 robots) cost as much as the checks.  The
        last solution serves for :data:`RESOLVE_AFTER` seconds while it joins the pair: a
        prediction is only where a check starts, and a link that arrived meanwhile enters
        the next solution.  ``fresh`` solves the links held now.
        """
        chains = self._chains_of(snap)
        if not chains.linked(a, b):
            return None
        used, at = self._solution
        recent = self._now - at < RESOLVE_AFTER
        if used is not None and used is not chains and recent and not fresh:
            held = used.solved()
            if predict(held[0], a, b) is not None:
                return held
        if used is not chains:
            self._solution = (chains, self._now)
        return chains.solved()

    def _rebuild(self, snap: Snapshot, settled: bool) -> None:
        """The global map of ``snap``, announced as ``settled`` or as a preview.

        A preview shows the placements of a round still in progress, and is fused without
        eq. (8)'s blur: each link of the round re-solves the pose graph and moves the
        placements' covariances (by a median 40 % in sigma at 16 robots), so nearly every
        preview blurred every map again, for a map the settled one replaces within the
        round.  Previews were 5 of each agent's 6 rebuilds at 16 robots, at about 0.5 s of
        CPU each.  The settled map is the paper's fusion, eqs. (8) and (33)-(37).
        """
        clock = _Clock.start()
        layers = self._layers
        warps = layers.warps
        components = build_components(
            snap.maps,
            snap.links,
            sound=self._soundness(snap),
            layers=layers,
            firsts=snap.firsts,
            blur=settled,
        )
        log.debug(
            "built %d components, %d maps warped: %.2f s, %.2f s CPU",
            len(components), layers.warps - warps, *clock.elapsed(),
        )  # fmt: skip
        self.on_global(GlobalState(components, settled, time.time()))
