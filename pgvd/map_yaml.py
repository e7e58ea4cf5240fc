"""ROS map_server YAML: the flat subset its files use, and the keys a map needs.

One ``key: value`` per line naming the image, its cell size (``resolution``), the ROS
``origin`` of its lower-left cell, ``negate``, the two thresholds and optionally the
``mode`` of its pixels (:mod:`pgvd.map_shades`).
"""

from __future__ import annotations

import math
import os
import re
from pathlib import Path

from pgvd.map_errors import MapFormatError, check_map_resolution, read_map_bytes
from pgvd.map_shades import FREE_THRESH, MODES, OCCUPIED_THRESH

#: Suffixes of map_server YAML files.
YAML_SUFFIXES = (".yaml", ".yml")

_REQUIRED_KEYS = ("image", "resolution", "origin", "negate", "occupied_thresh", "free_thresh")


_KEY_RE = re.compile(r"[A-Za-z_][A-Za-z0-9_]*\Z")
_NUMBER_RE = re.compile(r"[+-]?(\d+\.?\d*|\.\d+)([eE][+-]?\d+)?\Z")

YamlValue = float | int | str | list[float]


def parse_map_yaml(text: str, path: str | os.PathLike[str] = "<yaml>") -> dict[str, YamlValue]:
    """Parse the flat YAML subset used by map_server files.

    One ``key: value`` per line; values are numbers, plain or quoted strings,
    or ``[a, b, c]`` lists of numbers; ``#`` starts a comment; blank lines are
    skipped.  Anything else (nesting, indentation, duplicate keys, block
    lists) raises :class:`MapFormatError` naming the line.

    Parameters
    ----------
    text : the file's content.
    path : used in error messages only.

    Returns
    -------
    dict mapping each key to an ``int``, ``float``, ``str`` or list of floats.
    """
    out: dict[str, YamlValue] = {}
    for lineno, raw in enumerate(text.splitlines(), start=1):
        line = _strip_comment(raw).rstrip()
        if not line.strip() or line.strip() in ("---", "..."):
            continue
        where = f"line {lineno}"
        if line[0].isspace():
            raise MapFormatError(path, f"{where}: nested or indented YAML is not supported")
        key, sep, value = line.partition(":")
        key = key.strip()
        if not sep or not _KEY_RE.match(key):
            raise MapFormatError(path, f"{where}: expected 'key: value', got {raw.strip()[:60]!r}")
        if key in out:
            raise MapFormatError(path, f"{where}: duplicate key {key!r}")
        out[key] = _parse_value(value.strip(), path, f"{where} ({key})")
    return out


def _strip_comment(line: str) -> str:
    """Drop a ``#`` comment that is not inside quotes (YAML: '#' after whitespace or at start)."""
    quote = ""
    for i, ch in enumerate(line):
        if quote:
            if ch == quote:
                quote = ""
        elif ch in "'\"":
            quote = ch
        elif ch == "#" and (i == 0 or line[i - 1].isspace()):
            return line[:i]
    return line


def _parse_value(value: str, path: str | os.PathLike[str], where: str) -> YamlValue:
    if not value:
        raise MapFormatError(path, f"{where}: empty value")
    if value.startswith("["):
        if not value.endswith("]"):
            raise MapFormatError(path, f"{where}: unterminated list {value[:60]!r}")
        items = [s.strip() for s in value[1:-1].split(",")]
        if items == [""]:
            return []
        if not all(_NUMBER_RE.match(s) for s in items):
            raise MapFormatError(path, f"{where}: lists must hold numbers, got {value[:60]!r}")
        return [float(s) for s in items]
    if value[0] in "'\"":
        if len(value) < 2 or value[-1] != value[0] or value[0] in value[1:-1]:
            raise MapFormatError(path, f"{where}: badly quoted string {value[:60]!r}")
        return value[1:-1]
    if value[0] in "{&*!|>%@`" or value.startswith("- "):
        raise MapFormatError(path, f"{where}: unsupported YAML construct {value[:60]!r}")
    if _NUMBER_RE.match(value):
        return float(value) if any(c in value for c in ".eE") else int(value)
    if value.lower() in (".nan", "nan"):
        return math.nan
    return value


