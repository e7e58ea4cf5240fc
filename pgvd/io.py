"""Map file formats: ROS ``map_server`` YAML + PGM/PNG, bare PGM/PNG images and ``.npy`` arrays.

Reading gives a log-odds :class:`~pgvd.grid.Grid` (eq. (9)).  A map_server
image carries classes, not confidences, so the classes get definite
probabilities: occupied :data:`P_OCCUPIED` (log-odds +2.2), free
:data:`P_FREE` (log-odds -2.2), unknown 0.5 (log-odds 0).  Every problem with
a file raises :class:`MapFormatError`, a ``ValueError`` whose message is one
line naming the file and the problem.

A bare ``.pgm`` or ``.png`` (an image without its YAML, as map collections often ship
them) carries no cell size: it is read with one given by the caller, map_saver's thresholds
(occupied above 0.65, free below 0.196, so that its 0/205/254 pixels are occupied, unknown
and free) and the origin at ``(0, 0, 0)``.

map_server semantics (ROS1 ``image_loader``): ``shade`` is the gray value in
0..255 (RGB/RGBA averaged over the colour channels; 16-bit scaled to 0..255),
inverted when ``negate`` is set; ``p = (255 - shade) / 255``.

* ``trinary`` (default): ``p > occupied_thresh`` occupied, ``p < free_thresh``
  free, anything else unknown.
* ``scale``: occupied/free as trinary; a pixel with alpha < 255 is unknown; in
  between, the ROS occupancy ``ratio = (p - free_thresh) / (occupied_thresh -
  free_thresh)`` is scaled linearly into ``[P_FREE, P_OCCUPIED]``.
* ``raw``: ``shade`` is the ROS occupancy value itself: 0..100 is scaled
  linearly into ``[P_FREE, P_OCCUPIED]``, anything above 100 is unknown.
"""

from __future__ import annotations

import math
import os
import re
import secrets
import struct
import zlib
from collections.abc import Callable
from io import BytesIO
from pathlib import Path
from tokenize import TokenError
from typing import BinaryIO

import numpy as np

from pgvd.grid import Grid, check_cell_size

#: Probability given to an occupied map_server cell (log-odds ~ +2.2).
P_OCCUPIED = 0.9
#: Probability given to a free map_server cell (log-odds ~ -2.2).
P_FREE = 0.1
#: ROS map_server default thresholds, also used to classify a Grid's cells on writing.
OCCUPIED_THRESH = 0.65
FREE_THRESH = 0.196
#: Default limit on the number of cells of one map (8000 x 8000).
MAX_CELLS = 8000 * 8000
#: Resolution given to ``.npy`` maps, which carry none.
NPY_RESOLUTION = 0.05
#: Suffixes of map_server YAML files.
YAML_SUFFIXES = (".yaml", ".yml")
#: Suffixes of bare map images, read without a YAML (:func:`read_map`'s ``image_resolution``).
IMAGE_SUFFIXES = (".pgm", ".png")
_IS_DIRECTORY = "is a directory, not a map file"

_MODES = ("trinary", "scale", "raw")
_REQUIRED_KEYS = ("image", "resolution", "origin", "negate", "occupied_thresh", "free_thresh")
_PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


class MapFormatError(ValueError):
    """A map file that cannot be read; the message is one line naming the file."""

    def __init__(self, path: str | os.PathLike[str], problem: str) -> None:
        self.path = str(path)
        self.problem = " ".join(str(problem).split())  # one line, whatever the cause said
        super().__init__(f"{self.path}: {self.problem}")


# ----------------------------------------------------------------------------- YAML


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


def _number(meta: dict[str, YamlValue], key: str, path: Path) -> float:
    v = meta[key]
    if isinstance(v, bool) or not isinstance(v, int | float):
        raise MapFormatError(path, f"{key!r} must be a number, got {v!r}")
    return float(v)


def _check_resolution(path: Path, res: float) -> None:
    """``MapFormatError`` unless the cell size ``res`` is one of an occupancy grid
    (:func:`pgvd.grid.check_cell_size`)."""
    try:
        check_cell_size(res)
    except ValueError as exc:
        raise MapFormatError(path, f"resolution: {exc}") from None


