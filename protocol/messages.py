"""The typed messages of the wire format: immutable, validated on construction.

Every message names its ``fleet`` and the robot that sent it.  Versions and
sequence numbers are non-negative and only move forward per robot, which is
what :class:`protocol.auth.ReplayGuard` enforces.  Constructors raise
:class:`~protocol.errors.ProtocolError`, so a decoder that builds a message
from untrusted fields needs no second validation pass.
"""

from __future__ import annotations

import math
import re
from collections.abc import Mapping
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Union

import numpy as np

from protocol.errors import ProtocolError

#: Ids travel inside Zenoh key expressions, so they exclude ``/ * $ # ?`` and spaces.
ID_PATTERN = re.compile(r"[A-Za-z0-9][A-Za-z0-9_-]*")
#: Hard cap on id length; :class:`protocol.limits.Limits` may lower it.
MAX_ID_LENGTH = 64
#: Versions fit a signed 64-bit integer (msgpack int64, numpy int64).
MAX_VERSION = 2**63 - 1
#: Tile sides allowed: small enough that one encoded tile stays well under 64 KB.
TILE_SIZES = (16, 32, 64, 128, 256)
#: The default tile side: 128 x 128 int8 = 16 KiB before compression.
DEFAULT_TILE_SIZE = 128
#: A first epoch is the high part of a version below 2**63 whose low 31 bits are the minor.
FIRST_EPOCH_BITS = 32


def check_id(value: object, what: str) -> str:
    """Return ``value`` if it is a valid fleet/robot id, else raise ProtocolError."""
    if not isinstance(value, str):
        raise ProtocolError(f"{what} must be a string, got {type(value).__name__}", reason="schema")
    if not 0 < len(value) <= MAX_ID_LENGTH:
        raise ProtocolError(
            f"{what} must have 1..{MAX_ID_LENGTH} characters, got {len(value)}",
            reason="limit" if value else "value",
        )
    if not ID_PATTERN.fullmatch(value):
        raise ProtocolError(
            f"{what} {value!r} has characters outside [A-Za-z0-9_-]", reason="value"
        )
    return value


def check_version(value: object, what: str) -> int:
    """Return ``value`` if it is an int in ``[0, 2**63)`` (bools refused), else raise."""
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        raise ProtocolError(
            f"{what} must be an integer, got {type(value).__name__}", reason="schema"
        )
    if not 0 <= value <= MAX_VERSION:
        raise ProtocolError(f"{what} must be in [0, 2**63), got {value}", reason="value")
    return int(value)


def check_float(value: object, what: str) -> float:
    """Return ``value`` as a finite float (ints accepted, bools and NaN/inf refused)."""
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise ProtocolError(f"{what} must be a number, got {type(value).__name__}", reason="schema")
    out = float(value)
    if not math.isfinite(out):
        raise ProtocolError(f"{what} must be finite, got {out}", reason="value")
    return out


def check_matrix(value: object, what: str) -> tuple[tuple[float, float, float], ...]:
    """Return a 3x3 matrix of finite floats as a tuple of row tuples."""
    try:
        arr = np.asarray(value, dtype=object)
    except Exception as exc:  # ragged input makes numpy raise ValueError
        raise ProtocolError(f"{what} must be a 3x3 matrix", reason="schema") from exc
    if arr.shape != (3, 3):
        raise ProtocolError(f"{what} must be 3x3, got shape {arr.shape}", reason="schema")
    return tuple(
        tuple(check_float(arr[i, j], f"{what}[{i}][{j}]") for j in range(3)) for i in range(3)
    )  # type: ignore[return-value]


