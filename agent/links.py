"""Pairwise links: the cache, which pairs still need registering, and who registers them first.

A map version is ``epoch << 31 | minor`` (:func:`agent.book.next_version`).  The robot
that owns a map starts a new *registration epoch* when its map changed enough since the
epoch began (or its canvas moved); other versions only add detail in the same pixel
frame, so a link stays valid for every version of the epochs it was computed in.  Links
are therefore keyed by ``(a, epoch_a, b, epoch_b)``: "new pair or changed enough" is
exactly "no link for the current epochs yet", and a robot mapping continuously costs a
registration per epoch, not per version.

A pair whose best pose landed in the grey zone is a *candidate* (:mod:`agent.trust`): its
key is needed again at each new version of either map (:func:`stale_candidate`), and each
re-check is a record of the same key with newer versions and a higher ``revision``.

Two agents may register the same key (a timeout, a partition), possibly on different
minor versions; every agent keeps all candidates and uses the same one
(:meth:`LinkCache.get`: latest revision, then least ``decided_by``, then versions), so
agents that have seen the same links agree.

To bound CPU on a small machine, one agent of the pair (:func:`first_registrar`) registers
it first; the other robot's agent steps in after ``timeout`` and any third agent after
twice that, in case the first went silent.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Collection, Iterable, Mapping, Sequence
from dataclasses import dataclass
from functools import cached_property

import numpy as np

from agent import trust

#: ``(a, epoch_a, b, epoch_b)``.
LinkKey = tuple[str, int, str, int]
#: Bits of a version below its epoch.
EPOCH_SHIFT = 31


def epoch_of(version: int) -> int:
    """The registration epoch of a map version."""
    return int(version) >> EPOCH_SHIFT


def version_text(version: int) -> str:
    """A version as ``epoch.minor``, as the logs show it."""
    return f"{epoch_of(version)}.{int(version) & ((1 << EPOCH_SHIFT) - 1)}"


#: What a rejection the search gate gave without searching says first, on every agent
#: (:meth:`agent.worker.FusionWorker._gated`).
GATED = "not searched: "


@dataclass(frozen=True)
class LinkRecord:
    """A decided pair: ``matrix`` maps pixels of ``b``'s map to pixels of ``a``'s (a < b).

    ``covariance`` is 3x3 over (x px, y px, psi rad) as in ``pgvd merge --json``.
    A rejected pair (``accepted`` False) is recorded too, so nobody recomputes it, with its
    best pose (identity only when the decision found none), ``margin`` and ``reason``.

    The lifecycle (:mod:`agent.trust`): ``state`` is one of :data:`agent.trust.STATES`, and
    ``accepted`` is True exactly for the states that enter the global map.  ``first_a``,
    ``first_b`` are the versions the pair was first decided on in these epochs and
    ``first_margin`` that decision's margin, ``holds``
    how many re-checks a candidate's pose held, and ``revision`` how many times the pair
    was re-decided in these epochs: a later revision supersedes (:func:`preference`).
    """

    a: str
    version_a: int
    b: str
    version_b: int
    accepted: bool
    matrix: np.ndarray
    covariance: np.ndarray
    score: float
    decided_by: str
    state: str = ""
    margin: float | None = None
    first_margin: float | None = None
    reason: str = ""
    first_a: int = -1
    first_b: int = -1
    holds: int = 0
    revision: int = 0

    def __post_init__(self) -> None:
        if not self.a < self.b:
            raise ValueError(f"a link is stored with a < b, got {self.a!r}, {self.b!r}")
        if not self.state:  # a record of before the lifecycle: its outcome says it all
            object.__setattr__(self, "state", trust.ACCEPTED if self.accepted else trust.REJECTED)
        if self.state not in trust.STATES:
            raise ValueError(f"link state must be one of {trust.STATES}, got {self.state!r}")
        if bool(self.accepted) != (self.state in trust.IN_MAP):
            raise ValueError(f"a {self.state} link cannot have accepted={self.accepted}")
        for name in ("margin", "first_margin"):
            value = getattr(self, name)
            if value is not None and not np.isfinite(value):
                raise ValueError(f"link {name} must be finite or None")
        for name, version in (("first_a", self.version_a), ("first_b", self.version_b)):
            first = getattr(self, name)
            object.__setattr__(self, name, version if first < 0 else int(first))
            if getattr(self, name) > version:
                raise ValueError(f"link {name} is newer than the version decided on")
        if self.holds < 0 or self.revision < 0:
            raise ValueError("link holds and revision must be >= 0")
        for name in ("matrix", "covariance"):
            value = np.asarray(getattr(self, name), dtype=np.float64)
            if value.shape != (3, 3) or not np.isfinite(value).all():
                raise ValueError(f"link {name} must be a finite 3x3 matrix")
            object.__setattr__(self, name, value)
        if not np.isfinite(self.score):
            raise ValueError("link score must be finite")

    @cached_property
    def key(self) -> LinkKey:
        """The epochs this link is valid in (see the module docstring)."""
        return (self.a, epoch_of(self.version_a), self.b, epoch_of(self.version_b))

    @cached_property
    def rank(self) -> tuple[object, ...]:
        """:func:`preference` of this record, made once: a record never changes, and every
        agent ranks every link held at each step of its worker (the bytes of two matrices
        per link, 8000 links at 128 robots)."""
        return preference(self)

    @cached_property
    def identity(self) -> tuple[object, ...]:
        """What tells this candidate from any other of any key: its key, then its
        :attr:`rank`."""
        return (self.key, *self.rank)

    @cached_property
    def gated(self) -> bool:
        """Whether this is a rejection the search gate gave without searching (its reason
        says :data:`GATED`): for want of a map, which says nothing of the pair."""
        return not self.accepted and GATED in self.reason

    def current(self, versions: Mapping[str, int]) -> bool:
        """True if the link is of the epochs of ``versions`` (the latest maps)."""
        return (
            self.a in versions
            and self.b in versions
            and self.key == (self.a, epoch_of(versions[self.a]), self.b, epoch_of(versions[self.b]))
        )

    @property
    def pair(self) -> tuple[str, str]:
        return (self.a, self.b)

    def logfmt(self) -> str:
        """The decision as one logfmt line (``key=value``; quoted where it has spaces), for
        the agent's log: versions as ``epoch.minor``."""
        margin = "none" if self.margin is None else f"{self.margin:.2f}"
        reason = self.reason.replace("\\", "/").replace('"', "'")
        return (
            f"link pair={self.a}/{self.b} versions={version_text(self.version_a)}/"
            f"{version_text(self.version_b)} outcome={self.state} margin={margin} "
            f'holds={self.holds} by={self.decided_by} reason="{reason}"'
        )

    @cached_property
    def json_text(self) -> str:
        """:meth:`to_json` as one line of JSON, made once: a record never changes, and an
        agent rewrites its whole links file (:func:`dumps`) every status period while links
        arrive -- 120 of them at 16 robots, each encoded anew every second otherwise."""
        return json.dumps(self.to_json())

    def to_json(self) -> dict[str, object]:
        return {
            "a": self.a,
            "version_a": self.version_a,
            "b": self.b,
            "version_b": self.version_b,
            "accepted": self.accepted,
            "matrix": self.matrix.tolist(),
            "covariance": self.covariance.tolist(),
            "score": self.score,
            "decided_by": self.decided_by,
            "state": self.state,
            "margin": self.margin,
            "first_margin": self.first_margin,
            "reason": self.reason,
            "first_a": self.first_a,
            "first_b": self.first_b,
            "holds": self.holds,
            "revision": self.revision,
        }

    @classmethod
    def from_json(cls, obj: Mapping[str, object]) -> LinkRecord:
        """Inverse of :meth:`to_json`; raises ``ValueError`` on anything malformed."""
        try:
            return cls(
                a=str(obj["a"]),
                version_a=int(obj["version_a"]),  # type: ignore[arg-type]
                b=str(obj["b"]),
                version_b=int(obj["version_b"]),  # type: ignore[arg-type]
                accepted=bool(obj["accepted"]),
                matrix=np.asarray(obj["matrix"], dtype=np.float64),
                covariance=np.asarray(obj["covariance"], dtype=np.float64),
                score=float(obj["score"]),  # type: ignore[arg-type]
                decided_by=str(obj["decided_by"]),
                # absent from a links file of before the lifecycle: read as its outcome
                state=str(obj.get("state", "")),
                margin=None if obj.get("margin") is None else float(obj["margin"]),  # type: ignore[arg-type]
                first_margin=(
                    None if obj.get("first_margin") is None else float(obj["first_margin"])  # type: ignore[arg-type]
                ),
                reason=str(obj.get("reason", "")),
                first_a=int(obj.get("first_a", -1)),  # type: ignore[arg-type]
                first_b=int(obj.get("first_b", -1)),  # type: ignore[arg-type]
                holds=int(obj.get("holds", 0)),  # type: ignore[arg-type]
                revision=int(obj.get("revision", 0)),  # type: ignore[arg-type]
            )
        except (KeyError, TypeError) as exc:
            raise ValueError(f"malformed link record: {exc}") from None


