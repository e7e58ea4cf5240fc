"""Transformation uncertainty propagated to the transformed map, eqs. (4)-(8).

A transform ``P2 = R_psi P1 + T`` (eq. (1)) with covariance ``Sigma_tr`` over
``(x, y, psi)`` (eq. (3); x/y in pixels, psi in radians) moves every cell
with the covariance ``F Sigma_tr F^T`` (eq. (4)), ``F`` the Jacobian of (1).
Eq. (8) is a Gaussian blur whose covariance varies over the map.  It splits
into two cheap, exact parts:

* the rotation part ``sigma_psi^2 r r^T`` is tangential about the rotation
  centre with ``sigma = |r| sigma_psi`` -- in polar coordinates about the
  centre a *constant* 1-D blur along the angle (:func:`rotation_blur`);
* the translation part is one anisotropic Gaussian (:func:`translation_blur`).

A correlation between translation and heading shifts the centre of the
rotation blur and leaves the Schur complement for the translation blur
(:func:`propagate`), so the two parts reproduce eq. (4) at every cell.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from scipy import fft, ndimage

from pgvd.grid import finite_3x3, heading
from pgvd.transform import warp

#: Angular bins per sigma_psi in the polar blur; 3 keeps the blur's width within ~2 %.
_BINS_PER_SIGMA = 3.0
#: Ring spacing of the polar grid, pixels: bilinear splat + read smooths radially by ~this / 2.
_RING_PX = 0.5
#: Variance (pixels^2) added to a translation covariance so a degenerate one is invertible.
_DELTA_VARIANCE = 1e-2
#: Below this sigma (pixels; tangential at the far corner for rotation) a blur is skipped.
_MIN_SIGMA_PX = 0.25

_J = np.array([[0.0, 1.0], [-1.0, 0.0]])  # dR_psi/dpsi = R_psi @ _J, eq. (2)


def transform_covariance(xy: np.ndarray, psi: float, cov3: np.ndarray) -> np.ndarray:
    """Per-point covariance after the transform, eq. (4) with ``F`` the Jacobian of (1).

    ``F = [[1, 0, r1], [0, 1, r2]]`` with ``r1 = -x sin(psi) + y cos(psi)``,
    ``r2 = -x cos(psi) - y sin(psi)`` (eq. (7)).  ``Sigma11`` and ``Sigma22``
    are eq. (6) as printed; the off-diagonal is ``F Sigma_tr F^T`` worked out,
    ``s_xy + s_xpsi r2 + s_ypsi r1 + s_psipsi r1 r2``.  (Eq. (6) as printed
    pairs ``s_xpsi`` with ``r1`` and ``s_ypsi`` with ``r2`` there, which does
    not match the Jacobian; the test checks against finite differences.)

    Parameters
    ----------
    xy : numpy.ndarray
        (N, 2) points ``P1`` relative to the rotation centre, pixels.
    psi : float
        Heading of the transform, radians.
    cov3 : numpy.ndarray
        3x3 covariance over ``(x, y, psi)``, eq. (3).

    Returns
    -------
    numpy.ndarray
        (N, 2, 2) covariances of the transformed points, eq. (5).

    Raises
    ------
    ValueError
        If ``cov3`` is not a finite, symmetric, positive semi-definite 3x3 array.

    References
    ----------
    .. [1] Saeedi, S., Paull, L., Trentini, M., Seto, M., and Li, H., "Map merging
       using probabilistic generalized Voronoi diagrams", IROS 2012, eqs. (1)-(7).
    """
    xy = np.atleast_2d(np.asarray(xy, dtype=np.float64))
    c = check_covariance(cov3)
    s, co = math.sin(psi), math.cos(psi)
    r1 = -xy[:, 0] * s + xy[:, 1] * co
    r2 = -xy[:, 0] * co - xy[:, 1] * s
    out = np.empty((len(xy), 2, 2))
    out[:, 0, 0] = c[0, 0] + 2 * c[0, 2] * r1 + c[2, 2] * r1**2
    out[:, 1, 1] = c[1, 1] + 2 * c[1, 2] * r2 + c[2, 2] * r2**2
    out[:, 0, 1] = out[:, 1, 0] = c[0, 1] + c[0, 2] * r2 + c[1, 2] * r1 + c[2, 2] * r1 * r2
    return out


def _pose_jacobians(m: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    m = finite_3x3(m, "matrix")
    return m[:2, :2], m[:2, 2], heading(m)


def compose_covariance(
    m1: np.ndarray, cov1: np.ndarray, m2: np.ndarray, cov2: np.ndarray
) -> np.ndarray:
    """Covariance of ``(tx, ty, psi)`` of ``m1 @ m2`` from independent ``cov1``, ``cov2``.

    With eq. (1) ``M = [R_psi | T]``: ``psi = psi1 + psi2`` and
    ``T = R1 T2 + T1``, so a heading error of ``m1`` also moves ``T`` by
    ``dR1/dpsi1 T2 = R1 J T2`` (the ``r1, r2`` of eq. (7) at ``T2``).  First
    order, as eq. (4): ``Sigma = A1 Sigma1 A1^T + A2 Sigma2 A2^T``.

    Parameters
    ----------
    m1, m2 : numpy.ndarray
        Finite 3x3 rigid matrices.
    cov1, cov2 : numpy.ndarray
        Their 3x3 covariances over ``(tx, ty, psi)``, eq. (3).

    Returns
    -------
    numpy.ndarray
        3x3 symmetric covariance of ``m1 @ m2``.

    Raises
    ------
    ValueError
        If a matrix is not finite 3x3 or a covariance not symmetric positive semi-definite.

    References
    ----------
    .. [1] Saeedi, S., Paull, L., Trentini, M., Seto, M., and Li, H., "Map merging
       using probabilistic generalized Voronoi diagrams", IROS 2012, eqs. (1)-(7).
    """
    r1, _, _ = _pose_jacobians(m1)
    _, t2, _ = _pose_jacobians(m2)
    a1 = np.eye(3)
    a1[:2, 2] = r1 @ _J @ t2
    a2 = np.eye(3)
    a2[:2, :2] = r1
    out = a1 @ check_covariance(cov1) @ a1.T + a2 @ check_covariance(cov2) @ a2.T
    return (out + out.T) / 2.0


def inverse_covariance(m: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """Covariance of ``(tx, ty, psi)`` of ``inv(m)`` (first order, eq. (4)).

    ``inv(M) = [R^T | -R^T T]`` with heading ``-psi``: ``dT'/dT = -R^T``,
    ``dT'/dpsi = R^T J T``, ``dpsi'/dpsi = -1``.

    Parameters
    ----------
    m : numpy.ndarray
        Finite 3x3 rigid matrix.
    cov : numpy.ndarray
        Its 3x3 covariance over ``(tx, ty, psi)``, eq. (3).

    Returns
    -------
    numpy.ndarray
        3x3 symmetric covariance of ``inv(m)``.

    Raises
    ------
    ValueError
        If ``m`` is not finite 3x3 or ``cov`` not symmetric positive semi-definite.

    References
    ----------
    .. [1] Saeedi, S., Paull, L., Trentini, M., Seto, M., and Li, H., "Map merging
       using probabilistic generalized Voronoi diagrams", IROS 2012, eqs. (1)-(4).
    """
    r, t, _ = _pose_jacobians(m)
    a = np.zeros((3, 3))
    a[:2, :2] = -r.T
    a[:2, 2] = r.T @ _J @ t
    a[2, 2] = -1.0
    out = a @ check_covariance(cov) @ a.T
    return (out + out.T) / 2.0


def check_covariance(cov3: np.ndarray) -> np.ndarray:
    """``cov3`` as float64 if it is a finite, symmetric, positive semi-definite 3x3, eq. (3)."""
    c = finite_3x3(cov3, "covariance")
    if not np.allclose(c, c.T) or np.linalg.eigvalsh(c).min() < -1e-9 * max(1.0, abs(c).max()):
        raise ValueError("covariance must be symmetric positive semi-definite")
    return c


def release_caches() -> None:
    """Drop the polar geometry :func:`rotation_blur` keeps for its next call.

    One entry is kept (a merge blurs each candidate heading's map twice in a row, on the
    same canvas, so that is where it pays); about a centre far outside the image (the
    fusion's), it takes tens of MB until the next call on another canvas.  A long-running
    process calls this once a job is done.
    """
    _polar_geometry.cache_clear()
    _blurred_totals.cache_clear()
    _CACHED_KEY.clear()


#: The key of :func:`_polar_geometry`'s one cached entry, if any (:func:`rotation_blur`).
_CACHED_KEY: set[tuple[object, ...]] = set()


#: Fewest empty angle bins in a row for which the polar bins are cut to the arc the image
#: spans (:func:`_polar_geometry`): more than the polar blur's reach, ``3 sigma_bins``
#: rounded, which is at most 10 bins whenever 12 bins can be empty (``n_theta > 12`` makes
#: ``sigma_psi < pi / 2``, so ``sigma_bins <= 3 + sigma_psi / (2 pi) < 3.25``).
_ARC_GAP = 12


@dataclass(frozen=True)
class _Polar:
    """The polar bins of every pixel of an image about a centre (:func:`_polar_geometry`).

    Attributes
    ----------
    idx : (N, 2) flat indices of the two bins each pixel splats into and reads from.
    wts : (N, 2) float32 weights of those bins.
    totals : float32, the total weight of all pixels in each bin.
    n_rings, n_cols : the bins as ``n_rings x n_cols``, rings by angle.
    wrap : whether the angle columns go round the whole circle; else they are the arc the
        image spans, and beyond it every bin is empty.
    """

    idx: np.ndarray
    wts: np.ndarray
    totals: np.ndarray
    n_rings: int
    n_cols: int
    wrap: bool


@lru_cache(maxsize=1)
def _polar_geometry(shape: tuple[int, int], center: tuple[float, float], n_theta: int) -> _Polar:
    """Polar bins of every pixel about ``center``: linear in radius, nearest in angle.

    A centre at or beyond the image's edge sees the image under an angle of 180 degrees or
    less (90 at a corner; a few degrees from a centre far off, where eq. (8)'s heading
    error acts about a point the translation's correlation with the heading moves away),
    so most of the circle's angle bins hold nothing.  When at least :data:`_ARC_GAP` in a
    row are empty, the columns are cut to the arc that holds pixels: the bins, the splat
    and the blur shrink by the share of the circle left out, and their sums are the
    circle's at every bin: the blur reads zeros beyond the arc's ends as it would in the
    gap, which is wider than its reach, so neither end reaches the other round the circle.
    """
    h, w = shape
    # offsets in float64 first: the same pixel gets the same bins whichever window it is in
    dx = (np.arange(w) - center[0]).astype(np.float32)[None, :]
    dy = (np.arange(h) - center[1]).astype(np.float32)[:, None]
    r = np.hypot(dx, dy).ravel()
    r *= np.float32(1.0 / _RING_PX)
    ring = np.floor(r)
    fr = r - ring
    ring -= ring.min()  # a centre outside the image needs no empty inner rings
    n_rings = int(ring.max()) + 2
    itype = np.int32 if n_rings * n_theta < 2**31 else np.int64  # int32: faster gathers
    # nearest angle bin: bins are sigma_psi / 3 wide; rotation_blur discounts their variance
    t = np.arctan2(dy, dx).ravel()
    t *= np.float32(n_theta / (2 * np.pi))
    a = np.rint(t).astype(itype)
    a[a < 0] += n_theta
    a[a >= n_theta] -= n_theta
    a, n_cols = _cut_to_arc(a, n_theta)
    idx = np.empty((r.size, 2), itype)
    np.multiply(ring.astype(itype), n_cols, out=idx[:, 0])
    idx[:, 0] += a
    np.add(idx[:, 0], n_cols, out=idx[:, 1])
    wts = np.empty((r.size, 2), np.float32)
    np.subtract(np.float32(1.0), fr, out=wts[:, 0])
    wts[:, 1] = fr
    totals = np.bincount(idx.ravel(), wts.ravel(), minlength=n_rings * n_cols).astype(np.float32)
    for arr in (idx, wts, totals):
        arr.setflags(write=False)
    return _Polar(idx, wts, totals, n_rings, n_cols, n_cols == n_theta)


def _cut_to_arc(a: np.ndarray, n_theta: int) -> tuple[np.ndarray, int]:
    """Angle bins ``a`` (of ``n_theta`` round the circle) renumbered from the first of the
    arc that holds them, and the arc's length in bins; ``a`` and ``n_theta`` as they are
    when no :data:`_ARC_GAP` bins in a row are empty."""
    held = np.zeros(n_theta, bool)
    held[a] = True
    cols = np.flatnonzero(held)
    # the widest run of empty bins, around the circle: from cols[k] to cols[k + 1]
    gaps = np.diff(cols, append=cols[0] + n_theta) - 1
    k = int(np.argmax(gaps))
    if gaps[k] < _ARC_GAP:
        return a, n_theta
    a -= cols[(k + 1) % cols.size]
    a %= n_theta
    return a, n_theta - int(gaps[k])


def rotation_blur(
    image: np.ndarray, sigma_psi: float, center: tuple[float, float] | None = None
) -> np.ndarray:
    """Tangential Gaussian blur about ``center`` with ``sigma = r * sigma_psi``, eq. (8).

    This is the rotation part of eqs. (4)-(8): a heading error moves a cell at
    distance ``r`` from the rotation centre along the tangent by ``r dpsi``.
    In polar coordinates about the centre it is a constant 1-D Gaussian of
    ``sigma_psi`` radians along the angle (with wrap-around).  Pixels are
    splatted into (ring, angle) bins, the bins blurred as a normalised
    convolution (so sparse inner rings stay exact), and each pixel reads the
    bins back with the same weights: linear in radius, with rings half a
    pixel apart (radial smoothing below 0.35 px std), and nearest in angle,
    with bins ``sigma_psi / 3`` wide (the Gaussian is narrowed by the
    variance the two nearest-bin steps add; a single cell's blur is centred
    to within ``r sigma_psi / 6`` along the tangent).

    Parameters
    ----------
    image : numpy.ndarray
        (H, W) map.
    sigma_psi : float
        Heading standard deviation, radians, >= 0.
    center : tuple of float, optional
        ``(x, y)`` rotation centre in pixels; default the image centre.

    Returns
    -------
    numpy.ndarray
        (H, W) float32.

    Raises
    ------
    ValueError
        If ``image`` is not 2-D or ``sigma_psi`` is negative or not finite.

    References
    ----------
    .. [1] Saeedi, S., Paull, L., Trentini, M., Seto, M., and Li, H., "Map merging
       using probabilistic generalized Voronoi diagrams", IROS 2012, eqs. (4)-(8), Sec. IV-B.
    """
    img = np.asarray(image, dtype=np.float32)
    if img.ndim != 2:
        raise ValueError(f"image must be 2-D, got shape {img.shape}")
    if not math.isfinite(sigma_psi) or sigma_psi < 0:
        raise ValueError(f"sigma_psi must be finite and >= 0, got {sigma_psi}")
    h, w = img.shape
    cx, cy = ((w - 1) / 2.0, (h - 1) / 2.0) if center is None else map(float, center)
    r_max = max(math.hypot(x - cx, y - cy) for x in (0, w - 1) for y in (0, h - 1))
    if r_max * sigma_psi < _MIN_SIGMA_PX:
        return img.copy()
    # angular bins: fine enough to resolve sigma_psi, never finer than a pixel at r_max
    n_theta = int(
        min(math.ceil(2 * math.pi * _BINS_PER_SIGMA / sigma_psi), math.ceil(2 * math.pi * r_max))
    )
    key = ((h, w), (round(cx, 6), round(cy, 6)), n_theta)
    if key not in _CACHED_KEY:
        # another canvas: the cached geometry and totals go before the new ones are built,
        # not after, which held both at once (~20 MB more on a 550 x 550 global map)
        release_caches()
        _CACHED_KEY.add(key)
    geo = _polar_geometry(*key)
    # nearest-bin splat and read each add the variance of a uniform bin (1/12 bin^2)
    sigma_bins = round(math.sqrt(max((sigma_psi * n_theta / (2 * math.pi)) ** 2 - 1 / 6, 0)), 9)
    if sigma_bins == 0:  # under a bin's own quantisation: scipy would divide by 0
        return img.copy()
    # The bins outnumber the pixels ~10 to 1 (rings half a pixel apart, one bin per pixel at
    # r_max): each array of them is ~10 MB on a 550 x 550 global map, so as few are alive at
    # once as can be. The float64 counts go as soon as they are float32.
    binned = np.bincount(
        geo.idx.ravel(), (geo.wts * img.reshape(-1, 1)).ravel(), minlength=geo.totals.size
    ).astype(np.float32)
    polar = _angular_blur(binned.reshape(geo.n_rings, geo.n_cols), sigma_bins, geo.wrap)
    del binned
    # normalised only at the bins a pixel reads: a tenth of the bins, the same quotients
    norm = _blurred_totals(*key, sigma_bins)
    read = np.zeros(geo.idx.shape, np.float32)
    np.divide(polar[geo.idx], norm, out=read, where=norm > 1e-6)
    return np.einsum("ij,ij->i", read, geo.wts).reshape(h, w)


@lru_cache(maxsize=1)
def _blurred_totals(
    shape: tuple[int, int], center: tuple[float, float], n_theta: int, sigma_bins: float
) -> np.ndarray:
    """The normaliser of the polar blur: the blurred per-bin pixel weights, at the two bins
    each pixel reads (N, 2)."""
    geo = _polar_geometry(shape, center, n_theta)
    totals = geo.totals.reshape(geo.n_rings, geo.n_cols)
    out = _angular_blur(totals, sigma_bins, geo.wrap)[geo.idx]
    out.setflags(write=False)
    return out


def _angular_blur(bins: np.ndarray, sigma_bins: float, wrap: bool) -> np.ndarray:
    """``bins`` (rings x angle) blurred along the angle, flat: round the circle when
    ``wrap``, else over an arc beyond which every bin is empty (:func:`_polar_geometry`)."""
    mode = "wrap" if wrap else "constant"
    return ndimage.gaussian_filter1d(bins, sigma_bins, axis=1, mode=mode, truncate=3.0).ravel()


def translation_blur(image: np.ndarray, cov_xy: np.ndarray) -> np.ndarray:
    """Anisotropic Gaussian blur with a constant 2x2 covariance (pixels^2), eq. (8).

    This is the translation part of eq. (8) (``sigma_psi = 0``, Sec. IV-F).
    The 2-D kernel ``exp(-d^T Sigma^-1 d / 2)`` is sampled out to 4 sigma,
    normalised, and applied by FFT convolution on the image extended by
    mirroring (``scipy.ndimage``'s default ``reflect``).  The kernel is
    sampled in space, not its transfer function in frequency: for sigma
    below a pixel the latter rings across the whole map.

    Parameters
    ----------
    image : numpy.ndarray
        (H, W) map.
    cov_xy : numpy.ndarray
        2x2 covariance in the pixel frame ``(x, y)``.

    Returns
    -------
    numpy.ndarray
        (H, W) float32.

    Raises
    ------
    ValueError
        If ``image`` is not 2-D or ``cov_xy`` is not a finite, symmetric,
        positive semi-definite 2x2 array.

    References
    ----------
    .. [1] Saeedi, S., Paull, L., Trentini, M., Seto, M., and Li, H., "Map merging
       using probabilistic generalized Voronoi diagrams", IROS 2012, eq. (8), Sec. IV-F.
    """
    img = np.asarray(image, dtype=np.float32)
    cov = np.asarray(cov_xy, dtype=np.float64)
    if img.ndim != 2:
        raise ValueError(f"image must be 2-D, got shape {img.shape}")
    if cov.shape != (2, 2) or not np.isfinite(cov).all() or not np.allclose(cov, cov.T):
        raise ValueError(f"cov_xy must be a finite symmetric 2x2 array, got {cov.tolist()}")
    eig = np.linalg.eigvalsh(cov)
    if eig.min() < -1e-9 * max(1.0, eig.max()):
        raise ValueError(f"cov_xy must be positive semi-definite, got {cov.tolist()}")
    if eig.max() < _MIN_SIGMA_PX**2:
        return img.copy()
    # beyond the map's size a wider kernel changes nothing but the cost (a flat corridor
    # can leave a translation variance of thousands of cells^2)
    half = min(math.ceil(4.0 * math.sqrt(eig.max())), max(img.shape))
    ys, xs = np.mgrid[-half : half + 1, -half : half + 1].astype(np.float64)
    # a degenerate direction (e.g. translation fully explained by the heading) is a delta
    inv = np.linalg.inv(cov + _DELTA_VARIANCE * np.eye(2))
    kernel = np.exp(-0.5 * (inv[0, 0] * xs**2 + 2 * inv[0, 1] * xs * ys + inv[1, 1] * ys**2))
    kernel /= kernel.sum()
    h, w = img.shape
    padded = np.pad(img.astype(np.float64), half, mode="symmetric")
    # circular FFT convolution; the 'valid' part [k-1, n) never sees the wrap-around
    shape = tuple(fft.next_fast_len(n, real=True) for n in padded.shape)
    spectrum = fft.rfft2(padded, s=shape) * fft.rfft2(kernel, s=shape)
    full = fft.irfft2(spectrum, s=shape)
    k = kernel.shape[0] - 1
    return full[k : k + h, k : k + w].astype(np.float32)


def propagate(
    image: np.ndarray,
    matrix: np.ndarray,
    cov3: np.ndarray,
    out_shape: tuple[int, int],
    center: tuple[float, float] = (0.0, 0.0),
    cval: float = 0.0,
) -> np.ndarray:
    """Eq. (8): transform ``image`` by ``matrix`` and blur it by the transform's covariance.

    ``mu = R_psi (x) m + T`` is :func:`~pgvd.transform.warp`; the blur has at
    every cell the covariance of eq. (4).  With ``K = Sigma_T,psi / s_psipsi``
    the translation error splits as ``dT = K dpsi + e``; then the displacement
    of a cell at offset ``Q`` from the rotated centre is ``dpsi J (Q - J K) + e``
    (``J = dR/dpsi R^-1``): a rotation blur about the centre shifted by
    ``J K``, then a translation blur with the Schur complement
    ``Sigma_TT - K K^T s_psipsi`` -- exactly ``F Sigma_tr F^T`` at every cell.

    Parameters
    ----------
    image : numpy.ndarray
        (H, W) map B (probabilities, or log-odds).
    matrix : numpy.ndarray
        3x3, B pixel -> output pixel.
    cov3 : numpy.ndarray
        3x3 covariance over ``(x px, y px, psi rad)``, eq. (3), with the
        heading error acting about ``center``.
    out_shape : tuple of int
        (rows, cols) of the output frame.
    center : tuple of float, optional
        Rotation centre in B's pixels; default B's pixel origin, where
        eq. (1) with ``P1`` = B's pixel puts it (the convention of
        ``matrix_to_pose`` and of :class:`pgvd.result.MergeResult`).
    cval : float, optional
        Value outside B (0 for log-odds, 0.5 for probabilities).

    Returns
    -------
    numpy.ndarray
        (rows, cols) float32: B in the output frame, blurred by eq. (8).

    Raises
    ------
    ValueError
        If ``cov3`` is not a finite, symmetric, positive semi-definite 3x3 array.

    References
    ----------
    .. [1] Saeedi, S., Paull, L., Trentini, M., Seto, M., and Li, H., "Map merging
       using probabilistic generalized Voronoi diagrams", IROS 2012, eqs. (1)-(8).
    """
    c = check_covariance(cov3)
    m = np.asarray(matrix, dtype=np.float64)
    center_out = (m @ np.append(np.asarray(center, dtype=np.float64), 1.0))[:2]
    s_pp = c[2, 2]
    cov_t = c[:2, :2]
    if s_pp > 0:
        k = c[:2, 2] / s_pp
        center_out = center_out + _J @ k
        # the Schur complement is PSD; clip the rounding that could make it not so
        evals, evecs = np.linalg.eigh(cov_t - np.outer(k, k) * s_pp)
        cov_t = (evecs * np.clip(evals, 0.0, None)) @ evecs.T
    # Work in the window around B's footprint that the blurs can reach: beyond it the
    # output is exactly cval, and the union canvas of a merge is often much larger than B.
    h, w = np.shape(image)
    corners = (m @ np.array([[0, w - 1, 0, w - 1], [0, 0, h - 1, h - 1], [1, 1, 1, 1]]))[:2].T
    r_far = float(np.max(np.linalg.norm(corners - center_out, axis=1)))
    sigma_t = math.sqrt(max(float(np.linalg.eigvalsh(cov_t).max()), 0.0))
    reach = 3.0 + 3.5 * r_far * math.sqrt(s_pp) + 4.0 * sigma_t
    lo = np.maximum(np.floor(corners.min(axis=0) - reach), 0).astype(int)
    hi = np.minimum(np.ceil(corners.max(axis=0) + reach) + 1, out_shape[::-1]).astype(int)
    out = np.full(out_shape, cval, dtype=np.float32)
    if (hi <= lo).any():
        return out  # B lands outside the output
    shift = np.array([[1.0, 0.0, -lo[0]], [0.0, 1.0, -lo[1]], [0.0, 0.0, 1.0]])
    window = (int(hi[1] - lo[1]), int(hi[0] - lo[0]))
    # deviations from cval are blurred, so that cells outside B stay exactly cval
    to_window = shift @ m
    if window == np.shape(image) and np.array_equal(to_window, np.eye(3)):
        # B blurred where it is (the fusion's own-frame blur): the bilinear read would
        # return every cell as it is, at a third of the blur's cost
        moved = np.asarray(image, dtype=np.float32) - np.float32(cval)
    else:
        moved = warp(image, to_window, window, order=1, cval=cval).astype(np.float32) - cval
    if s_pp > 0:
        moved = rotation_blur(moved, math.sqrt(s_pp), tuple(center_out - lo))
    out[lo[1] : hi[1], lo[0] : hi[0]] = translation_blur(moved, cov_t) + cval
    return out