@dataclass(frozen=True)
class Geometry:
    """Where a grid lives and how it is cut into tiles.

    Attributes
    ----------
    shape : ``(H, W)`` cells, row 0 at the top of the image (pgvd.grid).
    resolution : metres per cell, finite and > 0.
    origin : ``(x, y, yaw)`` of the lower-left cell corner, ROS convention.
    tile_size : side of the square tiles, one of :data:`TILE_SIZES`; tiles of
        the last row/column are cropped to the grid.
    """

    shape: tuple[int, int]
    resolution: float
    origin: tuple[float, float, float] = (0.0, 0.0, 0.0)
    tile_size: int = DEFAULT_TILE_SIZE

    def __post_init__(self) -> None:
        if not isinstance(self.shape, (tuple, list)) or len(self.shape) != 2:
            raise ProtocolError(f"shape must be (H, W), got {self.shape!r}", reason="schema")
        h = check_version(self.shape[0], "shape[0]")
        w = check_version(self.shape[1], "shape[1]")
        if h == 0 or w == 0:
            raise ProtocolError(f"shape must be positive, got ({h}, {w})", reason="value")
        res = check_float(self.resolution, "resolution")
        if res <= 0:
            raise ProtocolError(f"resolution must be > 0, got {res}", reason="value")
        if not isinstance(self.origin, (tuple, list)) or len(self.origin) != 3:
            raise ProtocolError(f"origin must be (x, y, yaw), got {self.origin!r}", reason="schema")
        origin = tuple(check_float(v, f"origin[{i}]") for i, v in enumerate(self.origin))
        if isinstance(self.tile_size, bool) or self.tile_size not in TILE_SIZES:
            raise ProtocolError(
                f"tile_size must be one of {TILE_SIZES}, got {self.tile_size!r}", reason="value"
            )
        object.__setattr__(self, "shape", (h, w))
        object.__setattr__(self, "resolution", res)
        object.__setattr__(self, "origin", origin)
        object.__setattr__(self, "tile_size", int(self.tile_size))

    @property
    def tile_grid(self) -> tuple[int, int]:
        """Tiles per column and per row: ``(ceil(H / t), ceil(W / t))``."""
        t = self.tile_size
        return -(-self.shape[0] // t), -(-self.shape[1] // t)

    @property
    def n_tiles(self) -> int:
        """Number of tiles; tile indices run row-major over :attr:`tile_grid`."""
        rows, cols = self.tile_grid
        return rows * cols

    def tile_window(self, index: int) -> tuple[slice, slice]:
        """Row and column slices of tile ``index`` in the full grid."""
        if not 0 <= index < self.n_tiles:
            raise ProtocolError(f"tile index {index} outside [0, {self.n_tiles})", reason="value")
        t = self.tile_size
        r, c = divmod(index, self.tile_grid[1])
        return slice(r * t, min((r + 1) * t, self.shape[0])), slice(
            c * t, min((c + 1) * t, self.shape[1])
        )

    def tile_shape(self, index: int) -> tuple[int, int]:
        """``(rows, cols)`` of tile ``index``: full tiles except at the bottom/right edge."""
        rs, cs = self.tile_window(index)
        return rs.stop - rs.start, cs.stop - cs.start


@dataclass(frozen=True, eq=False)
class Tile:
    """One tile of a quantised grid (int8 steps of :data:`protocol.quantize.SCALE`).

    Attributes
    ----------
    index : row-major tile index in the geometry's :attr:`Geometry.tile_grid`.
    checksum : CRC-32 of the tile's full int8 content once applied (row-major bytes).
    cells : int8 array of the tile's shape; the full content when
        ``base_checksum`` is None, else the wrapping int8 difference to the base.
    base_checksum : CRC-32 of the content ``cells`` is a difference against,
        or None for a self-contained tile.
    """

    index: int
    checksum: int
    cells: np.ndarray
    base_checksum: int | None = None

    def __post_init__(self) -> None:
        check_version(self.index, "tile index")
        check_crc(self.checksum, "tile checksum")
        if self.base_checksum is not None:
            check_crc(self.base_checksum, "tile base checksum")
        if not isinstance(self.cells, np.ndarray) or self.cells.dtype != np.int8:
            raise ProtocolError(f"tile {self.index} cells must be an int8 array", reason="schema")
        if self.cells.ndim != 2:
            raise ProtocolError(
                f"tile {self.index} cells must be 2-D, got {self.cells.shape}", reason="schema"
            )
        cells = np.ascontiguousarray(self.cells)
        if cells.flags.writeable:
            cells = cells.copy()  # freeze a private copy, never the caller's array
        cells.flags.writeable = False
        object.__setattr__(self, "cells", cells)

    @property
    def is_delta(self) -> bool:
        """True when :attr:`cells` is a difference against :attr:`base_checksum`."""
        return self.base_checksum is not None


def check_unsigned(value: object, what: str, bits: int) -> int:
    """Return ``value`` as an int if it is an unsigned ``bits``-bit integer, else raise.

    Bools are refused although Python counts them as ints: no field of the
    wire format means a flag where it says a number.
    """
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        raise ProtocolError(
            f"{what} must be an integer, got {type(value).__name__}", reason="schema"
        )
    out = int(value)  # a plain int whatever came in: numpy scalars wrap, ints do not
    if not 0 <= out < 2**bits:
        raise ProtocolError(
            f"{what} must be a {bits}-bit unsigned integer, got {out}", reason="value"
        )
    return out


def check_crc(value: object, what: str) -> int:
    """Return ``value`` if it is an unsigned 32-bit integer (a CRC-32), else raise."""
    return check_unsigned(value, what, 32)


def _check_map_header(
    fleet: str, robot: str, version: int, geometry: Geometry, base_version: int | None
) -> None:
    """The fields a map's tiles and its manifest share; a delta's base must be older."""
    check_id(fleet, "fleet")
    check_id(robot, "robot")
    check_version(version, "version")
    if not isinstance(geometry, Geometry):
        raise ProtocolError("geometry must be a Geometry", reason="schema")
    if base_version is not None:
        check_version(base_version, "base_version")
        if base_version >= version:
            raise ProtocolError(
                f"base_version {base_version} must be older than version {version}", reason="value"
            )


@dataclass(frozen=True, eq=False)
class MapTiles:
    """Some tiles of one version of a robot's own local map.

    ``base_version`` names the version a delta was computed against (None for a
    full update); it is informational, because each delta tile names the exact
    content it applies to by :attr:`Tile.base_checksum`.
    """

    fleet: str
    robot: str
    version: int
    geometry: Geometry
    tiles: tuple[Tile, ...]
    base_version: int | None = None

    def __post_init__(self) -> None:
        _check_map_header(self.fleet, self.robot, self.version, self.geometry, self.base_version)
        tiles = tuple(self.tiles)
        if not tiles:
            raise ProtocolError("a MapTiles message must carry at least one tile", reason="schema")
        seen: set[int] = set()
        for tile in tiles:
            if not isinstance(tile, Tile):
                raise ProtocolError("tiles must be Tile objects", reason="schema")
            if tile.index in seen:
                raise ProtocolError(f"tile {tile.index} appears twice", reason="value")
            seen.add(tile.index)
            expected = self.geometry.tile_shape(tile.index)
            if tile.cells.shape != expected:
                raise ProtocolError(
                    f"tile {tile.index} has shape {tile.cells.shape}, geometry says {expected}",
                    reason="value",
                )
        object.__setattr__(self, "tiles", tiles)


@dataclass(frozen=True)
class Manifest:
    """What one version of a robot's map consists of: one checksum per tile that holds knowledge.

    A full manifest (``base_version`` None) lists every tile that holds
    knowledge; tiles not listed are entirely unknown (all zero).  A receiver
    compares these checksums with the tiles it holds to know which it lacks.

    A delta manifest lists only the tiles that differ from ``base_version``
    (a tile that lost all knowledge is listed with the checksum of an all-zero
    tile), plus ``digest``, the :func:`protocol.tiles.manifest_digest` of the
    full list, so a receiver holding ``base_version`` rebuilds and verifies the
    full manifest while the bytes stay proportional to the change, not the map.

    ``first_epoch`` is the registration epoch of the robot's first map version (the
    high part of a version, ``version >> 31`` for an agent's versions): the robot's age,
    which every receiver needs alike to anchor a merged frame at its oldest robot.  An
    unsigned 32-bit integer, or None for a manifest that does not say.

    ``final`` marks the robot's last map version (a replay's last map, a saved map): no
    newer version of its map will come, so a receiver need not wait for one before it
    trusts a decision on it.  False for a manifest that does not say.
    """

    fleet: str
    robot: str
    version: int
    geometry: Geometry
    checksums: Mapping[int, int] = field(default_factory=dict)
    base_version: int | None = None
    digest: int | None = None
    first_epoch: int | None = None
    final: bool = False

    def __post_init__(self) -> None:
        _check_map_header(self.fleet, self.robot, self.version, self.geometry, self.base_version)
        if (self.base_version is None) != (self.digest is None):
            raise ProtocolError(
                "a delta manifest needs both base_version and digest", reason="schema"
            )
        if self.digest is not None:
            object.__setattr__(self, "digest", check_unsigned(self.digest, "digest", 64))
        if self.first_epoch is not None:
            first = check_unsigned(self.first_epoch, "first_epoch", FIRST_EPOCH_BITS)
            object.__setattr__(self, "first_epoch", first)
        if not isinstance(self.final, bool):
            raise ProtocolError(
                f"final must be a bool, got {type(self.final).__name__}", reason="schema"
            )
        if not isinstance(self.checksums, Mapping):
            raise ProtocolError("checksums must map tile index -> checksum", reason="schema")
        clean = _plain_checksums(self.checksums, self.geometry.n_tiles)
        if clean is None:
            clean = _checked_checksums(self.checksums, self.geometry.n_tiles)
        object.__setattr__(self, "checksums", MappingProxyType(clean))

    @property
    def is_delta(self) -> bool:
        """True when only the tiles changed since :attr:`base_version` are listed."""
        return self.base_version is not None

    def _key(self) -> tuple:
        return (
            self.fleet, self.robot, self.version, self.geometry, dict(self.checksums),
            self.base_version, self.digest, self.first_epoch, self.final,
        )  # fmt: skip

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Manifest):
            return NotImplemented
        return self._key() == other._key()

    __hash__ = None  # type: ignore[assignment]


