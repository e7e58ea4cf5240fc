"""The one-line error of every map reader, and the file checks all readers share.

Every problem with a map file raises :class:`MapFormatError`, a ``ValueError`` whose
message is one line naming the file and the problem.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from pgvd.grid import check_cell_size

#: The problem named when a map path is a directory.
IS_DIRECTORY = "is a directory, not a map file"


class MapFormatError(ValueError):
    """A map file that cannot be read; the message is one line naming the file."""

    def __init__(self, path: str | os.PathLike[str], problem: str) -> None:
        self.path = str(path)
        self.problem = " ".join(str(problem).split())  # one line, whatever the cause said
        super().__init__(f"{self.path}: {self.problem}")


@contextmanager
def map_file_errors(path: Path) -> Iterator[None]:
    """Turn the ``OSError`` of opening or reading the map file ``path`` into its one line.

    Raises
    ------
    MapFormatError
        If the file is missing, a directory or unreadable.
    """
    try:
        yield
    except FileNotFoundError:
        raise MapFormatError(path, "no such file") from None
    except IsADirectoryError:
        raise MapFormatError(path, IS_DIRECTORY) from None
    except OSError as exc:
        raise MapFormatError(path, f"cannot read: {exc.strerror or exc}") from None


def read_map_bytes(path: Path) -> bytes:
    """The whole content of a map file, with :func:`map_file_errors`'s errors."""
    with map_file_errors(path):
        return path.read_bytes()


def check_map_size(path: Path, width: int, height: int, max_cells: int) -> None:
    """``MapFormatError`` unless a ``width`` x ``height`` map is non-empty and at most
    ``max_cells`` cells (checked on a header, before any pixel is decoded)."""
    if width <= 0 or height <= 0:
        raise MapFormatError(path, f"empty map ({width}x{height} cells)")
    if width * height > max_cells:
        raise MapFormatError(
            path, f"map of {width}x{height} cells exceeds the limit of {max_cells} cells"
        )


def check_map_resolution(path: Path, res: float) -> None:
    """``MapFormatError`` unless the cell size ``res`` is one of an occupancy grid
    (:func:`pgvd.grid.check_cell_size`)."""
    try:
        check_cell_size(res)
    except ValueError as exc:
        raise MapFormatError(path, f"resolution: {exc}") from None
