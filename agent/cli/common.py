"""What every ``pgvd`` sub-command shares: the exit codes, :class:`CliError`, the fleet key.

Exit codes: 0 success; 1 the command ran but did not achieve what it was asked (``pgvd demo``
without agreement, or standard output closed before everything was written); 2 bad input,
reported as one line on stderr; 3 the two maps of ``pgvd merge`` do not overlap.
"""

from __future__ import annotations

import importlib
from pathlib import Path

EXIT_OK = 0
EXIT_FAILED = 1
EXIT_BAD_INPUT = 2
EXIT_NO_OVERLAP = 3


class CliError(Exception):
    """A user error: printed as one line on stderr, exit code 2."""


def check_resolution_option(resolution: float) -> None:
    """``CliError`` naming ``--resolution`` unless it is an occupancy grid's cell size.

    Parameters
    ----------
    resolution : float
        The option's value, metres per cell (:func:`pgvd.grid.check_cell_size`).
    """
    # imported here: pgvd.grid loads numpy, which `pgvd --help` and `pgvd status` never need
    from pgvd.grid import check_cell_size

    try:
        check_cell_size(resolution)
    except ValueError as exc:
        raise CliError(f"--resolution {resolution:g}: {exc}") from None


def read_fleet_key(path: Path | None) -> bytes | None:
    """The fleet key in a file, for the HMAC every message of the fleet carries.

    Parameters
    ----------
    path : Path or None
        The key file; surrounding whitespace is not part of the key.

    Returns
    -------
    bytes or None
        The key, or None without a path (an unauthenticated fleet).

    Raises
    ------
    CliError
        When the file cannot be read or holds only whitespace.
    """
    if path is None:
        return None
    try:
        key = path.read_bytes().strip()
    except OSError as exc:
        raise CliError(f"cannot read key file: {exc.strerror}: {path}") from None
    if not key:
        raise CliError(f"key file is empty: {path}")
    return key


def require_extra(module: str, extra: str, needed_by: str) -> None:
    """Refuse, in one line, an option whose optional dependency is not installed.

    Parameters
    ----------
    module : the import name of the dependency (``rosbags``, ``foxglove``).
    extra : the project extra that installs it (``ros2``, ``view``).
    needed_by : what asked for it, for the message (``--source ros2:``).

    Raises
    ------
    CliError
        When ``module`` cannot be imported.
    """
    try:
        importlib.import_module(module)
    except ImportError:
        raise CliError(
            f"{needed_by} needs {module}, which is not installed: pip install 'pgvd-fleet[{extra}]'"
        ) from None