def _bits(values: object) -> bytes:
    """Float64 bytes with -0.0 read as 0.0 (the wire drops the sign of a zero)."""
    return (np.asarray(values, dtype=np.float64) + 0.0).tobytes()


def preference(rec: LinkRecord) -> tuple[object, ...]:
    """The order in which the candidates of one key are preferred: the latest revision (a
    re-decision supersedes what it re-decided), who decided, on which versions, then the
    decision itself. The order is total, so that agents holding the same candidates use the
    same one whatever order they came in: one robot can decide a pair twice on the same
    versions (after a crash lost its links file, or after it was forgotten and came back)
    and reach another matrix the second time."""
    content = (not rec.accepted, _bits(rec.matrix), _bits(rec.covariance), _bits(rec.score))
    lifecycle = (rec.state, _bits(-1.0 if rec.margin is None else rec.margin), rec.holds)
    return (-rec.revision, rec.decided_by, rec.version_a, rec.version_b, *content, *lifecycle)


def _rank(rec: LinkRecord) -> tuple[object, ...]:
    return rec.rank


def _preferred(held: list[LinkRecord]) -> LinkRecord:
    """The candidate of ``held`` (one key's) that :func:`preference` puts first."""
    return held[0] if len(held) == 1 else min(held, key=_rank)