def yaml_number(meta: dict[str, YamlValue], key: str, path: Path) -> float:
    """The number under ``key`` of the YAML ``path`` parsed as ``meta``; ``MapFormatError``
    if it is anything else."""
    v = meta[key]
    if isinstance(v, bool) or not isinstance(v, int | float):
        raise MapFormatError(path, f"{key!r} must be a number, got {v!r}")
    return float(v)


def read_map_yaml(path: Path) -> dict[str, YamlValue]:
    """Read a map_server YAML and check the keys a map needs.

    Parameters
    ----------
    path : pathlib.Path
        The ``.yaml``/``.yml`` file.

    Returns
    -------
    dict
        :func:`parse_map_yaml`'s keys, with every required one present and valid.

    Raises
    ------
    MapFormatError
        Unreadable file, bad YAML, a missing key or one of the wrong kind, a cell size
        outside :data:`pgvd.grid.CELL_SIZE_RANGE`, thresholds out of order.
    """
    text = read_map_bytes(path).decode("utf-8-sig", errors="replace")  # tolerate a BOM
    meta = parse_map_yaml(text, path)
    missing = [k for k in _REQUIRED_KEYS if k not in meta]
    if missing:
        raise MapFormatError(path, f"missing key(s): {', '.join(missing)}")
    check_map_resolution(path, yaml_number(meta, "resolution", path))
    origin = meta["origin"]
    if not isinstance(origin, list) or len(origin) != 3 or not all(map(math.isfinite, origin)):
        raise MapFormatError(path, f"origin must be a list of 3 finite numbers, got {origin!r}")
    occ, free = yaml_number(meta, "occupied_thresh", path), yaml_number(meta, "free_thresh", path)
    if not (0.0 <= free < occ <= 1.0):
        raise MapFormatError(
            path, f"need 0 <= free_thresh < occupied_thresh <= 1, got {free} and {occ}"
        )
    negate = meta["negate"]
    if negate not in (0, 1, "true", "false", "True", "False"):
        raise MapFormatError(path, f"negate must be 0 or 1, got {negate!r}")
    mode = meta.get("mode", "trinary")
    if mode not in MODES:
        raise MapFormatError(path, f"mode must be one of {', '.join(MODES)}, got {mode!r}")
    if not isinstance(meta["image"], str) or not meta["image"]:
        raise MapFormatError(path, f"image must be a file name, got {meta['image']!r}")
    return meta


def map_image_path(path: str | os.PathLike[str]) -> Path:
    """The image file a map_server YAML names, found as :func:`pgvd.io.read_map` finds it.

    Parameters
    ----------
    path : str or os.PathLike
        The ``.yaml``/``.yml`` file.

    Returns
    -------
    pathlib.Path
        The image path: relative names are relative to the YAML; an absolute path
        that does not exist falls back to the YAML's directory.  The image itself
        is not checked.

    Raises
    ------
    MapFormatError
        If the YAML cannot be read or lacks a valid key.
    """
    path = Path(path)
    return yaml_image_path(path, str(read_map_yaml(path)["image"]))


def yaml_image_path(yaml_path: Path, image: str) -> Path:
    """The image named in the YAML: relative to the YAML; an absolute path that does not
    exist falls back to the YAML's directory (files copied from another machine)."""
    p = Path(image)
    if not p.is_absolute():
        return yaml_path.parent / p
    if p.exists():
        return p
    return yaml_path.parent / p.name


def format_map_yaml(image: str, resolution: float, origin: tuple[float, float, float]) -> str:
    """The map_server YAML of a trinary image: what :func:`read_map_yaml` reads back.

    Parameters
    ----------
    image : str
        The image's file name, relative to the YAML.
    resolution : float
        Metres per cell.
    origin : tuple of float
        ``(x, y, yaw)`` of the lower-left cell (ROS).

    Returns
    -------
    str
        The file's text: ``mode: trinary``, ``negate: 0`` and map_server's default
        thresholds; numbers written to round-trip exactly.
    """
    ox, oy, yaw = (float(v) for v in origin)
    return (
        f"image: {image}\n"
        f"mode: trinary\n"
        f"resolution: {float(resolution)!r}\n"
        f"origin: [{ox!r}, {oy!r}, {yaw!r}]\n"
        f"negate: 0\n"
        f"occupied_thresh: {OCCUPIED_THRESH}\n"
        f"free_thresh: {FREE_THRESH}\n"
    )