def _read_meta(path: Path) -> dict[str, YamlValue]:
    text = _read_bytes(path).decode("utf-8-sig", errors="replace")  # tolerate a BOM
    meta = parse_map_yaml(text, path)
    missing = [k for k in _REQUIRED_KEYS if k not in meta]
    if missing:
        raise MapFormatError(path, f"missing key(s): {', '.join(missing)}")
    _check_resolution(path, _number(meta, "resolution", path))
    origin = meta["origin"]
    if not isinstance(origin, list) or len(origin) != 3 or not all(map(math.isfinite, origin)):
        raise MapFormatError(path, f"origin must be a list of 3 finite numbers, got {origin!r}")
    occ, free = _number(meta, "occupied_thresh", path), _number(meta, "free_thresh", path)
    if not (0.0 <= free < occ <= 1.0):
        raise MapFormatError(
            path, f"need 0 <= free_thresh < occupied_thresh <= 1, got {free} and {occ}"
        )
    negate = meta["negate"]
    if negate not in (0, 1, "true", "false", "True", "False"):
        raise MapFormatError(path, f"negate must be 0 or 1, got {negate!r}")
    mode = meta.get("mode", "trinary")
    if mode not in _MODES:
        raise MapFormatError(path, f"mode must be one of {', '.join(_MODES)}, got {mode!r}")
    if not isinstance(meta["image"], str) or not meta["image"]:
        raise MapFormatError(path, f"image must be a file name, got {meta['image']!r}")
    return meta


def map_image_path(path: str | os.PathLike[str]) -> Path:
    """The image file a map_server YAML names, found as :func:`read_map` finds it.

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
    return _image_path(path, str(_read_meta(path)["image"]))


def _image_path(yaml_path: Path, image: str) -> Path:
    """The image named in the YAML: relative to the YAML; an absolute path that does not
    exist falls back to the YAML's directory (files copied from another machine)."""
    p = Path(image)
    if not p.is_absolute():
        return yaml_path.parent / p
    if p.exists():
        return p
    return yaml_path.parent / p.name


# ----------------------------------------------------------------------------- images


def _read_bytes(path: Path) -> bytes:
    try:
        return path.read_bytes()
    except FileNotFoundError:
        raise MapFormatError(path, "no such file") from None
    except IsADirectoryError:
        raise MapFormatError(path, _IS_DIRECTORY) from None
    except OSError as exc:
        raise MapFormatError(path, f"cannot read: {exc.strerror or exc}") from None


def _check_size(path: Path, width: int, height: int, max_cells: int) -> None:
    if width <= 0 or height <= 0:
        raise MapFormatError(path, f"empty map ({width}x{height} cells)")
    if width * height > max_cells:
        raise MapFormatError(
            path, f"map of {width}x{height} cells exceeds the limit of {max_cells} cells"
        )


def _pgm_header(data: bytes, path: Path) -> tuple[bool, int, int, int, int]:
    """Parse a PGM header: ``(binary, width, height, maxval, offset of the pixels)``."""
    tokens: list[int] = []
    pos = 2
    n = len(data)
    while len(tokens) < 3:
        while pos < n and data[pos : pos + 1].isspace():
            pos += 1
        if pos < n and data[pos] == ord("#"):
            end = data.find(b"\n", pos)
            pos = n if end < 0 else end + 1
            continue
        start = pos
        while pos < n and data[pos : pos + 1].isdigit():
            pos += 1
        if start == pos:
            raise MapFormatError(path, "truncated or malformed PGM header")
        tokens.append(int(data[start:pos]))
    if pos >= n or not data[pos : pos + 1].isspace():
        raise MapFormatError(path, "malformed PGM header (no whitespace after maxval)")
    width, height, maxval = tokens
    if not 0 < maxval < 65536:
        raise MapFormatError(path, f"PGM maxval must be in 1..65535, got {maxval}")
    return data[:2] == b"P5", width, height, maxval, pos + 1


