"""Map images: PGM (P2/P5) and PNG decoded to gray shades; PGM and PNG encoders.

Decoding gives ``(shade 0..255, alpha 0..255 or None)`` as float32, for
:mod:`pgvd.map_shades` to read as occupancy.  A bare ``.pgm`` or ``.png`` (an image
without its YAML, as map collections often ship them) is a map too (:func:`pgvd.io.read_map`).
"""

from __future__ import annotations

import os
import struct
import zlib
from io import BytesIO
from pathlib import Path

import numpy as np

from pgvd.atomic import atomic_write
from pgvd.map_errors import MapFormatError, check_map_size, read_map_bytes

#: Suffixes of bare map images, read without a YAML (see :func:`pgvd.io.read_map`).
IMAGE_SUFFIXES = (".pgm", ".png")

_PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


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
    check_map_size(path, width, height, max_cells)
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
    check_map_size(path, width, height, max_cells)
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


def decode_image(path: Path, max_cells: int) -> tuple[np.ndarray, np.ndarray | None]:
    """Read a PGM or PNG map image as ``(shade, alpha or None)``, float32 in 0..255.

    Parameters
    ----------
    path : pathlib.Path
        The image; its format is told by its first bytes, not its name.
    max_cells : int
        Refuse images with more pixels than this (checked on the header).

    Raises
    ------
    MapFormatError
        Unreadable, truncated or malformed image, of another format, empty or too large.
    """
    data = read_map_bytes(path)
    if data[:2] in (b"P5", b"P2"):
        return _decode_pgm(data, path, max_cells)
    if data[:8] == _PNG_MAGIC:
        return _decode_png(data, path, max_cells)
    raise MapFormatError(path, "not a PGM (P2/P5) or PNG image")


def pgm_bytes(pixels: np.ndarray) -> bytes:
    """A binary (P5) 8-bit PGM of ``pixels``, an ``(H, W)`` uint8 array."""
    header = f"P5\n{pixels.shape[1]} {pixels.shape[0]}\n255\n".encode()
    return header + pixels.tobytes()


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