def _plain_checksums(checksums: Mapping[int, int], n: int) -> dict[int, int] | None:
    """``checksums`` sorted by tile, if every index and checksum is a plain ``int`` in range
    (a decoded manifest's always are: checked in bulk, ~10x faster per tile), else None."""
    if not checksums:
        return {}
    indices, crcs = list(checksums), list(checksums.values())
    if not all(type(v) is int for v in (*indices, *crcs)):  # bools and numpy ints go the slow way
        return None
    if min(indices) < 0 or max(indices) >= n or min(crcs) < 0 or max(crcs) > 0xFFFFFFFF:
        return None
    return dict(sorted(zip(indices, crcs, strict=True)))


def _checked_checksums(checksums: Mapping[object, object], n: int) -> dict[int, int]:
    """``checksums`` sorted by tile, each index and checksum checked on its own: the first
    that is wrong raises its precise error."""
    clean: dict[int, int] = {}
    for index in sorted(checksums):  # type: ignore[type-var]
        i = check_version(index, "manifest tile index")
        if i >= n:
            raise ProtocolError(f"manifest tile index {i} outside [0, {n})", reason="value")
        clean[i] = check_crc(checksums[index], f"checksum of tile {i}")
    return clean


#: The states of a link's lifecycle; ``accepted`` is True exactly for those of
#: :data:`LINK_IN_MAP` (the agent's ``agent.trust`` says what each means).
LINK_STATES = ("accepted", "candidate", "confirmed", "rejected", "withdrawn")
LINK_IN_MAP = ("accepted", "confirmed")
#: Longest reason a link carries, in characters (a merge's reason is under 200).
MAX_REASON_LENGTH = 400
#: Most re-decisions (and holds) one link may count within its epochs.
MAX_REVISION = 2**32 - 1