class LinkCache:
    """Links by ``(a, epoch_a, b, epoch_b)``, every candidate kept; old epochs are pruned.

    The keys are also indexed by pair, so that what one robot's new map or one new link
    changes is found without going over every link held (:meth:`used_for`).
    """

    def __init__(self, records: Iterable[LinkRecord] = ()) -> None:
        self._by_key: dict[LinkKey, list[LinkRecord]] = {}
        self._by_pair: dict[tuple[str, str], set[LinkKey]] = {}
        #: The robots each robot has a pair with in ``_by_pair``.
        self._partners: dict[str, set[str]] = {}
        for rec in records:
            self.add(rec)

    def add(self, rec: LinkRecord) -> bool:
        """Store ``rec``; True if it is the link now used for its key (it changed).

        Only the latest revision's records of a key are kept: an earlier one is never
        preferred again (:func:`preference`), and a candidate re-checked at every version
        would otherwise pile up its history in memory, the links file and every joiner's
        fetch.
        """
        held = self._by_key.setdefault(rec.key, [])
        latest = max((r.revision for r in held), default=rec.revision)
        if rec.revision < latest or any(r.rank == rec.rank for r in held):
            return False
        held[:] = [r for r in held if r.revision == rec.revision] + [rec]
        self._by_pair.setdefault(rec.pair, set()).add(rec.key)
        self._partners.setdefault(rec.a, set()).add(rec.b)
        self._partners.setdefault(rec.b, set()).add(rec.a)
        return _preferred(held) is rec

    def get(self, key: LinkKey) -> LinkRecord | None:
        """The link used for ``key``: the same on every agent that saw the same candidates."""
        held = self._by_key.get(key)
        return _preferred(held) if held else None

    def used_for(self, a: str, b: str, versions: Mapping[str, int]) -> LinkRecord | None:
        """The link :func:`select_links` uses for ``(a, b)`` (both in ``versions``): that of
        the current epochs when held, else that of the pair's newest epochs held."""
        current = self.get((a, epoch_of(versions[a]), b, epoch_of(versions[b])))
        if current is not None:
            return current
        keys = self._by_pair.get((a, b))
        return self.get(max(keys)) if keys else None

    def __len__(self) -> int:
        return len(self._by_key)

    def records(self) -> list[LinkRecord]:
        """The link used for each key, sorted by key."""
        return [self.get(k) for k in sorted(self._by_key)]  # type: ignore[misc]

    def candidates(self) -> list[LinkRecord]:
        """Every link held, for persistence and for peers' queries."""
        by_key = self._by_key
        return [r for k in sorted(by_key) for r in sorted(by_key[k], key=_rank)]

    def forget(self, robot: str) -> None:
        """Drop every link of ``robot``."""
        self._by_key = {k: v for k, v in self._by_key.items() if robot not in (k[0], k[2])}
        self._by_pair = {p: v for p, v in self._by_pair.items() if robot not in p}
        for other in self._partners.pop(robot, set()):
            self._partners[other].discard(robot)

    def prune(self, versions: Mapping[str, int], robot: str | None = None) -> None:
        """Drop links of superseded epochs, but keep per pair the newest of those.

        A link of epochs not yet seen (it can arrive before the maps) is kept.  The
        newest superseded link stands in for the pair (:func:`select_links`) while the
        link of the current epochs is being computed.  ``robot``: only its version changed
        since the last prune, so only its pairs are looked at.
        """
        epochs = {r: epoch_of(v) for r, v in versions.items()}
        if robot is None:
            pairs = list(self._by_pair)
        else:
            pairs = [(min(robot, r), max(robot, r)) for r in self._partners.get(robot, ())]
        for pair in pairs:
            self._prune_pair(pair, self._by_pair[pair], epochs)

    def _prune_pair(
        self, pair: tuple[str, str], keys: set[LinkKey], epochs: Mapping[str, int]
    ) -> None:
        """:meth:`prune` of one pair's ``keys``."""
        a, b = pair
        old = {k for k in keys if k[1] < epochs.get(a, -1) or k[3] < epochs.get(b, -1)}
        for key in old - {max(old, key=lambda k: (k[1], k[3]), default=None)}:
            keys.discard(key)
            del self._by_key[key]


