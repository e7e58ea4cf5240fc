"""An agent's status reply as ``pgvd status`` trusts it: a fleet MAC, then a checked shape.

The reply is the status JSON (:meth:`agent.node.FleetNode.status`); in a keyed fleet its
HMAC-SHA256 under the fleet key (:func:`protocol.auth.seal`, as on every map message) rides as
the reply's Zenoh attachment, so that a tool without the key can still read the JSON while one
with the key refuses forgeries. Whoever answers under ``pgvd/<fleet>/status/*`` is a stranger
until then, so the JSON is checked field by field for what the table prints before anything
reads it.
"""

from __future__ import annotations

import hmac
import json
from collections.abc import Callable

from protocol.auth import seal

#: Replies larger than this are not parsed (a real status is a few kB per robot).
MAX_STATUS_BYTES = 4 << 20


def read_status(payload: bytes, attachment: bytes | None, key: bytes | None) -> dict:
    """The status in a reply; ``ValueError`` with one line on why it cannot be trusted."""
    if len(payload) > MAX_STATUS_BYTES:
        raise ValueError(f"reply of {len(payload)} bytes exceeds {MAX_STATUS_BYTES}")
    if key is not None:
        if attachment is None:
            raise ValueError("reply carries no fleet MAC")
        if not hmac.compare_digest(attachment, seal(payload, key)):
            raise ValueError("reply's fleet MAC is wrong")
    try:
        obj = json.loads(payload)
    except (ValueError, RecursionError):
        raise ValueError("reply is not JSON") from None
    return check_status(obj)


def _is_int(v: object) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def _is_num(v: object) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def _is_str(v: object) -> bool:
    return isinstance(v, str)


def _maybe(check: Callable[[object], bool]) -> Callable[[object], bool]:
    return lambda v: v is None or check(v)


def _require(obj: dict, where: str, fields: dict[str, Callable[[object], bool]]) -> None:
    for name, check in fields.items():
        if name in obj and not check(obj[name]):
            raise ValueError(f"{where}{name} has the wrong type")


_TOP = {
    "own_version": _maybe(_is_int),
    "settled": lambda v: isinstance(v, bool),
    "bytes_sent": _is_int,
    "bytes_received": _is_int,
    "merges": _is_int,
    "global": _maybe(lambda v: isinstance(v, dict)),
    "robots": lambda v: isinstance(v, dict),
    "links": lambda v: isinstance(v, list),
    "drops": lambda v: isinstance(v, dict),
    "source": lambda v: isinstance(v, dict),
}
_SOURCE = {"read_errors": _is_int, "last_error": _maybe(_is_str)}
_GLOBAL = {
    "digest": _is_str,
    "anchor": _is_str,
    "members": lambda v: isinstance(v, list) and all(map(_is_str, v)),
}
_ROBOT = {"version": _maybe(_is_int), "alive": lambda v: isinstance(v, bool)}
_LINK = {
    "a": _is_str,
    "b": _is_str,
    "decided_by": _is_str,
    "version_a": _is_int,
    "version_b": _is_int,
    "accepted": lambda v: isinstance(v, bool),
    "score": _is_num,
    "rotation_deg": _is_num,
}
#: A link's lifecycle (:mod:`agent.trust`): absent from the status of an older agent.
_LINK_LIFECYCLE = {
    "state": _is_str,
    "margin": _maybe(_is_num),
    "reason": _is_str,
    "holds": _is_int,
}


def check_status(obj: object) -> dict:
    """``obj`` if every field the status table reads has its type; else ``ValueError``.

    Missing fields are allowed (the table prints ``-``); present ones must be right, and each
    link must carry all of its fields.
    """
    if not isinstance(obj, dict):
        raise ValueError("status is not a JSON object")
    _require(obj, "", _TOP)
    _require(obj.get("global") or {}, "global.", _GLOBAL)
    _require(obj.get("source", {}), "source.", _SOURCE)
    for robot, entry in obj.get("robots", {}).items():
        if not isinstance(entry, dict):
            raise ValueError(f"robots.{robot[:64]} is not an object")
        _require(entry, f"robots.{robot[:64]}.", _ROBOT)
    for i, link in enumerate(obj.get("links", [])):
        if not isinstance(link, dict) or set(_LINK) - set(link):
            raise ValueError(f"links[{i}] lacks fields")
        _require(link, f"links[{i}].", _LINK)
        _require(link, f"links[{i}].", _LINK_LIFECYCLE)
    if not all(_is_str(k) and _is_int(v) for k, v in obj.get("drops", {}).items()):
        raise ValueError("drops must map reasons to counts")
    return obj
