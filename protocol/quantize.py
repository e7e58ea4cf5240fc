"""Log-odds (eq. (9)) to int8 and back, with one fixed scale for the whole fleet.

The scale maps the clip limit of :data:`pgvd.grid.LOGODDS_LIMIT` to 127 so that
nothing a :class:`pgvd.grid.Grid` can hold is clipped on the wire.  Unknown
(log-odds exactly 0) stays exactly 0, and a cell that holds any knowledge,
however little, never becomes 0: fusion (33) adds log-odds, so erasing weak
evidence on the wire would make two agents disagree about what is unknown.
"""

from __future__ import annotations

import numpy as np

from pgvd.grid import LOGODDS_LIMIT

#: Log-odds per int8 step: +-LOGODDS_LIMIT maps to +-127.
SCALE = LOGODDS_LIMIT / 127.0


def quantise(logodds: np.ndarray) -> np.ndarray:
    """Quantise log-odds to int8 steps of :data:`SCALE`.

    Rounds to the nearest step, except that nonzero values below half a step
    go to +-1 (away from zero) rather than to 0, so no knowledge is erased.
    Values beyond +-LOGODDS_LIMIT saturate at +-127.

    Parameters
    ----------
    logodds : ndarray of finite floats, log-odds of eq. (9); 0 means unknown.

    Returns
    -------
    ndarray of int8, same shape.

    Raises
    ------
    ValueError
        If any value is NaN or infinite.
    """
    lo = np.asarray(logodds, dtype=np.float32)
    if not np.isfinite(lo).all():
        raise ValueError("log-odds must be finite to be quantised")
    steps = np.rint(lo / np.float32(SCALE))
    np.clip(steps, -127, 127, out=steps)
    q = steps.astype(np.int8)
    # Only cells that rounded to 0 need the away-from-zero rule.
    weak = (q == 0) & (lo != 0)
    if weak.any():
        q[weak] = np.where(lo[weak] > 0, 1, -1).astype(np.int8)
    return q


def dequantise(q: np.ndarray) -> np.ndarray:
    """Log-odds (float32) of int8 steps; ``quantise(dequantise(q)) == q`` for every int8 ``q``."""
    q = np.asarray(q)
    if q.dtype != np.int8:
        raise ValueError(f"quantised cells must be int8, got {q.dtype}")
    return q.astype(np.float32) * np.float32(SCALE)
