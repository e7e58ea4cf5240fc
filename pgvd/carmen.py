"""CARMEN laser logs: the ``FLASER`` scans and corrected poses of Radish/Freiburg logs.

A ``*.log`` or ``*.log.gz`` file holds one message per line; only ``FLASER``
(front laser) lines are read, each giving a planar scan and the corrected pose
it was taken from.  These scans are what :mod:`pgvd.integrate` ray-casts into
occupancy grids (eq. (9)).  Every malformed line raises :class:`LogFormatError`
naming the file and line.
"""

from __future__ import annotations

import gzip
import math
import zlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

#: A FLASER line with more beams than this is refused as corrupt (real lasers give <= 1081).
MAX_BEAMS = 100_000


@dataclass(frozen=True)
class LaserScan:
    """One ``FLASER`` message: a planar scan and the pose it was taken from.

    Beam ``i`` of ``n`` points at ``theta - fov / 2 + i * fov / (n - 1)`` in the
    log's world frame (the CARMEN convention), where ``theta`` is ``pose[2]``.

    Attributes
    ----------
    timestamp : IPC timestamp of the message, seconds.
    ranges : (n,) float32 ranges in metres; values at the sensor's maximum
        (81.83 m in intel, 81.91 m in freiburg-079) mean "no return".
    pose : (3,) float64 corrected ``x, y, theta`` of the laser (metres, radians).
    odom : (3,) float64 raw odometry ``x, y, theta``.
    fov : field of view in radians (FLASER carries none; the logs use 180 degrees).
    """

    timestamp: float
    ranges: np.ndarray
    pose: np.ndarray
    odom: np.ndarray
    fov: float = math.pi

    def beam_angles(self) -> np.ndarray:
        """World-frame heading of every beam, radians, as float64."""
        n = self.ranges.shape[0]
        if n == 1:
            return np.array([self.pose[2]])
        return self.pose[2] - self.fov / 2 + np.arange(n) * (self.fov / (n - 1))


class LogFormatError(ValueError):
    """A malformed CARMEN log; the message reads ``<file>:<line>: <problem>``."""


def _parse_flaser(tokens: list[str]) -> LaserScan:
    """One FLASER line, already split, to a :class:`LaserScan`; ``ValueError`` on any flaw.

    Layout: ``FLASER n r1..rn x y theta odom_x odom_y odom_theta ipc_timestamp
    hostname logger_timestamp``.
    """
    if len(tokens) < 2:
        raise ValueError("FLASER line without a beam count")
    try:
        n = int(tokens[1])
    except ValueError:
        raise ValueError(f"beam count {tokens[1]!r} is not an integer") from None
    if not 1 <= n <= MAX_BEAMS:
        raise ValueError(f"beam count {n} outside 1..{MAX_BEAMS}")
    expected = n + 11
    if len(tokens) != expected:
        raise ValueError(f"FLASER with {n} beams needs {expected} fields, got {len(tokens)}")
    try:
        values = np.array(tokens[2 : n + 9], dtype=np.float64)
        logger_ts = float(tokens[n + 10])
    except ValueError:
        raise ValueError("non-numeric range, pose or timestamp") from None
    if not (np.all(np.isfinite(values)) and math.isfinite(logger_ts)):
        raise ValueError("range, pose or timestamp is not finite")
    ranges = values[:n]
    if np.any(ranges < 0):
        raise ValueError("negative range")
    return LaserScan(
        timestamp=float(values[n + 6]),
        ranges=ranges.astype(np.float32),
        pose=values[n : n + 3].copy(),
        odom=values[n + 3 : n + 6].copy(),
    )


def read_carmen(path: str | Path, max_scans: int | None = None) -> list[LaserScan]:
    """Read the ``FLASER`` scans of a CARMEN log (``.log`` or gzip ``.log.gz``).

    Other message types (``ODOM``, ``PARAM``, ``NEFF``, comments) are skipped.

    Parameters
    ----------
    path : the log file; gzip is detected from its magic bytes, not its name.
    max_scans : stop after this many scans (``None``: read all).

    Returns
    -------
    The scans in file order.

    Raises
    ------
    LogFormatError
        On a malformed FLASER line, undecodable text or a corrupt gzip stream,
        with the file name and 1-based line number.
    OSError
        If the file cannot be opened.
    """
    path = Path(path)
    if max_scans is not None and max_scans < 0:
        raise ValueError(f"max_scans must be >= 0, got {max_scans}")
    with open(path, "rb") as raw:
        gzipped = raw.read(2) == b"\x1f\x8b"
    scans: list[LaserScan] = []
    lineno = 0
    # Bytes lines decoded one at a time, so that every error names its exact line.
    with gzip.open(path, "rb") if gzipped else open(path, "rb") as fh:
        try:
            for lineno, raw_line in enumerate(fh, start=1):  # noqa: B007 (used below)
                if max_scans is not None and len(scans) >= max_scans:
                    break
                if not raw_line.startswith(b"FLASER"):
                    continue
                tokens = raw_line.decode("ascii").split()
                if tokens[0] == "FLASER":
                    scans.append(_parse_flaser(tokens))
        except UnicodeDecodeError:
            raise LogFormatError(f"{path}:{lineno}: FLASER line is not ASCII text") from None
        except ValueError as exc:
            raise LogFormatError(f"{path}:{lineno}: {exc}") from None
        except (EOFError, gzip.BadGzipFile, zlib.error) as exc:
            # A truncated gzip stream raises EOFError, a corrupt one BadGzipFile or zlib.error.
            raise LogFormatError(f"{path}:{lineno + 1}: corrupt gzip stream ({exc})") from None
    return scans
