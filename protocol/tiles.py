"""Cutting a quantised grid into tiles, computing deltas, and putting tiles back together.

A quantised grid is the int8 array of :func:`protocol.quantize.quantise`.
Tiles that are all zero hold no knowledge and are never sent; a
:class:`~protocol.messages.Manifest` lists the checksum of every other tile,
and :class:`TileAssembler` rebuilds the exact array from tiles arriving in
any order, full or as differences against content the receiver already holds.
"""

from __future__ import annotations

import hashlib
import zlib
from collections.abc import Iterable, Mapping

import numpy as np

from protocol.errors import ProtocolError
from protocol.messages import Geometry, Manifest, Tile


def checksum(cells: np.ndarray) -> int:
    """CRC-32 of an int8 tile's row-major bytes (shape is implied by the tile index)."""
    return zlib.crc32(np.ascontiguousarray(cells, dtype=np.int8).data)


def zero_checksum(geometry: Geometry, index: int) -> int:
    """Checksum of tile ``index`` when it holds no knowledge (all zero)."""
    rows, cols = geometry.tile_shape(index)
    return zlib.crc32(bytes(rows * cols))


def pack_checksums(geometry: Geometry, checksums: Mapping[int, int]) -> bytes:
    """A bitmap of the listed tiles, then their CRC-32s little-endian in index order."""
    listed = np.zeros(geometry.n_tiles, bool)
    listed[list(checksums)] = True
    crcs = np.array([checksums[i] for i in sorted(checksums)], dtype="<u4")
    return np.packbits(listed).tobytes() + crcs.tobytes()


def manifest_digest(geometry: Geometry, checksums: Mapping[int, int]) -> int:
    """64-bit BLAKE2b of a full checksum list, carried by delta manifests to verify a rebuild."""
    packed = pack_checksums(geometry, checksums)
    return int.from_bytes(hashlib.blake2b(packed, digest_size=8).digest(), "little")


def expand_manifest(delta: Manifest, base: Mapping[int, int]) -> Manifest:
    """The full manifest of a delta manifest, given the full checksums of its base version.

    Raises
    ------
    ProtocolError
        If the rebuilt list does not match the delta's digest: ``base`` is not
        the sender's ``base_version``.
    """
    full = dict(base)
    for i, crc in delta.checksums.items():
        if crc == zero_checksum(delta.geometry, i):
            full.pop(i, None)
        else:
            full[i] = crc
    if manifest_digest(delta.geometry, full) != delta.digest:
        raise ProtocolError(
            f"delta manifest of version {delta.version} does not apply to the held "
            f"version {delta.base_version}",
            reason="value",
        )
    return Manifest(
        delta.fleet, delta.robot, delta.version, delta.geometry, full,
        first_epoch=delta.first_epoch, final=delta.final,
    )  # fmt: skip


def check_quantised(q: np.ndarray, geometry: Geometry) -> np.ndarray:
    """Return ``q`` if it is an int8 array of the geometry's shape, else raise ProtocolError."""
    if not isinstance(q, np.ndarray) or q.dtype != np.int8:
        raise ProtocolError("a quantised grid must be an int8 array", reason="schema")
    if q.shape != geometry.shape:
        raise ProtocolError(
            f"grid shape {q.shape} does not match geometry {geometry.shape}", reason="value"
        )
    return q


def knowledge_tiles(q: np.ndarray, geometry: Geometry) -> list[int]:
    """Indices of the tiles of ``q`` that hold any nonzero cell, ascending."""
    check_quantised(q, geometry)
    rows, cols = geometry.tile_grid
    t = geometry.tile_size
    known = q != 0
    # Pad to whole tiles so one reshape gives every tile's any().
    padded = np.zeros((rows * t, cols * t), dtype=bool)
    padded[: q.shape[0], : q.shape[1]] = known
    per_tile = padded.reshape(rows, t, cols, t).any(axis=(1, 3))
    return [int(i) for i in np.flatnonzero(per_tile)]


def manifest_checksums(q: np.ndarray, geometry: Geometry) -> dict[int, int]:
    """``{tile index: checksum}`` of every tile of ``q`` that holds knowledge."""
    return {i: checksum(q[geometry.tile_window(i)]) for i in knowledge_tiles(q, geometry)}


def full_tile(q: np.ndarray, geometry: Geometry, index: int) -> Tile:
    """Tile ``index`` of ``q`` as a self-contained tile."""
    cells = np.ascontiguousarray(q[geometry.tile_window(index)])
    return Tile(index, checksum(cells), cells)


def delta_tile(q: np.ndarray, base: np.ndarray, geometry: Geometry, index: int) -> Tile:
    """Tile ``index`` of ``q`` as the wrapping int8 difference to the same tile of ``base``.

    Unchanged cells become 0, which is what makes a delta compress to little.
    A tile whose base is all zero is sent whole: the difference would be the
    same bytes with an extra checksum.
    """
    window = geometry.tile_window(index)
    old = np.ascontiguousarray(base[window])
    if not old.any():
        return full_tile(q, geometry, index)
    new = np.ascontiguousarray(q[window])
    diff = (new.view(np.uint8) - old.view(np.uint8)).view(np.int8)
    return Tile(index, checksum(new), diff, base_checksum=checksum(old))


