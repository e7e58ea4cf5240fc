"""Alignment of B's walls on A's at full resolution (eqs. (1)-(2)) and its misfit.

* :func:`refine` is trimmed point-to-point ICP;
  :func:`refine_point_to_line` a robust point-to-line fit that does not stop
  short along corridors.
* :func:`residual_distortion` measures the local misfit left after the rigid fit.
* :func:`alignment_fit` gives the Gauss-Newton terms of the alignment cost at
  its minimum, from which :mod:`pgvd.covariance` makes the covariance.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pgvd.grid import heading, rigid_matrix
from pgvd.sampling import subsample
from pgvd.walls import Walls, nearest_walls, transform_points, wall_cells, wall_normals


def _fit_rigid(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """Least-squares rigid matrix (eq. (1) convention) with ``dst ~ R src + t``."""
    ms, md = src.mean(axis=0), dst.mean(axis=0)
    s, d = src - ms, dst - md
    phi = np.arctan2(np.sum(s[:, 0] * d[:, 1] - s[:, 1] * d[:, 0]), np.sum(s * d))
    m = rigid_matrix(-phi, 0.0, 0.0)
    t = md - m[:2, :2] @ ms
    m[:2, 2] = t
    return m


def refine(
    walls_a: Walls,
    walls_b: np.ndarray,
    matrix: np.ndarray,
    radii: tuple[float, ...] = (12.0, 8.0, 5.0, 3.0, 2.0),
    iterations: int = 4,
    max_points: int = 3000,
) -> np.ndarray:
    """Trimmed point-to-point ICP of B's wall cells onto A's, from ``matrix`` (B->A pixels).

    Correspondences farther than the current radius are dropped; the radius
    shrinks over ``radii`` so the coarse estimate is pulled in, then tightened.
    All but the last radius use an even subsample of ``max_points`` cells.

    Parameters
    ----------
    walls_a : scipy.spatial.cKDTree or WallMap
        A's wall cells ``(x, y)``.
    walls_b : numpy.ndarray
        (N, 2) B's wall cells ``(x, y)``.
    matrix : numpy.ndarray
        3x3 starting transform, B pixel -> A pixel.
    radii : tuple of float, optional
        Correspondence radii in cells, one stage each.
    iterations : int, optional
        Iterations per radius at most.
    max_points : int, optional
        Subsample size of the early stages.

    Returns
    -------
    numpy.ndarray
        The refined 3x3 rigid matrix (eqs. (1)-(2)), B pixel -> A pixel.
    """
    m = matrix.copy()
    sub = subsample(walls_b, max_points)
    for k, radius in enumerate(radii):
        pts = walls_b if k == len(radii) - 1 else sub
        for _ in range(iterations):
            dist, idx = nearest_walls(walls_a, transform_points(m, pts), radius)
            ok = np.isfinite(dist)
            if ok.sum() < 10:
                return m
            new = _fit_rigid(pts[ok], wall_cells(walls_a)[idx[ok]])
            step = np.abs(new - m).max()
            m = new
            if step < 1e-3:
                break
    return m


@dataclass(frozen=True)
class LineFit:
    """Point-to-line residuals of B's walls near A's at one pose (see :func:`point_to_line`)."""

    cells: np.ndarray  # (M, 2) B's wall cells within the radius, in B's frame
    moved: np.ndarray  # (M, 2) the same cells moved into A
    res: np.ndarray  # (M,) n_i . (R x_i + t - y_i)
    jac: np.ndarray  # (M, 3) d res / d (tx, ty, psi)


def point_to_line(walls_a: Walls, pts: np.ndarray, matrix: np.ndarray, radius: float) -> LineFit:
    """Residuals along A's wall normals, and their Jacobian, of B's cells within ``radius``.

    ``r_i = n_i . (R x_i + t - y_i)`` with ``y_i`` the nearest wall cell of A and
    ``n_i`` A's wall normal there; ``J_i = [n_x, n_y, n_i . dR/dpsi x_i]``
    (eqs. (1)-(2)).
    """
    moved = transform_points(matrix, pts)
    dist, idx = nearest_walls(walls_a, moved, radius)
    ok = np.isfinite(dist)
    x, y = pts[ok], wall_cells(walls_a)[idx[ok]]
    n = wall_normals(walls_a, idx[ok]) if ok.any() else np.zeros((0, 2))
    psi = heading(matrix)
    c, s = np.cos(psi), np.sin(psi)
    dx = np.column_stack([-s * x[:, 0] + c * x[:, 1], -c * x[:, 0] - s * x[:, 1]])
    jac = np.column_stack([n[:, 0], n[:, 1], np.sum(n * dx, axis=1)])
    return LineFit(x, moved[ok], np.sum(n * (moved[ok] - y), axis=1), jac)


def refine_point_to_line(
    walls_a: Walls,
    walls_b: np.ndarray,
    matrix: np.ndarray,
    radius: float = 3.0,
    scale: float = 1.0,
    iterations: int = 8,
    max_points: int = 4000,
) -> np.ndarray:
    """Robust point-to-line alignment of B's walls on A's, from ``matrix`` (B->A pixels).

    Point-to-point ICP (:func:`refine`) stops a fraction of a degree off along
    straight corridors, where a wall cell may slide along the wall at no cost.
    Here each B wall cell within ``radius`` of A's walls pulls only along A's
    wall normal ``n_i`` (residual ``r_i = n_i . (R x_i + t - y_i)``, Jacobian as
    in :func:`alignment_fit`, eqs. (1)-(2)), and Gauss-Newton steps
    weigh it by the Cauchy weight ``1 / (1 + (r_i / scale)^2)``: a drifted map
    has no single rigid fit, and the robust loss lets the consistent part of
    the overlap decide instead of averaging the misfit over all of it.

    Parameters
    ----------
    walls_a : scipy.spatial.cKDTree or WallMap
        A's wall cells ``(x, y)``.
    walls_b : numpy.ndarray
        (N, 2) B's wall cells ``(x, y)``.
    matrix : numpy.ndarray
        3x3 starting rigid transform, B pixel -> A pixel.
    radius : float, optional
        Correspondences farther than this (pixels) are dropped.
    scale : float, optional
        Scale (pixels) of the Cauchy loss.
    iterations : int, optional
        Gauss-Newton steps at most.
    max_points : int, optional
        Even subsample of B's walls used.

    Returns
    -------
    numpy.ndarray
        The refined 3x3 rigid matrix, B pixel -> A pixel.
    """
    pts = subsample(walls_b, max_points)
    m = matrix.copy()
    for _ in range(iterations):
        fit = point_to_line(walls_a, pts, m, radius)
        if len(fit.res) < 10:
            break
        jac, res = fit.jac, fit.res
        psi = heading(m)
        w = 1.0 / (1.0 + (res / scale) ** 2)
        # a tiny ridge keeps a corridor's free direction from blowing the step up
        step = np.linalg.solve((jac * w[:, None]).T @ jac + 1e-6 * np.eye(3), -(jac.T @ (w * res)))
        m = rigid_matrix(psi + step[2], m[0, 2] + step[0], m[1, 2] + step[1])
        if np.abs(step).max() < 1e-4:
            break
    return m


def residual_distortion(
    walls_a: Walls,
    walls_b: np.ndarray,
    matrix: np.ndarray,
    block: float = 100.0,
    radius: float = 10.0,
    min_points: int = 60,
    max_points: int = 20000,
) -> float:
    """Largest local misfit (pixels) of B's walls on A's after the rigid ``matrix``.

    A drifted map has no single rigid fit: the overlap is cut into
    ``block``-pixel squares (A's frame) and each square's own translation
    ``d`` is fitted point-to-line, ``min sum (n_i . (d - r_i))^2`` over the
    residuals ``r_i`` of B's walls within ``radius`` of A's (``n_i`` A's wall
    normals, as in :func:`alignment_fit`).  Squares whose walls run one
    way only (the fit along the wall is free) or with fewer than
    ``min_points`` walls are skipped.

    Parameters
    ----------
    walls_a : scipy.spatial.cKDTree or WallMap
        A's wall cells ``(x, y)``.
    walls_b : numpy.ndarray
        (N, 2) B's wall cells ``(x, y)``.
    matrix : numpy.ndarray
        3x3 rigid transform (eqs. (1)-(2)), B pixel -> A pixel.
    block : float, optional
        Side of the squares, pixels.
    radius : float, optional
        B's walls farther than this from A's are not part of the overlap.
    min_points : int, optional
        Fewest wall cells of a square that is fitted.
    max_points : int, optional
        An even subsample of at most this many of B's walls is used, each kept
        cell counting for the cells between it and the next (``min_points``).

    Returns
    -------
    float
        The largest ``|d|`` over the squares, pixels; 0 when none qualifies.
        On the development log pairs at their true pose it is a few pixels
        for rigid pairs (map noise, thick walls: median 2.5) and more with
        odometry drift (median 4.0), so it flags drift, it does not measure
        it exactly.
    """
    pts = subsample(walls_b, max_points)
    stride = len(walls_b) / max(1, len(pts))
    fit = point_to_line(walls_a, pts, matrix, radius)
    if len(fit.res) * stride < min_points:
        return 0.0
    n, r = fit.jac[:, :2], -fit.res
    keys = np.floor(fit.moved / block).astype(np.int64)
    keys -= keys.min(axis=0)
    _, group, counts = np.unique(
        keys[:, 0] * (keys[:, 1].max() + 1) + keys[:, 1], return_inverse=True, return_counts=True
    )
    # per square: the normal equations sum n n^T d = sum n r, summed by bincount
    terms = (n[:, 0] ** 2, n[:, 0] * n[:, 1], n[:, 1] ** 2, n[:, 0] * r, n[:, 1] * r)
    sxx, sxy, syy, bx, by = (np.bincount(group, t, counts.size) for t in terms)
    info = np.stack([np.stack([sxx, sxy], -1), np.stack([sxy, syy], -1)], -2)
    lo, hi = np.linalg.eigvalsh(info).T
    fitted = (counts * stride >= min_points) & (lo >= 0.1 * hi)
    if not fitted.any():
        return 0.0
    d = np.linalg.solve(info[fitted], np.column_stack([bx, by])[fitted][..., None])[..., 0]
    return float(np.hypot(d[:, 0], d[:, 1]).max())


@dataclass(frozen=True)
class AlignmentFit:
    """The point-to-line alignment of B's walls on A's at a given matrix (Gauss-Newton terms).

    Attributes
    ----------
    info : 3x3 ``J^T J`` over ``(tx, ty, psi)`` (psi about B's pixel origin, eq. (1)).
    sigma2 : residual variance along A's wall normals, px^2 (at least 1/12, quantisation).
    centroid : ``(x, y)`` mean of those cells in B's pixels.
    psi : heading of the matrix, eq. (2).
    """

    info: np.ndarray
    sigma2: float
    centroid: np.ndarray
    psi: float


def alignment_fit(
    walls_a: Walls,
    walls_b: np.ndarray,
    matrix: np.ndarray,
    radius: float = 2.0,
    max_points: int = 4000,
) -> AlignmentFit | None:
    """Gauss-Newton terms of the point-to-line alignment of B's walls on A's at ``matrix``.

    Each wall cell of B that lands within ``radius`` of A's walls gives a
    residual ``r_i = n_i . (R x_i + t - y_i)`` along A's wall normal ``n_i``
    with Jacobian ``J_i = [n_x, n_y, n_i . dR/dpsi x_i]`` (the ``r1, r2`` of
    eq. (7)).  An even subsample of at most ``max_points`` cells is used
    (:func:`pgvd.sampling.subsample`); ``info`` is scaled back to all of B's
    walls, each kept cell standing for the cells between it and the next.

    Parameters
    ----------
    walls_a : scipy.spatial.cKDTree or WallMap
        A's wall cells ``(x, y)``.
    walls_b : numpy.ndarray
        (N, 2) B's wall cells ``(x, y)``.
    matrix : numpy.ndarray
        3x3 transform at the optimum, B pixel -> A pixel.
    radius : float, optional
        Cells of B farther than this from A's walls are not counted.
    max_points : int, optional
        Subsample size of B's walls.

    Returns
    -------
    AlignmentFit or None
        None when fewer than 3 cells of B land near A's walls.
    """
    pts = subsample(walls_b, max_points)
    fit = point_to_line(walls_a, pts, matrix, radius)
    if len(fit.res) < 3:
        return None
    x, res = fit.cells, fit.res
    psi = heading(matrix)
    info = fit.jac.T @ fit.jac
    # a tiny prior keeps a degenerate direction finite instead of singular
    info += np.diag([1e-9, 1e-9, 1e-9 * max(1.0, float(np.abs(x).max())) ** 2])
    return AlignmentFit(
        info=info * (len(walls_b) / len(pts)),
        sigma2=max(float(np.mean(res**2)), 1.0 / 12.0),
        centroid=x.mean(axis=0),
        psi=float(psi),
    )
