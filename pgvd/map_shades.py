"""map_server pixel semantics: an image's gray shades to occupancy probabilities.

A map_server image carries classes, not confidences, so the classes get definite
probabilities: occupied :data:`P_OCCUPIED` (log-odds +2.2), free :data:`P_FREE`
(log-odds -2.2), unknown 0.5 (log-odds 0, eq. (9)).

ROS1 ``image_loader``: ``shade`` is the gray value in 0..255 (RGB/RGBA averaged over
the colour channels; 16-bit scaled to 0..255), inverted when ``negate`` is set;
``p = (255 - shade) / 255``.

* ``trinary`` (default): ``p > occupied_thresh`` occupied, ``p < free_thresh``
  free, anything else unknown.
* ``scale``: occupied/free as trinary; a pixel with alpha < 255 is unknown; in
  between, the ROS occupancy ``ratio = (p - free_thresh) / (occupied_thresh -
  free_thresh)`` is scaled linearly into ``[P_FREE, P_OCCUPIED]``.
* ``raw``: ``shade`` is the ROS occupancy value itself: 0..100 is scaled
  linearly into ``[P_FREE, P_OCCUPIED]``, anything above 100 is unknown.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pgvd.map_errors import MapFormatError

#: Probability given to an occupied map_server cell (log-odds ~ +2.2).
P_OCCUPIED = 0.9
#: Probability given to a free map_server cell (log-odds ~ -2.2).
P_FREE = 0.1
#: ROS map_server default thresholds, also used to classify a Grid's cells on writing.
OCCUPIED_THRESH = 0.65
FREE_THRESH = 0.196
#: The values of a map_server YAML's ``mode``.
MODES = ("trinary", "scale", "raw")


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


def check_has_occupied(path: Path, prob: np.ndarray) -> None:
    """``MapFormatError`` unless some cell of the map ``path`` read as ``prob`` is occupied."""
    if not np.any(prob > OCCUPIED_THRESH):
        raise MapFormatError(path, "map has no occupied cells")