def stale_candidate(rec: LinkRecord | None, versions: Mapping[str, int]) -> bool:
    """Whether ``rec`` is a candidate (:mod:`agent.trust`) decided on older versions than
    ``versions``: it is checked again at each new version of either map."""
    return (
        rec is not None
        and rec.state == trust.CANDIDATE
        and (rec.version_a, rec.version_b) != (versions.get(rec.a), versions.get(rec.b))
    )


def needed_key(a: str, b: str, versions: Mapping[str, int], cache: LinkCache) -> LinkKey | None:
    """The key of the current epochs of ``(a, b)`` (both in ``versions``) if no link covers
    it yet, or its link is a candidate of older versions (:func:`stale_candidate`)."""
    key = (a, epoch_of(versions[a]), b, epoch_of(versions[b]))
    held = cache.get(key)
    return key if held is None or stale_candidate(held, versions) else None


def needed_keys(versions: Mapping[str, int], cache: LinkCache) -> list[LinkKey]:
    """:func:`needed_key` of every pair of robots of ``versions``, sorted."""
    robots = sorted(versions)
    pairs = ((a, b) for i, a in enumerate(robots) for b in robots[i + 1 :])
    keys = (needed_key(a, b, versions, cache) for a, b in pairs)
    return [k for k in keys if k is not None]


