"""The pieces of an agent's status JSON (:meth:`agent.node.FleetNode.status`).

``pgvd status`` reads it back through :mod:`agent.status_reply`; ``pgvd demo``, the fleet tests
and ``bench/`` read the ``status.json`` each agent writes.
"""

from __future__ import annotations

import weakref
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import TypeVar

import numpy as np

from agent.globalmap import Component
from agent.links import LinkRecord
from agent.trust import STATES
from pgvd.grid import heading

_Halves = tuple[dict[str, object], dict[str, object]]
_T = TypeVar("_T")


@dataclass(frozen=True)
class HostFacts:
    """What only the process that runs the core knows, for the status."""

    pid: int
    source: dict[str, object]
    merges: int
    merge_seconds: float
    inbox_messages: int
    inbox_bytes: int


def robots_json(
    me: str, versions: Mapping[str, int], alive: Mapping[str, bool]
) -> dict[str, dict[str, object]]:
    """Every robot known by its map or its liveliness: the version held and whether it is up."""
    robots: dict[str, dict[str, object]] = {
        r: {"version": v, "alive": r == me or alive.get(r, False)}
        for r, v in sorted(versions.items())
    }
    for r, up in alive.items():
        robots.setdefault(r, {"version": None, "alive": up})
    return robots


def link_json(rec: LinkRecord, versions: Mapping[str, int]) -> dict[str, object]:
    """A link as the status shows it, with its rotation in degrees."""
    head, tail = _record_json(rec)
    # False for a link of older epochs that stands in while the current one is computed.
    return {**head, "current": rec.current(versions), **tail}


#: ``id(record) -> (weak reference, its JSON halves)``: a record never changes, and every
#: status write shows every link held (about 120 at 16 robots, 190 writes per agent).
_RECORD_JSON: dict[int, tuple[weakref.ref[LinkRecord], _Halves]] = {}


def _record_json(rec: LinkRecord) -> _Halves:
    """What :func:`link_json` shows of ``rec`` before and after ``current``, made once per
    record while it lives."""
    key = id(rec)
    held = _RECORD_JSON.get(key)
    if held is not None and held[0]() is rec:
        return held[1]
    psi = float(np.degrees(heading(rec.matrix)))
    head = {
        "a": rec.a,
        "version_a": rec.version_a,
        "b": rec.b,
        "version_b": rec.version_b,
        "accepted": rec.accepted,
        "score": round(rec.score, 4),
        "rotation_deg": round(psi, 3),
        "matrix": rec.matrix.tolist(),
        "decided_by": rec.decided_by,
    }
    tail = {
        # the lifecycle (agent.trust): accepted and confirmed links enter the global map
        "state": rec.state,
        "margin": None if rec.margin is None else round(rec.margin, 4),
        "reason": rec.reason,
        "holds": rec.holds,
        "first_version_a": rec.first_a,
        "first_version_b": rec.first_b,
    }

    def forget(ref: weakref.ref[LinkRecord]) -> None:
        # Only this record's entry: its id may already name a newer record's.
        if _RECORD_JSON.get(key, (None,))[0] is ref:
            del _RECORD_JSON[key]

    _RECORD_JSON[key] = (weakref.ref(rec, forget), (head, tail))
    return head, tail


class _LastCall:
    """``view(records, versions)`` remembered for the last records (by identity, in order)
    and versions it was called with: between two status writes the links held mostly stay
    the same records, while the status is written every second and at every new global map.
    The result is shared between the calls that hit it, so it is never to be changed."""

    def __init__(self, view: Callable[[Sequence[LinkRecord], Mapping[str, int]], _T]) -> None:
        self._view = view
        self._last: tuple[list[LinkRecord], dict[str, int], _T] | None = None

    def __call__(self, records: Sequence[LinkRecord], versions: Mapping[str, int]) -> _T:
        last = self._last  # one read: another thread may replace it meanwhile
        if (
            last is not None
            and len(last[0]) == len(records)
            and all(a is b for a, b in zip(last[0], records, strict=True))
            and last[1] == versions
        ):
            return last[2]
        out = self._view(records, versions)
        self._last = (list(records), dict(versions), out)
        return out


def _links_json(
    records: Sequence[LinkRecord], versions: Mapping[str, int]
) -> list[dict[str, object]]:
    return [link_json(rec, versions) for rec in records]


#: ``[link_json(rec, versions) for rec in records]``, made anew only when they changed.
links_json = _LastCall(_links_json)


def _link_states(
    records: Sequence[LinkRecord], versions: Mapping[str, int]
) -> dict[str, list[str]]:
    out: dict[str, list[str]] = {state: [] for state in STATES}
    for rec in records:
        if rec.current(versions):
            out[rec.state].append(f"{rec.a}/{rec.b}")
    return out


#: The pairs, ``a/b``, of the links of the current epochs of ``versions`` by lifecycle state
#: (every state listed): an older epoch's link standing in is in ``links`` only.
link_states = _LastCall(_link_states)


def component_json(comp: Component) -> dict[str, object]:
    """A component of the global map, without its grid."""
    return {
        "anchor": comp.anchor,
        "members": list(comp.members),
        "versions": comp.versions,
        "used": [list(p) for p in comp.used],
        "rejected": [list(p) for p in comp.rejected],
        # each member's pixels -> the anchor's pixels: compared with the truth
        # (agent.evaluate) and between consecutive global maps (steadiness, bench.soak)
        "transforms": {r: np.round(m, 6).tolist() for r, m in sorted(comp.transforms.items())},
        "evidence": [list(e) for e in comp.evidence],
        "digest": comp.digest,
        "shape": list(comp.grid.shape),
        "unblurred": list(comp.unblurred),
    }


def global_json(own: Component | None) -> dict[str, object] | None:
    """This robot's global map in brief, None before the first rebuild that holds it."""
    if own is None:
        return None
    return {"anchor": own.anchor, "digest": own.digest, "members": list(own.members)}


def globalmap_line(own: Component) -> str:
    """A global map in one logfmt line: its anchor, robots, the links it used and those the
    pose graph dropped around a cycle, and the start of its digest."""
    used = ",".join(f"{a}/{b}" for a, b in own.used) or "none"
    dropped = ",".join(f"{a}/{b}" for a, b in own.rejected) or "none"
    return (
        f"globalmap anchor={own.anchor} robots={','.join(own.members)} links={used} "
        f"dropped={dropped} digest={own.digest[:12]}"
    )


def versions_of(components: Iterable[Component]) -> dict[str, int]:
    """``{robot: version}`` that went into ``components``."""
    return {r: v for c in components for r, v in c.versions.items()}
