"""``.npy`` maps: 2-D arrays of occupancy probabilities, 0.5 = unknown, with no cell size."""

from __future__ import annotations

from pathlib import Path
from tokenize import TokenError

import numpy as np

from pgvd.grid import Grid
from pgvd.map_errors import (
    MapFormatError,
    check_map_resolution,
    check_map_size,
    map_file_errors,
)
from pgvd.map_shades import check_has_occupied

#: Resolution given to ``.npy`` maps, which carry none.
NPY_RESOLUTION = 0.05


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


def read_npy_map(path: Path, max_cells: int, resolution: float) -> Grid:
    """Read a ``.npy`` array of occupancy probabilities as a log-odds grid (eq. (9)).

    Parameters
    ----------
    path : pathlib.Path
        2-D numeric array of probabilities in [0, 1], 0.5 = unknown.
    max_cells : int
        Refuse arrays with more cells than this (checked on the header).
    resolution : float
        Metres per cell, which the array does not carry.

    Returns
    -------
    Grid
        The map, origin ``(0, 0, 0)``.

    Raises
    ------
    MapFormatError
        Unreadable or damaged file, an array of another rank or kind, too many cells,
        NaN or out-of-range values, no occupied cell, a cell size outside
        :data:`pgvd.grid.CELL_SIZE_RANGE`.
    """
    check_map_resolution(path, resolution)
    prob = _read_npy_array(path, max_cells).astype(np.float64)
    if np.isnan(prob).any():
        raise MapFormatError(path, f"{int(np.isnan(prob).sum())} NaN value(s)")
    if prob.min() < 0.0 or prob.max() > 1.0:
        raise MapFormatError(
            path, f"probabilities must lie in [0, 1], got {prob.min():g}..{prob.max():g}"
        )
    check_has_occupied(path, prob)
    return Grid.from_probability(prob, resolution)


def _read_npy_array(path: Path, max_cells: int) -> np.ndarray:
    """The 2-D numeric array of a ``.npy`` file, its shape and dtype checked on the header
    before the data is read."""
    with map_file_errors(path):
        f = path.open("rb")
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
        check_map_size(path, shape[1], shape[0], max_cells)
        data = f.read()
    count = shape[0] * shape[1]
    if len(data) < count * dtype.itemsize:
        raise MapFormatError(
            path, f"truncated .npy: {len(data)} data bytes, need {count * dtype.itemsize}"
        )
    return np.frombuffer(data, dtype=dtype, count=count).reshape(
        shape, order="F" if fortran else "C"
    )
