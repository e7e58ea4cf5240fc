"""What a fetch asks a peer's ``latest`` queryable for: the whole map, or a few tiles of a version.

A receiver that holds a version's manifest but lost some of its tiles (best-effort tiles over a
lossy link) names them, so the answer costs those tiles and the manifest rather than the whole
map. The request travels as the query's selector parameters, ``v=<version>;tiles=<i>,<i>,...``;
no parameters asks for the whole latest version. The answering side is the one exposed to
strangers, so :func:`parse_fetch` bounds the text before it splits it and refuses anything that is
not exactly this form.
"""

from __future__ import annotations

from collections.abc import Collection
from dataclasses import dataclass

from protocol.errors import ProtocolError
from protocol.limits import Limits

#: Tiles one fetch may name; a receiver missing more asks for the whole map.
MAX_FETCH_TILES = 256
_MAX_VERSION = 2**63 - 1
#: No map a decoder accepts has more tiles (:class:`~protocol.limits.Limits`).
_MAX_TILES = Limits().max_tiles
_INDEX_DIGITS = len(str(_MAX_TILES - 1))


@dataclass(frozen=True)
class TileFetch:
    """Tiles ``indices`` of map version ``version`` of the queried robot."""

    version: int
    indices: frozenset[int]


def fetch_parameters(version: int, indices: Collection[int]) -> dict[str, str] | None:
    """Selector parameters naming ``indices`` of ``version``; None when the whole map is better.

    That is when ``indices`` is empty (nothing to name: the manifest itself is wanted) or
    longer than :data:`MAX_FETCH_TILES`.
    """
    if not indices or len(indices) > MAX_FETCH_TILES:
        return None
    return {"v": str(version), "tiles": ",".join(str(i) for i in sorted(indices))}


def parse_fetch(version: str | None, tiles: str | None) -> TileFetch | None:
    """The request in a query's ``v`` and ``tiles`` parameters; None asks for the whole map.

    Raises
    ------
    ProtocolError
        ``schema`` if only one of the two is given or either is not decimal digits and commas,
        ``limit`` if it names more than :data:`MAX_FETCH_TILES` tiles, ``value`` for a version
        beyond 63 bits, an index beyond ``Limits.max_tiles`` or a repeated index.
    """
    if version is None and tiles is None:
        return None
    if version is None or tiles is None:
        raise ProtocolError("a tile fetch needs both v and tiles", reason="schema")
    if len(tiles) > MAX_FETCH_TILES * (_INDEX_DIGITS + 1) or len(version) > 19:
        raise ProtocolError(f"tile fetch parameters of {len(tiles)} characters", reason="limit")
    if not version.isdecimal() or not version.isascii():
        raise ProtocolError(f"tile fetch version {version[:20]!r} is not a number", reason="schema")
    parts = tiles.split(",")
    if len(parts) > MAX_FETCH_TILES:
        raise ProtocolError(
            f"a fetch of {len(parts)} tiles exceeds the limit of {MAX_FETCH_TILES}", reason="limit"
        )
    if not all(p.isdecimal() and p.isascii() and len(p) <= _INDEX_DIGITS for p in parts):
        raise ProtocolError("tile fetch indices must be decimal numbers", reason="schema")
    indices = [int(p) for p in parts]
    if int(version) > _MAX_VERSION:
        raise ProtocolError(f"tile fetch version {version} exceeds 63 bits", reason="value")
    if max(indices) >= _MAX_TILES or len(set(indices)) != len(indices):
        raise ProtocolError("tile fetch indices out of range or repeated", reason="value")
    return TileFetch(int(version), frozenset(indices))