class Ring:
    """The robots, sorted, on a circle (:func:`first_registrar`), placed once for many pairs.

    Every agent asks whose turn and which wave each pair still needed is at every step of
    its worker: sorting the robots anew for each pair cost O(n log n) per pair, O(n^3) per
    step.
    """

    def __init__(self, robots: Iterable[str]) -> None:
        self.robots = sorted(set(robots))
        self._at = {r: i for i, r in enumerate(self.robots)}

    def around(self, a: str, b: str) -> Ring:
        """This ring, or one with ``a`` and ``b`` added when it lacks either."""
        if a in self._at and b in self._at:
            return self
        return Ring([*self.robots, a, b])

    def first(self, a: str, b: str) -> str:
        """:func:`first_registrar` of ``(a, b)`` on this ring."""
        ring = self.around(a, b)
        n = len(ring.robots)
        i, j = ring._at[a], ring._at[b]
        d = (j - i) % n
        if 2 * d == n:  # opposite on an even circle: alternate
            return a if min(i, j) % 2 == 0 else b
        return a if 2 * d < n else b

    def distance(self, a: str, b: str) -> int:
        """:func:`ring_distance` of ``(a, b)`` on this ring."""
        ring = self.around(a, b)
        n = len(ring.robots)
        d = (ring._at[b] - ring._at[a]) % n
        return min(d, n - d)


def first_registrar(a: str, b: str, robots: Sequence[str]) -> str:
    """The robot whose agent registers the pair ``(a, b)`` first, among ``robots`` known.

    The robots, sorted, sit on a circle and each one takes its pairs with the next
    ``(n - 1) / 2`` robots clockwise (a balanced round-robin): every agent registers
    about half of its pairs, where "lower id first" would give robot 1 all of its
    ``n - 1``.  Agents that know different robot sets for a moment may disagree; the
    timeouts of :func:`wait_before_computing` cover that.
    """
    return Ring(robots).first(a, b)


def ring_distance(a: str, b: str, robots: Sequence[str]) -> int:
    """Steps between ``a`` and ``b`` on the circle of :func:`first_registrar`: 1 .. n // 2."""
    return Ring(robots).distance(a, b)


def open_keys(
    keys: Iterable[LinkKey],
    predicted: Collection[LinkKey],
    robots: Sequence[str],
    holding: Iterable[tuple[str, str]] = (),
) -> list[LinkKey]:
    """Of the needed ``keys``, those whose turn it is fleet-wide, the same rule on every agent.

    A key of ``predicted`` (a check may decide it: accepted links join its robots, or both
    their initial poses are known) is open at once.  The others need a full search, and go
    by *waves*: wave ``d`` is the pairs ``d`` steps apart on the circle of robots
    (:func:`ring_distance`), n pairs per wave of which every agent is
    :func:`first_registrar` of one.  Only the lowest wave still holding a key to search is
    open: the links it adds join components, and the pairs of a later wave whose robots
    they joined become checks instead of searches.  When the first wave's pairs overlap, a
    fleet of n robots searches n pairs and checks the rest, not n(n-1)/2 searches.  Every
    wave opens in turn while keys to search remain, so a pair no link reaches is searched
    in the end.

    ``holding``: pairs decided without a search (their map was too small to search) that
    keep later waves closed as if still to search: a wave opens on what searches found.
    """
    keys = list(keys)
    ring = Ring(robots)
    waves = {k: ring.distance(k[0], k[2]) for k in keys if k not in predicted}
    held = [ring.distance(a, b) for a, b in holding]
    first = min([*waves.values(), *held], default=None)
    return [k for k in keys if k in predicted or waves[k] == first]