def _decode_pgm(data: bytes, path: Path, max_cells: int) -> tuple[np.ndarray, None]:
    binary, width, height, maxval, offset = _pgm_header(data, path)
    _check_size(path, width, height, max_cells)
    count = width * height
    if binary:
        dtype = np.dtype(">u2") if maxval > 255 else np.dtype(np.uint8)
        need = count * dtype.itemsize
        if len(data) - offset < need:
            raise MapFormatError(
                path, f"truncated PGM: {len(data) - offset} pixel bytes, need {need}"
            )
        pixels = np.frombuffer(data, dtype=dtype, count=count, offset=offset)
    else:
        fields = data[offset:].split()
        if len(fields) < count or not all(f.isdigit() for f in fields[:count]):
            raise MapFormatError(path, f"ASCII PGM must hold {count} integer pixel values")
        pixels = np.array([int(f) for f in fields[:count]], dtype=np.int64)
    if pixels.max() > maxval:
        raise MapFormatError(path, f"pixel value {int(pixels.max())} exceeds maxval {maxval}")
    gray = pixels.reshape(height, width).astype(np.float32) * np.float32(255.0 / maxval)
    return gray, None


def _decode_png(data: bytes, path: Path, max_cells: int) -> tuple[np.ndarray, np.ndarray | None]:
    """Decode a PNG into ``(shade 0..255, alpha 0..255 or None)``; the IHDR size is checked
    against ``max_cells`` before any pixel is decompressed."""
    if len(data) < 33 or data[12:16] != b"IHDR":
        raise MapFormatError(path, "truncated PNG (no IHDR chunk)")
    width, height = struct.unpack(">II", data[16:24])
    _check_size(path, width, height, max_cells)
    # pillow comes with scikit-image; its own decompression-bomb limit (89 M pixels) is
    # above the default max_cells and left alone (it is process-wide)
    from PIL import Image

    try:
        with Image.open(BytesIO(data)) as im:
            im.load()
            img = _pil_to_array(im)
    # Pillow reports corrupt data through many exception types (OSError, SyntaxError,
    # zlib.error, struct.error, EOFError, ...); all of them mean "bad file" here.
    except Exception as exc:
        raise MapFormatError(path, f"cannot decode PNG: {exc}") from None
    return img


def _pil_to_array(im) -> tuple[np.ndarray, np.ndarray | None]:
    mode = im.mode
    if mode in ("P", "PA", "1", "CMYK", "YCbCr", "LAB", "HSV"):
        im = im.convert("RGBA" if "A" in mode or "transparency" in im.info else "RGB")
        mode = im.mode
    arr = np.asarray(im)
    if mode.startswith("I") or mode == "F":
        # 16-bit gray ('I;16', 'I;16B', 'I'): scale to 0..255
        return arr.astype(np.float32) * np.float32(255.0 / 65535.0), None
    arr = arr.astype(np.float32)
    if mode == "L":
        return arr, None
    if mode == "LA":
        return arr[..., 0], arr[..., 1]
    if mode == "RGB":
        return arr.mean(axis=2), None
    if mode == "RGBA":
        return arr[..., :3].mean(axis=2), arr[..., 3]
    raise ValueError(f"unsupported PNG pixel mode {mode}")


def _decode_image(path: Path, max_cells: int) -> tuple[np.ndarray, np.ndarray | None]:
    data = _read_bytes(path)
    if data[:2] in (b"P5", b"P2"):
        return _decode_pgm(data, path, max_cells)
    if data[:8] == _PNG_MAGIC:
        return _decode_png(data, path, max_cells)
    raise MapFormatError(path, "not a PGM (P2/P5) or PNG image")


# ----------------------------------------------------------------------------- semantics