@dataclass(frozen=True)
class LinkTrust:
    """Where a link stands in its lifecycle, carried so every agent reads the same state.

    Attributes
    ----------
    state : one of :data:`LINK_STATES`.
    margin : the acceptance statistic at the link's pose, None when none was scored.
    first_margin : the margin of the pair's first decision in these epochs, None likewise.
    reason : why, in words (printable, at most :data:`MAX_REASON_LENGTH` characters).
    first_version_a, first_version_b : the versions the pair was first decided on in these
        epochs: no newer than the link's own.
    holds : re-checks on which a candidate's pose held.
    revision : re-decisions of the pair in these epochs; a later one supersedes.
    """

    state: str
    margin: float | None
    first_margin: float | None
    reason: str
    first_version_a: int
    first_version_b: int
    holds: int
    revision: int

    def __post_init__(self) -> None:
        if not isinstance(self.state, str) or self.state not in LINK_STATES:
            raise ProtocolError(
                f"link state must be one of {LINK_STATES}, got {self.state!r}", reason="value"
            )
        for name in ("margin", "first_margin"):
            value = getattr(self, name)
            if value is not None:
                object.__setattr__(self, name, check_float(value, name))
        if not isinstance(self.reason, str):
            raise ProtocolError("link reason must be a string", reason="schema")
        if len(self.reason) > MAX_REASON_LENGTH:
            raise ProtocolError(
                f"link reason of {len(self.reason)} characters exceeds {MAX_REASON_LENGTH}",
                reason="limit",
            )
        if not self.reason.isprintable():
            raise ProtocolError("link reason has unprintable characters", reason="value")
        check_version(self.first_version_a, "first_version_a")
        check_version(self.first_version_b, "first_version_b")
        for name in ("holds", "revision"):
            value = check_version(getattr(self, name), name)
            if value > MAX_REVISION:
                why = f"{name} must be <= {MAX_REVISION}, got {value}"
                raise ProtocolError(why, reason="value")