class Waves:
    """:func:`open_keys` of one agent, kept from one call to the next: only the keys whose
    robots' epochs, groups or re-check changed are looked at again.

    A worker asks for the keys open at every change of its book (each map version, each
    link record, O(N) of them per epoch), and at 64 robots some thousands of keys are
    needed: going over them all each time grew like N^3 per agent and epoch.  The answer is
    :func:`open_keys` of the same arguments, in the same order (the needed keys' order, by
    pair), whatever the calls before.
    """

    def __init__(self) -> None:
        self._reset(None)

    def _reset(self, robots: Sequence[str] | None) -> None:
        """Nothing placed, on the circle of ``robots`` (None: none yet)."""
        #: The robots of the circle the waves are placed on.
        self._robots = None if robots is None else tuple(robots)
        self._ring = Ring(robots or ())
        self._needed: set[LinkKey] = set()
        self._rechecks: frozenset[LinkKey] = frozenset()
        #: The needed keys of each robot (both of a pair's).
        self._by_robot: dict[str, set[LinkKey]] = {}
        #: The needed keys a check may decide, and the others by wave.
        self._checkable: set[LinkKey] = set()
        self._by_wave: dict[int, set[LinkKey]] = {}
        #: The wave of each needed key not in ``_checkable``.
        self._wave_of: dict[LinkKey, int] = {}

    def update(
        self,
        needed: Collection[LinkKey],
        rechecks: frozenset[LinkKey],
        robots: Sequence[str],
        holding: Iterable[tuple[str, str]],
        joined: Callable[[str, str], bool],
        regrouped: Collection[str] | None,
    ) -> tuple[set[LinkKey], list[LinkKey]]:
        """The keys of ``needed`` a check may decide (those of ``rechecks``, and those whose
        robots ``joined`` says a check may decide), and :func:`open_keys` of ``needed``.

        ``regrouped``: the robots for which ``joined`` may answer otherwise than at the last
        call (their group changed); None: any.
        """
        now = set(needed)
        if regrouped is None or tuple(robots) != self._robots:
            self._reset(robots)
            dirty = now
        else:
            for key in self._needed - now:
                self._drop(key)
            dirty = now - self._needed
            for robot in regrouped:
                dirty |= self._by_robot.get(robot, set())
            dirty |= (rechecks ^ self._rechecks) & now
        for key in dirty:
            self._place(key, key in rechecks or joined(key[0], key[2]))
        self._needed, self._rechecks = now, rechecks
        held = [self._ring.distance(a, b) for a, b in holding]
        first = min([*self._by_wave, *held], default=None)
        opened = self._checkable | self._by_wave.get(first, set())  # type: ignore[arg-type]
        return set(self._checkable), sorted(opened)

    def _place(self, key: LinkKey, checkable: bool) -> None:
        """File the needed ``key`` as checkable or in its wave."""
        if key in (self._checkable if checkable else self._wave_of):
            return  # filed so already: the common case of a regrouped robot's keys
        self._unplace(key)
        a, _, b, _ = key
        self._by_robot.setdefault(a, set()).add(key)
        self._by_robot.setdefault(b, set()).add(key)
        if checkable:
            self._checkable.add(key)
        else:
            wave = self._wave_of[key] = self._ring.distance(a, b)
            self._by_wave.setdefault(wave, set()).add(key)

    def _unplace(self, key: LinkKey) -> None:
        """Take ``key`` out of the checkable keys or its wave."""
        self._checkable.discard(key)
        wave = self._wave_of.pop(key, None)
        if wave is not None:
            keys = self._by_wave[wave]
            keys.discard(key)
            if not keys:
                del self._by_wave[wave]

    def _drop(self, key: LinkKey) -> None:
        """Forget ``key``, needed no more."""
        self._unplace(key)
        for robot in (key[0], key[2]):
            keys = self._by_robot[robot]
            keys.discard(key)
            if not keys:
                del self._by_robot[robot]