def changed_tiles(q: np.ndarray, base: np.ndarray, geometry: Geometry) -> list[int]:
    """Indices of tiles whose content differs between ``base`` and ``q`` and that hold knowledge.

    A tile that lost all its knowledge is not returned: the manifest, which
    no longer lists it, already tells a receiver to clear it.
    """
    check_quantised(q, geometry)
    check_quantised(base, geometry)
    rows, cols = geometry.tile_grid
    t = geometry.tile_size
    padded = np.zeros((rows * t, cols * t), dtype=bool)
    padded[: q.shape[0], : q.shape[1]] = q != base
    changed = padded.reshape(rows, t, cols, t).any(axis=(1, 3)).ravel()
    return [i for i in knowledge_tiles(q, geometry) if changed[i]]


def apply_tile(tile: Tile, held: np.ndarray | None) -> np.ndarray:
    """The full content of ``tile``, given the content ``held`` for its index (or None).

    Raises
    ------
    ProtocolError
        If a delta's base is not what is held, or the result fails its checksum.
    """
    if tile.base_checksum is None:
        content = tile.cells
    else:
        if held is None or checksum(held) != tile.base_checksum:
            raise ProtocolError(f"tile {tile.index}: delta base is not held", reason="value")
        content = (held.view(np.uint8) + tile.cells.view(np.uint8)).view(np.int8)
    if checksum(content) != tile.checksum:
        raise ProtocolError(f"tile {tile.index}: checksum mismatch", reason="value")
    if content.min(initial=0) == -128:
        raise ProtocolError(
            f"tile {tile.index}: cell value -128 is outside the quantised range", reason="value"
        )
    return content


class TileAssembler:
    """Rebuilds the exact quantised grid of a manifest from tiles in any order.

    Tiles held from earlier versions are kept: a tile whose checksum equals the
    manifest's needs no transfer, and delta tiles apply to them.  Sans-I/O:
    feed it tiles, ask what is missing, take the grid once nothing is.

    Parameters
    ----------
    geometry : the geometry every tile and manifest must share; a different
        geometry (a grown map) needs a new assembler.
    """

    def __init__(self, geometry: Geometry) -> None:
        self.geometry = geometry
        self._held: dict[int, np.ndarray] = {}
        self._crc: dict[int, int] = {}

    def add(self, tile: Tile) -> None:
        """Store ``tile`` (applying it to the held content if it is a delta).

        Raises
        ------
        ProtocolError
            If the tile does not fit the geometry, its delta base is not held,
            or its content fails the checksum.  Nothing is stored then.
        """
        expected = self.geometry.tile_shape(tile.index)
        if tile.cells.shape != expected:
            raise ProtocolError(
                f"tile {tile.index} has shape {tile.cells.shape}, geometry says {expected}",
                reason="value",
            )
        content = apply_tile(tile, self._held.get(tile.index))
        content = content.copy()
        content.flags.writeable = False
        self._held[tile.index] = content
        self._crc[tile.index] = tile.checksum

    def can_apply(self, tile: Tile) -> bool:
        """False for a delta whose base content is not held (it must be fetched in full)."""
        return tile.base_checksum is None or self._crc.get(tile.index) == tile.base_checksum

    def holds(self, index: int, crc: int) -> bool:
        """True when the content held for tile ``index`` has checksum ``crc``."""
        return self._crc.get(index) == crc

    def missing(self, manifest: Manifest) -> list[int]:
        """Tile indices of ``manifest`` whose content is not held, ascending."""
        self._check_geometry(manifest)
        return [i for i, crc in manifest.checksums.items() if self._crc.get(i) != crc]

    def assemble(self, manifest: Manifest) -> np.ndarray:
        """The int8 grid of ``manifest``; tiles it does not list are zero.

        Raises
        ------
        ProtocolError
            If any tile of the manifest is missing.
        """
        lacking = self.missing(manifest)
        if lacking:
            raise ProtocolError(
                f"{len(lacking)} tiles of version {manifest.version} are missing", reason="value"
            )
        q = np.zeros(self.geometry.shape, dtype=np.int8)
        for i in manifest.checksums:
            q[self.geometry.tile_window(i)] = self._held[i]
        return q

    def forget(self, keep: Iterable[int]) -> None:
        """Drop held tiles whose index is not in ``keep`` (tiles a newer map no longer has)."""
        keep = set(keep)
        for i in [i for i in self._held if i not in keep]:
            del self._held[i], self._crc[i]

    def _check_geometry(self, manifest: Manifest) -> None:
        if manifest.geometry.shape != self.geometry.shape or (
            manifest.geometry.tile_size != self.geometry.tile_size
        ):
            raise ProtocolError("manifest geometry differs from the assembler's", reason="value")
