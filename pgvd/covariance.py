"""The covariance of a merge's pose, eq. (3), calibrated on real pairs.

:func:`calibrated_covariance` turns the curvature of the alignment cost at its
minimum (:func:`pgvd.alignment.alignment_fit`) into a covariance: a Laplace
approximation inflated by the residual misfit, its heading widened, with
constants fitted on real pairs, that matches the errors the merge makes.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pgvd.alignment import AlignmentFit


@dataclass(frozen=True)
class CovarianceModel:
    """Constants of :func:`calibrated_covariance`.

    Attributes
    ----------
    correlation : wall cells per independent residual at a residual of grid
        quantisation (scales the Laplace covariance).
    misfit_power : how steeply the covariance grows with the residual variance
        ``sigma^2`` beyond quantisation: ``(12 sigma^2) ** (misfit_power - 1)``.
    floor_m : isotropic translation floor (metres) at the centroid of the matched walls.
    floor_rad : heading floor (radians).
    heading_scale : factor on the heading standard deviation of the inflated Laplace
        term, about the centroid of the matched walls (1: the Laplace shape as it is).
    """

    correlation: float
    misfit_power: float
    floor_m: float
    floor_rad: float
    heading_scale: float = 1.0


#: Fitted by ``python3 -m bench.covariance fit`` (maximum likelihood) on one half of
#: the development pairs (intel and freiburg-079 logs, 0.05 m cells) as the merge in use
#: accepts them; reported on the other half in ``bench/results/covariance.md``.  The floors
#: come out at nothing: on these pairs the misfit term carries it all.  The heading scale
#: (1.34) brings the heading of the fitted half to its chi2(1) mean; on the held-out half
#: the heading NEES is 0.96 (band 0.73-1.27; 1.36 without it).  Refit whenever the walls'
#: reading or the decision changes which pairs are accepted
#: (``docs/studies-merge-history.md`` lists the refits).
CALIBRATED = CovarianceModel(
    correlation=1.9401,
    misfit_power=3.6557,
    floor_m=1.8153e-27,
    floor_rad=6.6729e-13,
    heading_scale=1.3372,
)


def calibrated_covariance(
    fit: AlignmentFit | None, resolution: float, model: CovarianceModel = CALIBRATED
) -> np.ndarray:
    """Covariance of ``(tx, ty, psi)`` (eq. (3); px, px, rad) calibrated on real pairs.

    The model, with ``S = (J^T J)^-1``, ``sigma^2`` the residual variance
    (px^2) of :func:`alignment_fit`, ``q = 1/12`` that of grid quantisation
    and ``L = correlation sigma^2 (sigma^2 / q) ** (misfit_power - 1) S``::

        Sigma = A^-1 (D A L A^T D + diag(f^2, f^2, f_psi^2)) A^-T,
        D = diag(1, 1, heading_scale)

    * ``L`` is the Laplace approximation ``sigma^2 (J^T J)^-1`` of the fit
      (noise of the residuals, shrinking as one over the matched walls, with
      the shape of ``S``: a corridor stays uncertain along its length),
      inflated as the residuals grow beyond quantisation.  On real pairs the
      errors are biased by map content (walls seen from one side, drift
      within a map); the residual misfit is what signals it, and the error
      grows faster than the residual variance (``misfit_power`` > 1).
    * ``D`` scales the heading of ``L`` alone, about the centroid ``c`` of
      the matched walls.  ``S`` takes the heading's precision from the spread
      of the walls about ``c``, as if every wall pinned it independently;
      the heading of real pairs is biased by map content more than that (a
      drift that bends one map's far walls, short walls at the ends of the
      overlap), so one factor on the heading's standard deviation, fitted
      with the others, brings it to its errors.  About ``c`` the heading is
      nearly uncorrelated with the translation; scaling it there also moves
      B's origin through the lever arm, as a heading error does (scaling the
      heading about B's origin instead would keep its variance from the lever
      arm and break the link between the two).
    * ``f, f_psi`` are a floor on translation (metres over ``resolution``)
      and heading at ``c``.
    * ``A = [[I, -dR/dpsi c], [0, 1]]`` moves the pose error from B's pixel
      origin, the reference point of eq. (1), to ``c`` (a heading error
      about ``c`` moves the origin by ``-dR/dpsi c dpsi``).

    Parameters
    ----------
    fit : AlignmentFit or None
        The alignment at the merge's result (:func:`alignment_fit`).
    resolution : float
        Metres per cell of the maps.
    model : CovarianceModel, optional
        The constants; by default those fitted on the development pairs.

    Returns
    -------
    numpy.ndarray
        3x3 covariance over ``(tx px, ty px, psi rad)`` of eq. (1) about B's
        pixel origin, eq. (3); ``inf`` on the diagonal when ``fit`` is None.

    Raises
    ------
    ValueError
        If ``resolution`` is not positive.
    """
    if fit is None:
        return np.diag([np.inf, np.inf, np.inf])
    if not resolution > 0:
        raise ValueError(f"resolution must be > 0, got {resolution}")
    misfit = (12.0 * fit.sigma2) ** (model.misfit_power - 1.0)
    laplace = model.correlation * fit.sigma2 * misfit * np.linalg.inv(fit.info)
    floor = model.floor_m / resolution
    # T = T_c - R c, so a heading error about the centroid moves B's origin by -dR/dpsi c
    (cx, cy), c, sn = fit.centroid, np.cos(fit.psi), np.sin(fit.psi)
    a_inv, a = np.eye(3), np.eye(3)
    a_inv[:2, 2] = [sn * cx - c * cy, c * cx + sn * cy]
    a[:2, 2] = -a_inv[:2, 2]
    d = np.diag([1.0, 1.0, model.heading_scale])
    at_centroid = d @ a @ laplace @ a.T @ d
    at_centroid += np.diag([floor**2, floor**2, model.floor_rad**2])
    cov = a_inv @ at_centroid @ a_inv.T
    return 0.5 * (cov + cov.T)