@dataclass(frozen=True)
class Link:
    """A pairwise transform between two robots' map versions, accepted or rejected.

    Attributes
    ----------
    decided_by : the robot whose agent ran the match.
    robot_a, robot_b : the pair; ``matrix`` maps B pixels to A pixels (x = column, y = row).
    version_a, version_b : the map versions the decision was made on.
    accepted : outcome of the existence test (32) and the global check.
    matrix : 3x3 homogeneous rigid transform, eqs. (1)-(2).
    covariance : 3x3 covariance of (x px, y px, psi rad), eqs. (4)-(8).
    score : agreement / (agreement + disagreement) of the overlaid maps.
    trust : its lifecycle (:class:`LinkTrust`); None for a link of the older format, which
        carried no lifecycle: read as ``accepted`` or ``rejected`` by its outcome.
    """

    fleet: str
    decided_by: str
    robot_a: str
    robot_b: str
    version_a: int
    version_b: int
    accepted: bool
    matrix: tuple[tuple[float, float, float], ...]
    covariance: tuple[tuple[float, float, float], ...]
    score: float
    trust: LinkTrust | None = None

    def __post_init__(self) -> None:
        check_id(self.fleet, "fleet")
        check_id(self.decided_by, "decided_by")
        check_id(self.robot_a, "robot_a")
        check_id(self.robot_b, "robot_b")
        if self.robot_a == self.robot_b:
            raise ProtocolError(
                f"a link needs two different robots, got {self.robot_a!r} twice", reason="value"
            )
        check_version(self.version_a, "version_a")
        check_version(self.version_b, "version_b")
        if not isinstance(self.accepted, bool):
            raise ProtocolError("accepted must be a bool", reason="schema")
        object.__setattr__(self, "matrix", check_matrix(self.matrix, "matrix"))
        object.__setattr__(self, "covariance", check_matrix(self.covariance, "covariance"))
        object.__setattr__(self, "score", check_float(self.score, "score"))
        if self.trust is not None:
            self._check_trust(self.trust)

    def _check_trust(self, trust: LinkTrust) -> None:
        if not isinstance(trust, LinkTrust):
            raise ProtocolError("trust must be a LinkTrust", reason="schema")
        if self.accepted != (trust.state in LINK_IN_MAP):
            raise ProtocolError(
                f"a {trust.state} link cannot have accepted={self.accepted}", reason="value"
            )
        if trust.first_version_a > self.version_a or trust.first_version_b > self.version_b:
            raise ProtocolError("a link's first versions are newer than its own", reason="value")

    @property
    def robot(self) -> str:
        """The sender, for code that treats every message alike."""
        return self.decided_by


@dataclass(frozen=True)
class Heartbeat:
    """I am alive; ``map_version`` is my latest local map version (None before the first)."""

    fleet: str
    robot: str
    seq: int
    map_version: int | None = None

    def __post_init__(self) -> None:
        check_id(self.fleet, "fleet")
        check_id(self.robot, "robot")
        check_version(self.seq, "seq")
        if self.map_version is not None:
            check_version(self.map_version, "map_version")


@dataclass(frozen=True)
class Status:
    """Free-form counters (messages dropped, merges done, ...) as a flat str -> number map."""

    fleet: str
    robot: str
    seq: int
    counters: Mapping[str, int | float] = field(default_factory=dict)

    def __post_init__(self) -> None:
        check_id(self.fleet, "fleet")
        check_id(self.robot, "robot")
        check_version(self.seq, "seq")
        if not isinstance(self.counters, Mapping):
            raise ProtocolError("counters must be a mapping", reason="schema")
        clean: dict[str, int | float] = {}
        for name in sorted(self.counters, key=str):
            check_counter_name(name)
            value = self.counters[name]
            if isinstance(value, (int, np.integer)) and not isinstance(value, bool):
                if not -(2**63) <= value < 2**63:
                    raise ProtocolError(f"counter {name!r} does not fit 64 bits", reason="value")
                clean[name] = int(value)
            else:
                clean[name] = check_float(value, f"counter {name!r}")
        object.__setattr__(self, "counters", MappingProxyType(clean))

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Status):
            return NotImplemented
        return (self.fleet, self.robot, self.seq, dict(self.counters)) == (
            other.fleet,
            other.robot,
            other.seq,
            dict(other.counters),
        )

    __hash__ = None  # type: ignore[assignment]


COUNTER_PATTERN = re.compile(r"[A-Za-z0-9_.-]{1,64}")


def check_counter_name(name: object) -> str:
    """Return ``name`` if it is a valid counter name (1..64 of ``[A-Za-z0-9_.-]``)."""
    if not isinstance(name, str) or not COUNTER_PATTERN.fullmatch(name):
        raise ProtocolError(
            f"counter name {name!r} must be 1..64 characters of [A-Za-z0-9_.-]", reason="value"
        )
    return name


#: Any message of the wire format.
Message = Union[MapTiles, Manifest, Link, Heartbeat, Status]  # noqa: UP007