def shade_to_probability(
    shade: np.ndarray,
    alpha: np.ndarray | None,
    *,
    mode: str = "trinary",
    negate: bool = False,
    occupied_thresh: float = OCCUPIED_THRESH,
    free_thresh: float = FREE_THRESH,
) -> np.ndarray:
    """map_server pixel semantics: gray ``shade`` (0..255) to occupancy probability.

    See the module docstring for the three modes.  Unknown is 0.5 exactly, so
    that its log-odds (9) is exactly 0.

    Returns
    -------
    float32 array of the shape of ``shade``.
    """
    shade = np.asarray(shade, dtype=np.float32)
    if negate:
        shade = 255.0 - shade
    out = np.full(shade.shape, 0.5, dtype=np.float32)
    if mode == "raw":
        known = shade <= 100.0
        out[known] = P_FREE + (P_OCCUPIED - P_FREE) * shade[known] / 100.0
        return out
    p = (255.0 - shade) / 255.0
    occupied, free = p > occupied_thresh, p < free_thresh
    if mode == "scale":
        between = ~occupied & ~free
        if alpha is not None:
            between &= alpha >= 255.0
        ratio = (p[between] - free_thresh) / (occupied_thresh - free_thresh)
        out[between] = P_FREE + (P_OCCUPIED - P_FREE) * ratio
    out[occupied] = P_OCCUPIED
    out[free] = P_FREE
    return out


def _check_content(path: Path, prob: np.ndarray) -> None:
    if not np.any(prob > OCCUPIED_THRESH):
        raise MapFormatError(path, "map has no occupied cells")


# ----------------------------------------------------------------------------- read


def read_map(
    path: str | os.PathLike[str],
    max_cells: int = MAX_CELLS,
    *,
    npy_resolution: float = NPY_RESOLUTION,
    image_resolution: float | None = None,
) -> Grid:
    """Read an occupancy map into a log-odds :class:`~pgvd.grid.Grid` (eq. (9)).

    Parameters
    ----------
    path : str or os.PathLike
        ``.yaml``/``.yml`` (ROS map_server, PGM or PNG image), a bare ``.pgm``/``.png``
        image (map_saver's classes, see the module docstring) or ``.npy`` (2-D
        probabilities in [0, 1], 0.5 = unknown).
    max_cells : int, optional
        Refuse maps with more cells than this (checked on the header,
        before pixels are decoded).
    npy_resolution : float, optional
        Resolution given to ``.npy`` maps, which carry none.
    image_resolution : float, optional
        Resolution (m) of a bare image, which carries none; reading one without it is
        refused (a guessed cell size would scale every metric threshold of the merge).

    Returns
    -------
    Grid
        Log-odds per cell, the map's resolution and ROS origin.

    Raises
    ------
    MapFormatError
        Missing/unreadable file, bad YAML or keys, a cell size outside
        :data:`pgvd.grid.CELL_SIZE_RANGE`, empty map,
        no occupied cells, too many cells, NaN or out-of-range values, a bare image
        without ``image_resolution``.
    """
    path = Path(path)
    if path.is_dir():  # whatever its name: "unknown map format" would send the user astray
        raise MapFormatError(path, _IS_DIRECTORY)
    suffix = path.suffix.lower()
    if suffix in YAML_SUFFIXES:
        return _read_yaml_map(path, max_cells)
    if suffix == ".npy":
        return _read_npy_map(path, max_cells, npy_resolution)
    if suffix in IMAGE_SUFFIXES:
        return _read_bare_image(path, max_cells, image_resolution)
    raise MapFormatError(path, "unknown map format (expected .yaml, .yml, .pgm, .png or .npy)")


def _read_bare_image(path: Path, max_cells: int, resolution: float | None) -> Grid:
    """A map image without its YAML: map_saver's classes, ``resolution``, origin (0, 0, 0)."""
    if resolution is None:
        raise MapFormatError(
            path,
            "a bare image carries no cell size: give it (pgvd merge --resolution M) "
            "or write a map_server YAML that names the image",
        )
    _check_resolution(path, resolution)
    shade, alpha = _decode_image(path, max_cells)
    prob = shade_to_probability(shade, alpha)
    _check_content(path, prob)
    return Grid.from_probability(prob, resolution)


def _read_yaml_map(path: Path, max_cells: int) -> Grid:
    meta = _read_meta(path)
    image = _image_path(path, str(meta["image"]))
    shade, alpha = _decode_image(image, max_cells)
    prob = shade_to_probability(
        shade,
        alpha,
        mode=str(meta.get("mode", "trinary")),
        negate=meta["negate"] in (1, "true", "True"),
        occupied_thresh=_number(meta, "occupied_thresh", path),
        free_thresh=_number(meta, "free_thresh", path),
    )
    _check_content(image, prob)
    ox, oy, yaw = meta["origin"]  # type: ignore[misc]
    return Grid.from_probability(prob, _number(meta, "resolution", path), (ox, oy, yaw))


