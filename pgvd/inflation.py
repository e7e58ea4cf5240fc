"""Inflation of the pose covariance (3) where the overlap's evidence is thin.

:func:`pgvd.covariance.calibrated_covariance` scales the Gauss-Newton covariance
``sigma^2 (J^T J)^-1`` of the point-to-line fit (the ``r1, r2`` of eq. (7)) by
constants fitted on rich overlaps, where the wall normals point every way.
That covariance weighs a link in the pose graph and sets the blur a transformed
map is given (eqs. (4)-(8)); too narrow, it trusts a pose more than its errors
allow.  Two things the information matrix ``J^T J`` cannot see make it
overconfident where the evidence is thin:

* **Spurious information from normal noise.**  Each residual pulls along A's
  wall normal ``n_i``, estimated from a few neighbouring cells, so it is off
  the wall's true normal by a random angle ``delta``, ``E[sin^2 delta] = s^2``.  Along a
  straight corridor, where every true normal is across it, that jitter alone
  puts about ``s^2 N`` cells of information along the corridor (``N`` the
  matched cells).  In expectation, with ``T`` the translation block of the
  information::

      E[T_measured] = (1 - s^2) T_true + s^2 N I

  so the information that can be trusted in a direction ``u`` of eigenvalue
  ``lambda_u`` is ``(lambda_u - s^2 N) / (1 - s^2)``.
* **Correlated neighbouring cells.**  Residuals of neighbouring cells along a
  wall share the wall's shape and the laser's view of it: ``ell`` cells of
  wall make about one independent measurement.  An accepted pose is pinned in
  every direction by at least one such piece, so the trusted information in a
  direction is at least ``ell`` cells; and the whole fit rests on
  ``n = N / ell`` independent measurements for its 3 parameters, so the
  residual variance it was scaled by is low by ``n / (n - 3)`` (to first
  order ``1 + 3 / n``: few wall cells, a wider covariance).

The inflated covariance, at the centroid of the matched walls (where the heading
is nearly uncorrelated with the translation), with ``(lambda_u, u)`` the
eigenpairs of ``T`` and ``v_u = u^T Sigma_t u`` the variance along ``u`` of the
translation block ``Sigma_t`` of the covariance there::

    k_u = max(1, lambda_u / max((lambda_u - s^2 N) / (1 - s^2), ell))
    Sigma' = (1 + 3 / n) (Sigma + sum_u (k_u - 1) v_u u u^T)

Along each ``u`` the translation variance is multiplied by ``(1 + 3/n) k_u``; the
added terms are positive semi-definite and the factor at least 1, so it never
shrinks.  Rich overlaps (normals in every direction, thousands of cells) are
widened by about 10 %.  The two constants, ``s^2`` and ``ell``, are
measured on development pairs at their true poses, not fitted to the errors
(:class:`EvidenceModel`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pgvd.alignment import AlignmentFit, alignment_fit
from pgvd.covariance import calibrated_covariance
from pgvd.model_error import MODEL_ERROR_SCALE, model_error_covariance
from pgvd.walls import WallMap

#: Parameters of the pose (tx, ty, psi) of eq. (1): the degrees of freedom of the fit.
POSE_PARAMETERS = 3


@dataclass(frozen=True)
class EvidenceModel:
    """Constants of :func:`inflate`.

    Attributes
    ----------
    normal_noise : ``s^2 = E[sin^2 delta]``, ``delta`` the angle between a wall
        normal as the fit estimates it and the wall's true normal.
    correlation_m : length of wall (metres) that makes one independent
        measurement (``ell`` in cells at the fit's resolution).
    """

    normal_noise: float
    correlation_m: float


#: Measured by ``python3 -m bench covariance_evidence`` on development pairs of the
#: intel and freiburg-079 logs at their true poses: the normal noise from the angle
#: between A's and B's normals at matched wall cells (each map contributes half its
#: variance), the correlation length from the residuals of neighbouring cells
#: (``bench/results/covariance-evidence.md``: s^2 an rms angle of 15 degrees, ell 5.8
#: cells of 0.05 m).  On the pairs the covariance was calibrated on, the widened one
#: keeps its targets (``bench/results/covariance.md``).
MEASURED = EvidenceModel(normal_noise=0.0704, correlation_m=0.288)


def _check_square(name: str, m: np.ndarray, size: int) -> np.ndarray:
    m = np.asarray(m, dtype=float)
    if m.shape != (size, size):
        raise ValueError(f"{name} must be {size}x{size}, got shape {m.shape}")
    if np.isnan(m).any():
        raise ValueError(f"{name} holds NaN")
    finite = np.abs(m[np.isfinite(m)])
    scale = max(1.0, float(finite.max())) if finite.size else 1.0
    if not np.allclose(m, m.T, rtol=1e-6, atol=1e-12 * scale):
        raise ValueError(f"{name} must be symmetric")
    return m


def centroid_shift(centroid: np.ndarray, psi: float) -> np.ndarray:
    """The 3x3 ``A`` that moves a pose error from B's pixel origin to ``centroid``.

    A heading error ``dpsi`` about the origin moves the point ``c`` by
    ``dR/dpsi c dpsi`` (eq. (1)'s ``R = [[cos, sin], [-sin, cos]]``), so the
    error at ``c`` is ``A e`` with ``A = [[I, dR/dpsi c], [0, 1]]``.

    Parameters
    ----------
    centroid : numpy.ndarray
        ``(x, y)`` in B's pixels.
    psi : float
        Heading of the pose (rad).

    Returns
    -------
    numpy.ndarray
        3x3 matrix.
    """
    (cx, cy), c, s = np.asarray(centroid, dtype=float), np.cos(psi), np.sin(psi)
    a = np.eye(3)
    a[:2, 2] = [c * cy - s * cx, -c * cx - s * cy]
    return a


def direction_factors(
    translation_info: np.ndarray, normal_noise: float, piece_cells: float
) -> tuple[np.ndarray, np.ndarray]:
    """Variance factors ``k_u >= 1`` along the eigen-directions of the translation
    information (the module's first two effects).

    Parameters
    ----------
    translation_info : numpy.ndarray
        2x2 ``sum n_i n_i^T`` over the matched wall cells (translation block of
        ``J^T J``, eq. (7)); its trace is the number of cells ``N``.
    normal_noise : float
        ``s^2 = E[sin^2 delta]`` of a normal's angle error ``delta``, in ``[0, 0.5)``.
    piece_cells : float
        ``ell``, wall cells per independent measurement, > 0.

    Returns
    -------
    factors : numpy.ndarray
        (2,) ``k_u``, smallest information first.
    directions : numpy.ndarray
        2x2, column ``u`` the unit direction of ``factors[u]``.

    Raises
    ------
    ValueError
        If the information is not a finite symmetric positive semi-definite 2x2,
        or a constant is out of range.
    """
    t = _check_square("translation information", translation_info, 2)
    if not np.isfinite(t).all():
        raise ValueError("translation information must be finite")
    if not 0.0 <= normal_noise < 0.5:
        raise ValueError(f"normal noise must be in [0, 0.5), got {normal_noise}")
    if not piece_cells > 0:
        raise ValueError(f"cells per independent measurement must be > 0, got {piece_cells}")
    lam, vec = np.linalg.eigh(t)
    if lam[0] < -1e-9 * max(1.0, lam[1]):
        raise ValueError(f"translation information must be positive semi-definite: {lam}")
    lam = np.maximum(lam, 0.0)
    trusted = np.maximum((lam - normal_noise * lam.sum()) / (1.0 - normal_noise), piece_cells)
    return np.maximum(1.0, lam / trusted), vec


def dof_factor(cells: float, piece_cells: float) -> float:
    """``1 + 3 / n``, ``n = cells / piece_cells`` independent measurements: the first-order
    bias ``n / (n - 3)`` of a residual variance that fits the 3 pose parameters.

    Parameters
    ----------
    cells : float
        Matched wall cells ``N`` (trace of the translation information), >= 0.
    piece_cells : float
        ``ell``, wall cells per independent measurement, > 0.

    Returns
    -------
    float
        The factor, >= 1 (infinite without cells).

    Raises
    ------
    ValueError
        If ``cells`` is negative or NaN, or ``piece_cells`` not positive.
    """
    if not cells >= 0:
        raise ValueError(f"cells must be >= 0, got {cells}")
    if not piece_cells > 0:
        raise ValueError(f"cells per independent measurement must be > 0, got {piece_cells}")
    if cells == 0:
        return float("inf")
    return 1.0 + POSE_PARAMETERS * piece_cells / cells


def inflate(
    cov: np.ndarray,
    fit: AlignmentFit | None,
    resolution: float,
    model: EvidenceModel = MEASURED,
) -> np.ndarray:
    """``cov`` inflated where the fit's evidence is thin (module docstring, eq. (3)).

    Parameters
    ----------
    cov : numpy.ndarray
        3x3 covariance of ``(tx px, ty px, psi rad)`` about B's pixel origin, of
        the pose ``fit`` is about (:func:`pgvd.covariance.calibrated_covariance`).
    fit : AlignmentFit or None
        The point-to-line fit at that pose (:func:`pgvd.alignment.alignment_fit`);
        None (no fit) leaves ``cov`` as it is.
    resolution : float
        Metres per cell of the fit's maps.
    model : EvidenceModel, optional
        The constants; by default those measured on the development pairs.

    Returns
    -------
    numpy.ndarray
        3x3 covariance, ``>= cov`` (their difference is positive semi-definite).

    Raises
    ------
    ValueError
        If ``cov`` is not a symmetric 3x3 without NaN, or ``resolution`` not positive.
    """
    cov = _check_square("covariance", cov, 3)
    if not resolution > 0:
        raise ValueError(f"resolution must be > 0, got {resolution}")
    if fit is None or not np.isfinite(cov).all():
        return cov
    piece = model.correlation_m / resolution
    a = centroid_shift(fit.centroid, fit.psi)
    a_inv = np.linalg.inv(a)
    # the information about the centroid: e_c = A e, so H_c = A^-T H A^-1
    info_c = a_inv.T @ fit.info @ a_inv
    t = 0.5 * (info_c[:2, :2] + info_c[:2, :2].T)
    factors, vec = direction_factors(t, model.normal_noise, piece)
    at_c = a @ cov @ a.T
    along = np.einsum("iu,ij,ju->u", vec, at_c[:2, :2], vec)
    added = np.zeros((3, 3))
    added[:2, :2] = (vec * ((factors - 1.0) * along)) @ vec.T
    out = dof_factor(float(np.trace(t)), piece) * (cov + a_inv @ added @ a_inv.T)
    return 0.5 * (out + out.T)


def inflated_covariance(
    fine_a: WallMap, fine_b: WallMap, matrix: np.ndarray, resolution: float
) -> np.ndarray:
    """The covariance (3) a merge reports for the pose ``matrix`` of B on A.

    :func:`pgvd.covariance.calibrated_covariance` of the point-to-line fit of B's
    walls on A's at ``matrix`` (:func:`pgvd.alignment.alignment_fit`), inflated
    where that fit's evidence is thin (:func:`inflate`), plus the error a rigid fit
    cannot see, the disagreement of the overlap's parts where a map is bent
    (:func:`pgvd.model_error.model_error_covariance`, weighed by
    :data:`pgvd.model_error.MODEL_ERROR_SCALE`).  The pose graph weighs the link by it
    and the fused map blurs the transformed map with it (eqs. (4)-(8)).  The merge,
    :mod:`pgvd.verify` and an agent's candidate link all report this one, so that a link
    verified later carries the covariance its merge would have.

    Parameters
    ----------
    fine_a, fine_b : WallMap
        The two maps at the fit's resolution.
    matrix : numpy.ndarray
        3x3 B pixel -> A pixel.
    resolution : float
        Metres per cell.

    Returns
    -------
    numpy.ndarray
        3x3 covariance over ``(tx px, ty px, psi rad)`` about B's pixel origin.
    """
    fit = alignment_fit(fine_a.tree, fine_b.walls, matrix)
    cov = inflate(calibrated_covariance(fit, resolution), fit, resolution)
    if fit is None:
        return cov
    bent = model_error_covariance(fine_a.tree, fine_b.walls, matrix)
    return cov + MODEL_ERROR_SCALE * bent
