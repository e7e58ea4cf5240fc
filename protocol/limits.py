"""Bounds a decoder enforces, so a hostile or broken peer cannot make it allocate or loop."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Limits:
    """Upper bounds checked by :func:`protocol.codec.decode` and the reassembler.

    Attributes
    ----------
    max_message_bytes : size of one encoded message on the wire.
    max_cells : cells of one map (H * W).
    max_side : rows or columns of one map.
    max_tiles : tiles of one map (bounds a manifest).
    max_tiles_per_message : tiles carried by one MapTiles message.
    max_tile_cells : cells of one tile, hence the decompressed bytes of one tile.
    max_message_cells : cells of all tiles of one message, hence what decoding one
        message may allocate (a well-compressed 64 KB message could otherwise
        inflate to 256 full tiles of 64 KB each).
    max_id_length : characters of a fleet or robot id.
    max_status_entries : counters in one Status message.
    max_buffered_cells : cells of the tiles a reassembler holds for versions whose
        manifest has not arrived (per peer robot).
    """

    max_message_bytes: int = 65_536
    max_cells: int = 16_000_000
    max_side: int = 16_384
    max_tiles: int = 4_096
    max_tiles_per_message: int = 256
    max_tile_cells: int = 65_536
    max_message_cells: int = 1_048_576
    max_id_length: int = 64
    max_status_entries: int = 128
    max_buffered_cells: int = 4_194_304
