"""Pairwise links: the cache, which pairs still need registering, and who registers them first.

The merge is deterministic, so the link of ``(a, version_a, b, version_b)`` computed by
any agent *is* the link of those versions: it is cached under that key, published, and
reused by everyone.  A robot bumps its map version only when its map changed enough
(:class:`agent.sources.ChangeGate`), so "new pair or changed map" is exactly "no link for
the latest versions yet".

To bound CPU on a small machine, one agent of the pair (:func:`first_registrar`) registers
it first; the other robot's agent steps in after ``timeout`` and any third agent after
twice that, in case the first went silent.
"""

from __future__ import annotations

import json
from collections.abc import Collection, Iterable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np

LinkKey = tuple[str, int, str, int]


@dataclass(frozen=True)
class LinkRecord:
    """A decided pair: ``matrix`` maps pixels of ``b``'s map to pixels of ``a``'s (a < b).

    ``covariance`` is 3x3 over (x px, y px, psi rad) as in ``pgvd merge --json``.
    A rejected pair (``accepted`` False) is recorded too, so nobody recomputes it.
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

    def __post_init__(self) -> None:
        if not self.a < self.b:
            raise ValueError(f"a link is stored with a < b, got {self.a!r}, {self.b!r}")
        for name in ("matrix", "covariance"):
            value = np.asarray(getattr(self, name), dtype=np.float64)
            if value.shape != (3, 3) or not np.isfinite(value).all():
                raise ValueError(f"link {name} must be a finite 3x3 matrix")
            object.__setattr__(self, name, value)
        if not np.isfinite(self.score):
            raise ValueError("link score must be finite")

    @property
    def key(self) -> LinkKey:
        return (self.a, self.version_a, self.b, self.version_b)

    @property
    def pair(self) -> tuple[str, str]:
        return (self.a, self.b)

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
            )
        except (KeyError, TypeError) as exc:
            raise ValueError(f"malformed link record: {exc}") from None


def ordered(r1: str, r2: str) -> tuple[str, str]:
    return (r1, r2) if r1 < r2 else (r2, r1)


class LinkCache:
    """Links by ``(a, version_a, b, version_b)``; old versions are pruned, never consulted."""

    def __init__(self, records: Iterable[LinkRecord] = ()) -> None:
        self._by_key: dict[LinkKey, LinkRecord] = {}
        for rec in records:
            self.add(rec)

    def add(self, rec: LinkRecord) -> bool:
        """Store ``rec``; True if it was not known (the first decision for a key stays)."""
        if rec.key in self._by_key:
            return False
        self._by_key[rec.key] = rec
        return True

    def get(self, key: LinkKey) -> LinkRecord | None:
        return self._by_key.get(key)

    def __len__(self) -> int:
        return len(self._by_key)

    def records(self) -> list[LinkRecord]:
        return sorted(self._by_key.values(), key=lambda r: r.key)

    def prune(self, versions: Mapping[str, int]) -> None:
        """Drop links of superseded versions, but keep per pair the newest of those.

        A link of versions not yet seen (it can arrive before the maps) is kept.  The
        newest superseded link stands in for the pair (:func:`select_links`) while the
        link of the latest versions is being computed.
        """
        keep: dict[LinkKey, LinkRecord] = {}
        newest: dict[tuple[str, str], LinkRecord] = {}
        for rec in self._by_key.values():
            if rec.version_a >= versions.get(rec.a, -1) and rec.version_b >= versions.get(
                rec.b, -1
            ):
                keep[rec.key] = rec
                continue
            old = newest.get(rec.pair)
            if old is None or (rec.version_a, rec.version_b) > (old.version_a, old.version_b):
                newest[rec.pair] = rec
        for rec in newest.values():
            keep.setdefault(rec.key, rec)
        self._by_key = keep


def needed_keys(versions: Mapping[str, int], cache: LinkCache) -> list[LinkKey]:
    """Keys of the latest versions of every pair of robots that no link covers yet."""
    robots = sorted(versions)
    keys = []
    for i, a in enumerate(robots):
        for b in robots[i + 1 :]:
            key = (a, versions[a], b, versions[b])
            if cache.get(key) is None:
                keys.append(key)
    return keys


def first_registrar(a: str, b: str, robots: Sequence[str]) -> str:
    """The robot whose agent registers the pair ``(a, b)`` first, among ``robots`` known.

    The robots, sorted, sit on a circle and each one takes its pairs with the next
    ``(n - 1) / 2`` robots clockwise (a balanced round-robin): every agent registers
    about half of its pairs, where "lower id first" would give robot 1 all of its
    ``n - 1``.  Agents that know different robot sets for a moment may disagree; the
    timeouts of :func:`wait_before_computing` cover that.
    """
    ring = sorted(set(robots) | {a, b})
    n = len(ring)
    i, j = ring.index(a), ring.index(b)
    d = (j - i) % n
    if 2 * d == n:  # opposite on an even circle: alternate
        return a if min(i, j) % 2 == 0 else b
    return a if 2 * d < n else b


def wait_before_computing(
    me: str,
    key: LinkKey,
    timeout: float,
    robots: Sequence[str] = (),
    alive: Collection[str] | None = None,
) -> float:
    """Seconds an agent waits for someone else's link before registering ``key`` itself.

    :func:`first_registrar` computes at once, the other robot of the pair after
    ``timeout``, anyone else after ``2 * timeout``: normally one registration per pair
    for the whole fleet.  With ``alive`` (the robots whose liveliness token is up), a
    robot that left hands its turn on at once: the other robot of the pair computes
    immediately, and if both left, anyone after ``timeout``.
    """
    a, _, b, _ = key
    first = first_registrar(a, b, robots)
    order = [first, b if first == a else a]
    if alive is not None:
        order = [r for r in order if r in alive] + [r for r in order if r not in alive]
    if me == order[0]:
        return 0.0
    if me in order:
        return timeout
    if alive is not None and not (set(order) & set(alive)):
        return timeout
    return 2.0 * timeout


def due_keys(
    me: str,
    keys: Iterable[LinkKey],
    first_needed: Mapping[LinkKey, float],
    now: float,
    timeout: float,
    robots: Sequence[str] = (),
    alive: Collection[str] | None = None,
) -> list[LinkKey]:
    """Of ``keys``, those this agent should register now, own pairs first, then by key."""
    due = [
        k
        for k in keys
        if now - first_needed.get(k, now) >= wait_before_computing(me, k, timeout, robots, alive)
    ]
    return sorted(due, key=lambda k: (me not in (k[0], k[2]), k))


def select_links(versions: Mapping[str, int], cache: LinkCache) -> tuple[list[LinkRecord], bool]:
    """The one link per pair the global map uses, and whether all are of the latest versions.

    The link of the latest versions when known; otherwise the newest older link of the
    pair stands in, and the result is not *settled*: agents agree on the global map only
    once every pair is settled (fleet invariant 2).
    """
    chosen: dict[tuple[str, str], LinkRecord] = {}
    settled = True
    for rec in cache.records():
        if rec.a not in versions or rec.b not in versions:
            continue
        exact = versions[rec.a] == rec.version_a and versions[rec.b] == rec.version_b
        old = chosen.get(rec.pair)
        if (
            exact
            or old is None
            or (
                not _is_exact(old, versions)
                and (rec.version_a, rec.version_b) > (old.version_a, old.version_b)
            )
        ):
            chosen[rec.pair] = rec
    robots = sorted(versions)
    for i, a in enumerate(robots):
        for b in robots[i + 1 :]:
            rec = chosen.get((a, b))
            if rec is None or not _is_exact(rec, versions):
                settled = False
    return [chosen[p] for p in sorted(chosen)], settled


def _is_exact(rec: LinkRecord, versions: Mapping[str, int]) -> bool:
    return versions.get(rec.a) == rec.version_a and versions.get(rec.b) == rec.version_b


def dumps(records: Iterable[LinkRecord]) -> str:
    return json.dumps([r.to_json() for r in records], indent=1)


def loads(text: str) -> list[LinkRecord]:
    """Records of :func:`dumps`; ``ValueError`` if the text is not such a list."""
    try:
        data = json.loads(text)
    except json.JSONDecodeError as exc:
        raise ValueError(f"links file is not JSON: {exc}") from None
    if not isinstance(data, list):
        raise ValueError("links file must hold a JSON list")
    return [LinkRecord.from_json(item) for item in data]