#: What numpy raises reading a damaged ``.npy`` (alone or in an ``.npz``): it parses the
#: header's dict as Python, so a mangled header is a SyntaxError, or a TokenError when an
#: unclosed bracket leaves it mid-statement.
NPY_HEADER_ERRORS: tuple[type[Exception], ...] = (
    ValueError,
    OSError,
    SyntaxError,
    EOFError,
    TokenError,
)


def _read_npy_map(path: Path, max_cells: int, resolution: float) -> Grid:
    _check_resolution(path, resolution)
    try:
        f = path.open("rb")
    except FileNotFoundError:
        raise MapFormatError(path, "no such file") from None
    except OSError as exc:
        raise MapFormatError(path, f"cannot read: {exc.strerror or exc}") from None
    with f:
        try:
            version = np.lib.format.read_magic(f)
            header = (
                np.lib.format.read_array_header_1_0
                if version == (1, 0)
                else np.lib.format.read_array_header_2_0
            )
            shape, fortran, dtype = header(f)
        except NPY_HEADER_ERRORS as exc:
            raise MapFormatError(path, f"not a valid .npy file: {exc}") from None
        if len(shape) != 2:
            raise MapFormatError(path, f"expected a 2-D array, got shape {shape}")
        if dtype.kind not in "fiub" or dtype.hasobject:
            raise MapFormatError(path, f"expected a numeric array, got dtype {dtype}")
        _check_size(path, shape[1], shape[0], max_cells)
        data = f.read()
    count = shape[0] * shape[1]
    if len(data) < count * dtype.itemsize:
        raise MapFormatError(
            path, f"truncated .npy: {len(data)} data bytes, need {count * dtype.itemsize}"
        )
    arr = np.frombuffer(data, dtype=dtype, count=count).reshape(
        shape, order="F" if fortran else "C"
    )
    prob = arr.astype(np.float64)
    if np.isnan(prob).any():
        raise MapFormatError(path, f"{int(np.isnan(prob).sum())} NaN value(s)")
    if prob.min() < 0.0 or prob.max() > 1.0:
        raise MapFormatError(
            path, f"probabilities must lie in [0, 1], got {prob.min():g}..{prob.max():g}"
        )
    _check_content(path, prob)
    return Grid.from_probability(prob, resolution)


# ----------------------------------------------------------------------------- write


