"""A robot's placement in its anchor's pixels, snapped to a lattice before it is fused.

The pose graph (:func:`pgvd.posegraph.solve`) re-solves a component whenever any of its
links changes, and every placement then moves by a rounding-size amount.  The fusion keeps
each robot's warped layer (eq. (8), :class:`agent.fusecache.LayerCache`) for as long as
its placement is the same, so a placement that moved by 1e-12 px would re-warp the whole
component at every link change.  Snapping the placement to a lattice finer than anything
eq. (8) resolves makes such a re-solve re-warp nobody, and a placement that really moved
still re-warps.

The snapped placement is a function of the solve's output and the map's shape alone,
never of what a cache held before, so every agent snaps the same solution to the same
bytes (fleet invariant 2).
"""

from __future__ import annotations

import math

import numpy as np

from pgvd.grid import heading, rigid_matrix

#: Translation lattice, pixels: a snapped map is at most 1/64 px from where it was solved.
TRANSLATION_STEP_PX = 1.0 / 32.0
#: Heading lattice, as the arc it moves the map's far corner, pixels.
HEADING_ARC_PX = 1.0 / 32.0
#: Standard-deviation lattice on a log scale: 2^(1/32), steps of 2.2 %.
LOG_SIGMA_STEP = math.log(2.0) / 32.0
#: Correlation lattice.
CORRELATION_STEP = 0.02


def heading_step(shape: tuple[int, int]) -> float:
    """The heading lattice, radians, of a map of ``shape`` (rows, cols): the angle that moves
    its corner farthest from the rotation centre (its pixel origin, eq. (1)) by
    :data:`HEADING_ARC_PX`."""
    rows, cols = shape
    return HEADING_ARC_PX / max(math.hypot(rows - 1, cols - 1), 1.0)


def snap_placement(
    matrix: np.ndarray, covariance: np.ndarray, shape: tuple[int, int]
) -> tuple[np.ndarray, np.ndarray]:
    """``matrix`` (map px -> anchor px) and its ``covariance`` over ``(x px, y px, psi)``,
    eq. (3), snapped to the placement lattice of a map of ``shape``.

    Why these steps change eq. (8)'s layer by far less than anything measured of a global
    map (a cell, 0.1 degrees, an int8 log-odds step on the wire):

    - ``(tx, ty)`` to :data:`TRANSLATION_STEP_PX`: the warp moves by at most 1/64 px, a
      bilinear read changes by 1/64 of a neighbour's difference;
    - ``psi`` to :func:`heading_step`: no cell of the map moves by more than 1/64 px;
    - each standard deviation to a power of 2^(1/32): the blur of eqs. (4)-(8) widens or
      narrows by at most 1.1 %, well inside the 2 % its polar binning already allows
      (:func:`pgvd.uncertainty.rotation_blur`);
    - each correlation to :data:`CORRELATION_STEP` (at most 0.01 off), which shifts the
      rotation blur's centre and the Schur complement of :func:`pgvd.uncertainty.propagate`
      by about 1 % of the blur's own width.

    Measured on the layers of a 16-robot rebuild (``python3 -m bench globalmap``'s
    fleets), the 99th percentile of the change of a known cell's log-odds is about 0.02
    from the translation's snap, under 0.01 from the heading's and about 0.07 from the
    covariance's: as much as a 0.1 % change of ``sigma_psi`` gives, since the polar bins
    of :func:`pgvd.uncertainty.rotation_blur` are laid out anew for every ``sigma_psi``;
    the steps add nothing to eq. (8)'s own discretisation, and stay under half an int8
    step of the wire (0.157).  On the covariances a running 16-agent fleet's pose graph
    gives (wider heading uncertainty than the bench's), the covariance's snap changed a
    known cell by up to 0.31 at the 99th percentile, and a 0.1 % change of ``sigma_psi``
    alone by 0.33: the same rule (the snap is no coarser than the blur's own binning), at
    about one int8 step there.

    A correlation matrix that rounding made indefinite has its negative eigenvalues
    clipped and its diagonal rescaled to one, so the covariance stays positive
    semi-definite.  A standard deviation of 0 stays 0.  Inputs that are not finite are
    returned as given: the fusion's fallback handles them the same way on every agent.

    Parameters
    ----------
    matrix : numpy.ndarray
        3x3 rigid matrix of eqs. (1)-(2).
    covariance : numpy.ndarray
        3x3 covariance of ``matrix``, eq. (3).
    shape : tuple of int
        (rows, cols) of the map placed.

    Returns
    -------
    tuple of numpy.ndarray
        The snapped matrix and covariance, float64.
    """
    m = np.asarray(matrix, dtype=np.float64)
    c = np.asarray(covariance, dtype=np.float64)
    if not (np.isfinite(m).all() and np.isfinite(c).all()):
        return m, c
    psi_step = heading_step(shape)
    snapped = 0.0 + rigid_matrix(  # 0.0 +: no -0.0 from -sin(0)
        round(heading(m) / psi_step) * psi_step,
        round(m[0, 2] / TRANSLATION_STEP_PX) * TRANSLATION_STEP_PX,
        round(m[1, 2] / TRANSLATION_STEP_PX) * TRANSLATION_STEP_PX,
    )
    return snapped, snap_covariance(c)


def snap_covariance(c: np.ndarray) -> np.ndarray:
    """``c`` rebuilt from its snapped standard deviations and correlations, PSD."""
    variances = np.clip(np.diag(c), 0.0, None)
    sigma = np.sqrt(variances)
    known = sigma > 0
    sigma[known] = np.exp(np.round(np.log(sigma[known]) / LOG_SIGMA_STEP) * LOG_SIGMA_STEP)
    corr = np.zeros_like(c)
    both = np.outer(known, known)
    scale = np.sqrt(np.outer(variances, variances))
    corr[both] = np.clip(c[both] / scale[both], -1.0, 1.0)
    corr = np.round(corr / CORRELATION_STEP) * CORRELATION_STEP
    np.fill_diagonal(corr, known.astype(np.float64))
    evals, evecs = np.linalg.eigh(corr)
    if evals.min() < 0:
        corr = (evecs * np.clip(evals, 0.0, None)) @ evecs.T
        d = np.sqrt(np.diag(corr))
        d[d == 0] = 1.0
        corr = corr / np.outer(d, d)
    out = corr * np.outer(sigma, sigma)
    return (out + out.T) / 2.0
