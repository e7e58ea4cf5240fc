"""Map files: ROS ``map_server`` YAML + PGM/PNG, bare PGM/PNG images and ``.npy`` arrays.

Reading gives a log-odds :class:`~pgvd.grid.Grid` (eq. (9)): a map_server image's
classes get the definite probabilities of :mod:`pgvd.map_shades`, in its ``trinary``,
``scale`` or ``raw`` mode, ``negate`` honoured.  Every problem with a file raises
:class:`~pgvd.map_errors.MapFormatError`, a ``ValueError`` whose message is one line
naming the file and the problem.

A bare ``.pgm`` or ``.png`` (an image without its YAML, as map collections often ship
them) carries no cell size: it is read with one given by the caller, map_saver's thresholds
(occupied above 0.65, free below 0.196, so that its 0/205/254 pixels are occupied, unknown
and free) and the origin at ``(0, 0, 0)``.

The formats themselves live in :mod:`pgvd.map_yaml`, :mod:`pgvd.map_image` and
:mod:`pgvd.npy_map`; this module is the entry that picks one by the file's suffix.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from pgvd.atomic import atomic_write
from pgvd.grid import Grid
from pgvd.map_errors import IS_DIRECTORY, MapFormatError, check_map_resolution
from pgvd.map_image import IMAGE_SUFFIXES, decode_image, pgm_bytes, write_png
from pgvd.map_shades import (
    FREE_THRESH,
    OCCUPIED_THRESH,
    check_has_occupied,
    shade_to_probability,
)
from pgvd.map_yaml import (
    YAML_SUFFIXES,
    format_map_yaml,
    read_map_yaml,
    yaml_image_path,
    yaml_number,
)
from pgvd.npy_map import NPY_RESOLUTION, read_npy_map

__all__ = ["MAX_CELLS", "MapFormatError", "read_map", "write_map", "write_png", "written_files"]

#: Default limit on the number of cells of one map (8000 x 8000).
MAX_CELLS = 8000 * 8000


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
        raise MapFormatError(path, IS_DIRECTORY)
    suffix = path.suffix.lower()
    if suffix in YAML_SUFFIXES:
        return _read_yaml_map(path, max_cells)
    if suffix == ".npy":
        return read_npy_map(path, max_cells, npy_resolution)
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
    check_map_resolution(path, resolution)
    shade, alpha = decode_image(path, max_cells)
    prob = shade_to_probability(shade, alpha)
    check_has_occupied(path, prob)
    return Grid.from_probability(prob, resolution)


def _read_yaml_map(path: Path, max_cells: int) -> Grid:
    meta = read_map_yaml(path)
    image = yaml_image_path(path, str(meta["image"]))
    shade, alpha = decode_image(image, max_cells)
    prob = shade_to_probability(
        shade,
        alpha,
        mode=str(meta.get("mode", "trinary")),
        negate=meta["negate"] in (1, "true", "True"),
        occupied_thresh=yaml_number(meta, "occupied_thresh", path),
        free_thresh=yaml_number(meta, "free_thresh", path),
    )
    check_has_occupied(image, prob)
    ox, oy, yaw = meta["origin"]  # type: ignore[misc]
    return Grid.from_probability(prob, yaml_number(meta, "resolution", path), (ox, oy, yaw))


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
    atomic_write(image, lambda f: f.write(pgm_bytes(pixels)))
    text = format_map_yaml(image.name, grid.resolution, grid.origin)
    atomic_write(path, lambda f: f.write(text.encode()))