def atomic_write(
    path: str | os.PathLike[str], write: Callable[[BinaryIO], object], durable: bool = True
) -> None:
    """Write a file so that a crash or power cut leaves either the old or the new one whole.

    ``write`` fills a temporary file ``.<name>.<random>.tmp`` in the same
    directory; the file is fsynced, renamed over ``path``, and the directory
    fsynced so that the rename itself is on disk.  On any error the temporary
    file is removed and the old file, if any, is untouched.

    Parameters
    ----------
    path : str or os.PathLike
        The file to create or replace; missing parent directories are created.
    write : callable
        Called once with the temporary file, opened for binary writing.
    durable : bool, optional
        False skips both fsyncs: a crash of the process (``kill -9``) still leaves the old
        or the new file whole (the kernel holds what was written), a power cut may not.
        For files whose content can be had again; each fsync can cost tens of milliseconds.

    Raises
    ------
    OSError
        If the directory or the file cannot be written; whatever ``write`` raises.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.parent / f".{path.name}.{secrets.token_hex(6)}.tmp"
    # mode 0666 minus the umask, like any open(): tempfile.mkstemp would leave the file
    # readable by its owner only
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
    try:
        with os.fdopen(fd, "wb") as f:
            write(f)
            f.flush()
            if durable:
                os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    if not durable:
        return
    dir_fd = os.open(path.parent, os.O_RDONLY)
    try:
        os.fsync(dir_fd)
    finally:
        os.close(dir_fd)


def written_files(path: str | os.PathLike[str]) -> tuple[Path, ...]:
    """The files :func:`write_map` writes for ``path``: a YAML and the ``.pgm`` beside it,
    or the ``.npy``.

    Parameters
    ----------
    path : str or os.PathLike
        ``.yaml``/``.yml`` or ``.npy``.

    Returns
    -------
    tuple of pathlib.Path
    """
    path = Path(path)
    if path.suffix.lower() in YAML_SUFFIXES:
        return (path, path.with_suffix(".pgm"))
    return (path,)


def write_map(path: str | os.PathLike[str], grid: Grid) -> None:
    """Write a grid as map_server ``.yaml`` + trinary ``.pgm`` beside it, or as ``.npy``.

    The YAML form keeps the classes (occupied ``p > 0.65`` -> 0, free
    ``p < 0.196`` -> 254, unknown -> 205, ``mode: trinary``), so that
    :func:`read_map` gives back the same classes; ``.npy`` keeps the
    probabilities themselves (float32).  Both writes are atomic.

    Parameters
    ----------
    path : str or os.PathLike
        ``.yaml``/``.yml`` (the ``.pgm`` goes beside it) or ``.npy``.
    grid : Grid
        The map.

    Raises
    ------
    ValueError
        If the suffix is none of those.
    OSError
        If a file cannot be written.
    """
    path = Path(path)
    prob = grid.probability()
    suffix = path.suffix.lower()
    if suffix == ".npy":
        atomic_write(path, lambda f: np.save(f, prob.astype(np.float32), allow_pickle=False))
        return
    if suffix not in YAML_SUFFIXES:
        raise ValueError(f"{path}: unknown map format (expected .yaml, .yml or .npy)")
    pixels = np.full(prob.shape, 205, dtype=np.uint8)
    pixels[prob > OCCUPIED_THRESH] = 0
    pixels[prob < FREE_THRESH] = 254
    image = written_files(path)[1]
    header = f"P5\n{pixels.shape[1]} {pixels.shape[0]}\n255\n".encode()
    atomic_write(image, lambda f: f.write(header + pixels.tobytes()))
    ox, oy, yaw = (float(v) for v in grid.origin)
    text = (
        f"image: {image.name}\n"
        f"mode: trinary\n"
        f"resolution: {float(grid.resolution)!r}\n"
        f"origin: [{ox!r}, {oy!r}, {yaw!r}]\n"
        f"negate: 0\n"
        f"occupied_thresh: {OCCUPIED_THRESH}\n"
        f"free_thresh: {FREE_THRESH}\n"
    )
    atomic_write(path, lambda f: f.write(text.encode()))


def write_png(path: str | os.PathLike[str], image: np.ndarray) -> None:
    """Write an 8-bit gray ``(H, W)`` or RGB ``(H, W, 3)`` array as PNG, atomically.

    A minimal encoder (filter 0 on every row, zlib): no imaging library needed.

    Parameters
    ----------
    path : str or os.PathLike
        The PNG file.
    image : numpy.ndarray
        uint8 pixels, (H, W) gray or (H, W, 3) RGB.

    Raises
    ------
    ValueError
        If the array is not uint8, of another shape, or empty.
    OSError
        If the file cannot be written.
    """
    img = np.asarray(image)
    if img.dtype != np.uint8:
        raise ValueError(f"write_png needs uint8 pixels, got {img.dtype}")
    if img.ndim == 2:
        color_type = 0
    elif img.ndim == 3 and img.shape[2] == 3:
        color_type = 2
    else:
        raise ValueError(f"write_png needs (H, W) or (H, W, 3), got {img.shape}")
    h, w = img.shape[:2]
    if h == 0 or w == 0:
        raise ValueError("write_png needs a non-empty image")
    rows = np.ascontiguousarray(img).reshape(h, -1)
    raw = np.hstack([np.zeros((h, 1), np.uint8), rows]).tobytes()

    def chunk(tag: bytes, body: bytes) -> bytes:
        return struct.pack(">I", len(body)) + tag + body + struct.pack(">I", zlib.crc32(tag + body))

    png = (
        _PNG_MAGIC
        + chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, color_type, 0, 0, 0))
        + chunk(b"IDAT", zlib.compress(raw, 6))
        + chunk(b"IEND", b"")
    )
    atomic_write(Path(path), lambda f: f.write(png))