def wait_before_computing(
    me: str,
    key: LinkKey,
    timeout: float,
    robots: Sequence[str] | Ring = (),
    alive: Collection[str] | None = None,
) -> float:
    """Seconds an agent waits for someone else's link before registering ``key`` itself.

    :func:`first_registrar` computes at once, the other robot of the pair after
    ``timeout``, anyone else after ``2 * timeout``: normally one registration per pair
    for the whole fleet.  With ``alive`` (the robots whose liveliness token is up), a
    robot that left hands its turn on at once: the other robot of the pair computes
    immediately, and if both left, anyone after ``timeout``.  ``robots`` may be a
    :class:`Ring` already placed, for many keys.
    """
    a, _, b, _ = key
    ring = robots if isinstance(robots, Ring) else Ring(robots)
    first = ring.first(a, b)
    order = [first, b if first == a else a]
    if alive is not None:
        order = [r for r in order if r in alive] + [r for r in order if r not in alive]
    if me == order[0]:
        return 0.0
    if me in order:
        return timeout
    if alive is not None and not any(r in alive for r in order):
        return timeout
    return 2.0 * timeout


class Turns:
    """Which open keys one agent should register now (:meth:`due`), each key's wait
    (:func:`wait_before_computing`) kept while the circle of robots, the robots alive and
    the timeout stay as they were.

    A worker asks at every step, and at 64 robots about a hundred keys are open at each:
    their waits, worked out again each time, were a tenth of a worker's CPU.
    """

    def __init__(self) -> None:
        self._basis: tuple[object, ...] | None = None
        self._ring = Ring(())
        self._waits: dict[LinkKey, float] = {}

    def due(
        self,
        me: str,
        keys: Iterable[LinkKey],
        opened_at: Mapping[LinkKey, float],
        now: float,
        timeout: float,
        robots: Sequence[str] = (),
        alive: Collection[str] | None = None,
    ) -> list[LinkKey]:
        """Of ``keys``, those agent ``me`` should register now, own pairs first, then by
        key.

        ``opened_at`` says since when each key has been open (:func:`open_keys`): the waits
        of :func:`wait_before_computing` count from then.
        """
        keys = list(keys)
        basis = (me, tuple(robots), None if alive is None else frozenset(alive), timeout)
        if basis != self._basis:
            self._basis, self._ring, self._waits = basis, Ring(robots), {}
        elif len(self._waits) > 2 * len(keys) + 64:  # waits of keys long closed
            self._waits = {}
        waits = self._waits
        # no wait is longer: a key open that long is due whoever registers it first
        longest = max(0.0, timeout, 2.0 * timeout)
        due = []
        for k in keys:
            waited = now - opened_at.get(k, now)
            if waited >= longest:
                due.append(k)
                continue
            wait = waits.get(k)
            if wait is None:
                wait = waits[k] = wait_before_computing(me, k, timeout, self._ring, alive)
            if waited >= wait:
                due.append(k)
        return sorted(due, key=lambda k: (me not in (k[0], k[2]), k))


def select_links(versions: Mapping[str, int], cache: LinkCache) -> tuple[list[LinkRecord], bool]:
    """The one link per pair the global map uses, and whether all are of the current epochs.

    The link of the current epochs when known; otherwise the newest older link of the
    pair stands in (:meth:`LinkCache.used_for`), and the result is not *settled*: agents
    agree on the global map only once every pair is settled (fleet invariant 2).
    """
    robots = sorted(versions)
    used = (cache.used_for(a, b, versions) for i, a in enumerate(robots) for b in robots[i + 1 :])
    chosen = [rec for rec in used if rec is not None]
    n = len(robots)
    settled = len(chosen) == n * (n - 1) // 2 and all(rec.current(versions) for rec in chosen)
    return chosen, settled


def dumps(records: Iterable[LinkRecord]) -> str:
    """A JSON list of the records, one per line (:func:`loads` reads it back)."""
    return "[\n" + ",\n".join(r.json_text for r in records) + "\n]\n"


def loads(text: str) -> list[LinkRecord]:
    """Records of :func:`dumps`; ``ValueError`` if the text is not such a list."""
    try:
        data = json.loads(text)
    except json.JSONDecodeError as exc:
        raise ValueError(f"links file is not JSON: {exc}") from None
    if not isinstance(data, list):
        raise ValueError("links file must hold a JSON list")
    return [LinkRecord.from_json(item) for item in data]
