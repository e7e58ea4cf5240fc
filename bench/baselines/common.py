"""What the baselines share: cell classes, warping of class images, the acceptance index."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from pgvd.grid import Grid

#: Acceptance-index threshold of the Hough-spectrum and exhaustive baselines (Birk and
#: Carpin's omega); fixed a priori, not tuned on the bench pairs.
OMEGA_ACCEPT = 0.9
#: An overlay with fewer agreeing+disagreeing cells than this is no evidence at all.
MIN_COMPARED = 500

FREE, OCCUPIED = 1, 2


@dataclass
class BaselineResult:
    """Outcome of one baseline merge: ``matrix`` maps B pixels to A pixels."""

    accepted: bool
    matrix: np.ndarray
    score: float


def classes(grid: Grid) -> np.ndarray:
    """uint8 class image: 0 unknown, FREE (log-odds < 0), OCCUPIED (log-odds > 0)."""
    out = np.zeros(grid.shape, np.uint8)
    out[grid.logodds < 0] = FREE
    out[grid.logodds > 0] = OCCUPIED
    return out


def warp_classes(labels_b: np.ndarray, matrix: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """B's class image resampled (nearest) into A's pixel frame of ``shape``."""
    swap = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    inv = swap @ np.linalg.inv(matrix) @ swap  # A (row, col) -> B (row, col)
    return ndimage.affine_transform(
        labels_b, inv[:2, :2], offset=inv[:2, 2], output_shape=shape, order=0, cval=0
    )


def acceptance_index(labels_a: np.ndarray, labels_b: np.ndarray, matrix: np.ndarray) -> float:
    """Birk and Carpin's omega = agree / (agree + disagree) of the overlaid maps.

    Cells agree when both are free or both occupied and disagree when one is
    free and the other occupied; 0 when fewer than MIN_COMPARED cells compare.
    """
    wb = warp_classes(labels_b, matrix, labels_a.shape)
    both = (labels_a > 0) & (wb > 0)
    agree = int(np.count_nonzero(both & (labels_a == wb)))
    disagree = int(np.count_nonzero(both)) - agree
    if agree + disagree < MIN_COMPARED:
        return 0.0
    return agree / (agree + disagree)


def rotation_about(psi: float, centre_from: np.ndarray, centre_to: np.ndarray) -> np.ndarray:
    """Pixel-frame rotation by ``psi`` (eq. (2)'s sense) taking ``centre_from`` to ``centre_to``."""
    c, s = np.cos(psi), np.sin(psi)
    rot = np.array([[c, s], [-s, c]])
    m = np.eye(3)
    m[:2, :2] = rot
    m[:2, 2] = np.asarray(centre_to) - rot @ np.asarray(centre_from)
    return m


def translation(tx: float, ty: float) -> np.ndarray:
    """3x3 pixel translation."""
    return np.array([[1.0, 0.0, tx], [0.0, 1.0, ty], [0.0, 0.0, 1.0]])
