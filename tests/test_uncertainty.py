"""Eqs. (4)-(8): covariance against the numerical Jacobian of (1), and the blurs' real spread."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import pytest
from scipy.stats import chi2

from pgvd import uncertainty
from pgvd.covariance import CovarianceModel
from pgvd.grid import matrix_to_pose, rigid_matrix
from pgvd.transform import warp
from pgvd.uncertainty import (
    compose_covariance,
    inverse_covariance,
    propagate,
    rotation_blur,
    transform_covariance,
    translation_blur,
)


def _f(params: np.ndarray, p1: np.ndarray) -> np.ndarray:
    """Eq. (1): P2 = R_psi P1 + T, with params = (x_t, y_t, psi) in the order of eq. (3)."""
    tx, ty, psi = params
    r = np.array([[np.cos(psi), np.sin(psi)], [-np.sin(psi), np.cos(psi)]])  # eq. (2)
    return r @ p1 + np.array([tx, ty])


def _random_cov(rng: np.random.Generator) -> np.ndarray:
    a = rng.normal(size=(3, 3)) * np.array([2.0, 2.0, 0.02])[:, None]
    return a @ a.T


def test_transform_covariance_matches_numerical_jacobian() -> None:
    rng = np.random.default_rng(0)
    for _ in range(50):
        psi = rng.uniform(-np.pi, np.pi)
        cov = _random_cov(rng)
        pts = rng.uniform(-500, 500, (20, 2))
        got = transform_covariance(pts, psi, cov)
        params = np.array([*rng.uniform(-100, 100, 2), psi])
        h = 1e-6
        for p1, sigma in zip(pts, got, strict=True):
            jac = np.column_stack(
                [(_f(params + h * e, p1) - _f(params - h * e, p1)) / (2 * h) for e in np.eye(3)]
            )
            np.testing.assert_allclose(sigma, jac @ cov @ jac.T, rtol=1e-5, atol=1e-6)


def test_printed_eq6_off_diagonal_differs_from_the_jacobian() -> None:
    """Eq. (6) as printed pairs s_xpsi with r1 in Sigma12; F Sigma F^T pairs it with r2."""
    cov = np.array([[1.0, 0.0, 0.01], [0.0, 1.0, 0.0], [0.01, 0.0, 1e-4]])
    x, y, psi = 100.0, 0.0, 0.0
    r1, r2 = -x * np.sin(psi) + y * np.cos(psi), -x * np.cos(psi) - y * np.sin(psi)
    printed = cov[0, 1] + cov[0, 2] * r1 + cov[1, 2] * r2 + cov[2, 2] * r1 * r2
    ours = transform_covariance([[x, y]], psi, cov)[0, 0, 1]
    assert printed == pytest.approx(0.0) and ours == pytest.approx(0.01 * r2)


def _moments(img: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    ys, xs = np.mgrid[: img.shape[0], : img.shape[1]]
    w = img / img.sum()
    mean = np.array([(w * xs).sum(), (w * ys).sum()])
    d = np.stack([xs - mean[0], ys - mean[1]])
    cov = np.einsum("iyx,jyx,yx->ij", d, d, w)
    return mean, cov


@pytest.mark.parametrize(("r", "sigma_psi"), [(60, 0.03), (200, 0.01), (330, 0.02)])
def test_rotation_blur_spreads_r_sigma_along_the_tangent(r: float, sigma_psi: float) -> None:
    img = np.zeros((701, 701), np.float32)
    rng = np.random.default_rng(int(r))
    ang = rng.uniform(0, 2 * np.pi)
    x, y = round(350 + r * np.cos(ang)), round(350 + r * np.sin(ang))
    img[y, x] = 1.0
    out = rotation_blur(img, sigma_psi, (350.0, 350.0))
    assert out.sum() == pytest.approx(1.0, rel=0.05)
    mean, cov = _moments(out)
    radial = np.array([x - 350.0, y - 350.0])
    radius = np.linalg.norm(radial)
    u = radial / radius
    t = np.array([-u[1], u[0]])
    tangential_std = np.sqrt(t @ cov @ t)
    radial_std = np.sqrt(u @ cov @ u)
    assert tangential_std == pytest.approx(radius * sigma_psi, rel=0.08)
    assert radial_std < 0.35  # half-pixel rings, bilinear splat and read
    # centre quantised to the angle bins (sigma_psi / 3 wide) and the arc's sagitta
    along = abs(t @ (mean - [x, y]))
    assert (
        along < radius * sigma_psi / 6 + 0.05
        and abs(u @ (mean - [x, y])) < 0.1 + radius * sigma_psi**2
    )


def test_rotation_blur_keeps_constants_and_zero_sigma_is_identity() -> None:
    img = np.full((120, 90), 0.3, np.float32)
    np.testing.assert_allclose(rotation_blur(img, 0.05), img, atol=1e-5)
    rnd = np.random.default_rng(1).random((50, 40)).astype(np.float32)
    np.testing.assert_array_equal(rotation_blur(rnd, 0.0), rnd)
    with pytest.raises(ValueError, match="sigma_psi"):
        rotation_blur(rnd, -1.0)


def test_translation_blur_has_the_requested_covariance() -> None:
    img = np.zeros((121, 121), np.float32)
    img[60, 60] = 1.0
    cov = np.array([[9.0, 4.0], [4.0, 4.0]])
    out = translation_blur(img, cov)
    mean, got = _moments(out)
    np.testing.assert_allclose(mean, [60, 60], atol=1e-3)
    np.testing.assert_allclose(got, cov, atol=0.05)
    with pytest.raises(ValueError, match="semi-definite"):
        translation_blur(img, np.array([[1.0, 2.0], [2.0, 1.0]]))


def test_propagate_spreads_each_cell_by_eq4() -> None:
    """Warp + blur puts a point of B at M P1 with covariance F Sigma_tr F^T (eqs. (4)-(8)),
    including correlated heading/translation errors, about B's centre or (eq. (1) as
    written, the default) about B's pixel origin."""
    rng = np.random.default_rng(7)
    h, w = 301, 301
    s_psi = 0.012
    cov = np.diag([1.5, 2.5, s_psi**2])
    cov[0, 2] = cov[2, 0] = 0.6 * np.sqrt(1.5) * s_psi
    cov[1, 2] = cov[2, 1] = -0.4 * np.sqrt(2.5) * s_psi
    for case in range(4):
        if case < 2:  # heading error about B's centre
            c = np.array([150.0, 150.0])
            psi = rng.uniform(-np.pi, np.pi)
            m = rigid_matrix(psi, 0.0, 0.0)
            m[:2, 2] = np.array([250.0, 250.0]) - m[:2, :2] @ c
            p1 = c + rng.uniform(-100, 100, 2).round()
        else:  # eq. (1) literally: P1 is B's pixel, rotation about B's origin
            c = np.zeros(2)
            psi = rng.uniform(-0.3, 0.3)
            m = rigid_matrix(psi, 100.0, 150.0)
            p1 = rng.uniform(50, 250, 2).round()
        img = np.zeros((h, w), np.float32)
        img[int(p1[1]), int(p1[0])] = 1.0
        out = propagate(img, m, cov, (500, 500), center=tuple(c))
        mean, got = _moments(out)
        # the centre is quantised to the polar blur's angle bins (see rotation_blur)
        tol = 0.1 + np.linalg.norm(p1 - c) * s_psi / 6
        np.testing.assert_allclose(mean, (m @ [*p1, 1.0])[:2], atol=tol)
        expect = transform_covariance([p1 - c], psi, cov)[0]
        # bilinear warp of a single cell adds up to 1/6 px^2 per axis, the rings ~1/12,
        # and the arc of a wide tangential blur is not quite a Gaussian's straight line
        np.testing.assert_allclose(got, expect, rtol=0.03, atol=0.35)
    # propagate with cval: the canvas outside B stays exactly cval
    out = propagate(np.full((50, 50), 0.5, np.float32), np.eye(3), cov, (80, 80), cval=0.5)
    assert np.allclose(out[60:, 60:], 0.5)


def test_propagate_window_equals_blurring_the_whole_canvas() -> None:
    """propagate blurs only around B's footprint; on the whole canvas the result is the same."""
    rng = np.random.default_rng(5)
    b = (rng.random((120, 90)) < 0.2).astype(np.float32) * 0.8 + 0.1
    m = rigid_matrix(0.7, 300.0, 100.0)
    # sigma_psi large enough that both polar grids get the same angle bins (they are capped
    # at one pixel per bin at the far corner, which differs between window and canvas)
    cov = np.diag([2.0, 0.5, 0.05**2])
    cov[0, 1] = cov[1, 0] = 0.4
    got = propagate(b, m, cov, (500, 600), center=(10.0, 20.0), cval=0.5)
    whole = warp(b, m, (500, 600), cval=0.5) - 0.5
    whole = rotation_blur(whole, 0.05, tuple((m @ [10.0, 20.0, 1.0])[:2]))
    whole = translation_blur(whole, cov[:2, :2]) + 0.5
    np.testing.assert_allclose(got, whole, atol=1e-5)
    assert (got != 0.5).sum() > 0.5 * b.size


def _pose(m: np.ndarray) -> np.ndarray:
    psi, tx, ty = matrix_to_pose(m)
    return np.array([tx, ty, psi])


def _numeric_jacobian(
    fn: Callable[[np.ndarray], np.ndarray], x: np.ndarray, h: float = 1e-6
) -> np.ndarray:
    return np.column_stack([(fn(x + h * e) - fn(x - h * e)) / (2 * h) for e in np.eye(len(x))])


def test_compose_and_inverse_covariance_match_numerical_jacobians() -> None:
    """First-order covariance of m1 @ m2 and of inv(m), against finite differences of
    the pose of the composed/inverted matrix (eq. (4) through the composition)."""
    rng = np.random.default_rng(11)
    for _ in range(20):
        x1 = np.array([*rng.uniform(-300, 300, 2), rng.uniform(-np.pi, np.pi)])
        x2 = np.array([*rng.uniform(-300, 300, 2), rng.uniform(-np.pi, np.pi)])
        c1, c2 = _random_cov(rng), _random_cov(rng)
        m1, m2 = rigid_matrix(x1[2], *x1[:2]), rigid_matrix(x2[2], *x2[:2])

        def composed(x: np.ndarray) -> np.ndarray:
            return _pose(rigid_matrix(x[2], *x[:2]) @ rigid_matrix(x[5], *x[3:5]))

        jac = _numeric_jacobian(composed, np.concatenate([x1, x2]))
        joint = np.zeros((6, 6))
        joint[:3, :3], joint[3:, 3:] = c1, c2
        np.testing.assert_allclose(
            compose_covariance(m1, c1, m2, c2), jac @ joint @ jac.T, rtol=1e-5, atol=1e-8
        )

        def inverted(x: np.ndarray) -> np.ndarray:
            return _pose(np.linalg.inv(rigid_matrix(x[2], *x[:2])))

        jac = _numeric_jacobian(inverted, x1)
        np.testing.assert_allclose(
            inverse_covariance(m1, c1), jac @ c1 @ jac.T, rtol=1e-5, atol=1e-8
        )


def test_rotation_blur_below_one_angle_bin_is_identity_not_a_crash() -> None:
    # sigma_psi * r_max = 0.35 px: above the no-op threshold, but the angle-bin
    # quantisation alone already covers it, so the residual blur is 0 (scipy would divide
    # by 0); found by a fleet agent fusing a link with a tiny heading variance.
    img = np.random.default_rng(0).random((200, 200)).astype(np.float32)
    out = rotation_blur(img, 0.0025)
    assert out.shape == img.shape and np.isfinite(out).all()


@pytest.mark.parametrize(
    "center", [(0.0, 0.0), (-40.0, 10.0), (0.0, 60.0), (45.5, 30.5), (-3000.0, 2500.0)]
)
def test_the_polar_blur_cut_to_the_images_arc_is_the_whole_circles_bit_for_bit(
    center: tuple[float, float], monkeypatch: pytest.MonkeyPatch
) -> None:
    """A centre at a corner, outside, on an edge, inside and far off: the polar bins are cut
    to the arc of angles the image spans (_polar_geometry), which changes no pixel of the
    blur; with no gap wide enough to cut, the whole circle is kept."""
    rng = np.random.default_rng(3)
    img = rng.random((80, 90)).astype(np.float32) - 0.5
    uncertainty.release_caches()
    cut = rotation_blur(img, 0.01, center)
    (key,) = uncertainty._CACHED_KEY
    geo = uncertainty._polar_geometry(*key)
    assert geo.wrap == (center == (45.5, 30.5))  # inside: every angle holds a pixel
    uncertainty.release_caches()
    monkeypatch.setattr(uncertainty, "_ARC_GAP", 10**9)
    whole = rotation_blur(img, 0.01, center)
    assert uncertainty._polar_geometry(*key).n_cols == key[2]
    assert cut.tobytes() == whole.tobytes()
    uncertainty.release_caches()


def _walls(shared_dir, name: str):
    from pgvd.io import read_map
    from pgvd.walls import WallMap

    g = read_map(shared_dir / name)
    return g, WallMap(g.probability(), 0.65, 0.3)


def test_calibrated_covariance_grows_with_fewer_supporting_walls(shared) -> None:
    from pgvd.alignment import alignment_fit
    from pgvd.covariance import calibrated_covariance

    g, wm = _walls(shared, "maps/intel_split_gt/intel_partA.yaml")
    m = rigid_matrix(0.3, 40.0, -25.0)
    # A = m(B): B's walls are A's moved back, all of them or only those of one corner
    walls_b = (wm.walls - m[:2, 2]) @ np.linalg.inv(m[:2, :2]).T
    corner = (wm.walls[:, 0] < np.quantile(wm.walls[:, 0], 0.3)) & (
        wm.walls[:, 1] < np.quantile(wm.walls[:, 1], 0.3)
    )
    full = calibrated_covariance(alignment_fit(wm.tree, walls_b, m), g.resolution)
    part = calibrated_covariance(alignment_fit(wm.tree, walls_b[corner], m), g.resolution)
    assert corner.sum() < 0.2 * len(walls_b)
    # fewer, shorter walls: a wider heading and a larger uncertainty volume
    assert part[2, 2] > 2.0 * full[2, 2]
    assert np.linalg.det(part) > 2.0 * np.linalg.det(full)
    # the calibrated covariance is never tighter than the Laplace one it contains
    laplace = calibrated_covariance(
        alignment_fit(wm.tree, walls_b, m), g.resolution, CovarianceModel(1.0, 1.0, 0.0, 0.0)
    )
    assert np.linalg.eigvalsh(full - laplace).min() > -1e-12


def test_calibrated_covariance_floor_acts_about_the_matched_walls() -> None:
    from pgvd.alignment import AlignmentFit
    from pgvd.covariance import calibrated_covariance

    # no residual information at all: only the floor, about a centroid c of B's pixels
    c, psi0 = np.array([100.0, 40.0]), 0.3
    fit = AlignmentFit(np.eye(3) * 1e12, 0.1, c, psi0)
    model = CovarianceModel(correlation=1.0, misfit_power=1.0, floor_m=0.05, floor_rad=0.01)
    cov = calibrated_covariance(fit, 0.05, model)
    assert cov[2, 2] == pytest.approx(1e-4)
    # a pose error (t, p) at the centroid, P2 = R(psi0 + p) (P1 - c) + R(psi0) c + t,
    # moves B's origin (eq. (1)'s reference point) by t + R(psi0) c - R(psi0 + p) c
    rng = np.random.default_rng(0)
    e = rng.normal(size=(20000, 3)) * np.array([1.0, 1.0, 0.01])  # floor: 1 cell, 0.01 rad
    origin = np.array(
        [_f(np.array([*t, psi0]), c) - _f(np.array([0, 0, psi0 + p]), c) for *t, p in e]
    )
    sample = np.cov(np.column_stack([origin, e[:, 2]]).T)
    np.testing.assert_allclose(sample[:2, :2], cov[:2, :2], rtol=0.05)
    np.testing.assert_allclose(sample[:2, 2], cov[:2, 2], atol=3e-4)  # of 0.01: sampling
    assert cov[0, 0] + cov[1, 1] == pytest.approx(2.0 + (np.hypot(*c) * 0.01) ** 2, rel=1e-6)


def test_heading_scale_widens_the_heading_about_the_matched_walls(shared) -> None:
    from pgvd.alignment import alignment_fit
    from pgvd.covariance import calibrated_covariance

    g, wm = _walls(shared, "maps/intel_split_gt/intel_partA.yaml")
    m = rigid_matrix(0.3, 40.0, -25.0)
    walls_b = (wm.walls - m[:2, 2]) @ np.linalg.inv(m[:2, :2]).T  # A = m(B)
    fit = alignment_fit(wm.tree, walls_b, m)
    plain = calibrated_covariance(fit, g.resolution, CovarianceModel(5.0, 3.0, 0.0, 0.0))
    wide = calibrated_covariance(fit, g.resolution, CovarianceModel(5.0, 3.0, 0.0, 0.0, 1.5))
    assert wide[2, 2] == pytest.approx(1.5**2 * plain[2, 2], rel=1e-9)
    # a heading error p about the centroid c moves B's origin by lever * p (eq. (1)),
    # so the pose error at c is (t - lever * p, p)
    h = 1e-7
    lever = (
        _f(np.array([0, 0, fit.psi]), fit.centroid)
        - _f(np.array([0, 0, fit.psi + h]), fit.centroid)
    ) / h
    to_c = np.eye(3)
    to_c[:2, 2] = -lever
    plain_c, wide_c = to_c @ plain @ to_c.T, to_c @ wide @ to_c.T
    # there only the heading is wider: the translation keeps its spread
    np.testing.assert_allclose(wide_c[:2, :2], plain_c[:2, :2], rtol=1e-6)
    np.testing.assert_allclose(wide_c[:2, 2], 1.5 * plain_c[:2, 2], rtol=1e-6, atol=1e-12)
    # at B's origin the translation widens too, through the lever arm
    assert wide[0, 0] + wide[1, 1] > plain[0, 0] + plain[1, 1]


def test_merge_covariance_is_consistent_on_real_pairs(shared) -> None:
    from bench.covariance import nees, pose_error
    from bench.data.pairs import make_pairs
    from pgvd.carmen import read_carmen
    from pgvd.merge import merge
    from pgvd.params import MergeParams

    scans = read_carmen(shared / "logs/intel-corrected.log.gz")
    # seed 3: none of these pairs is among those the constants were fitted on (seed 10)
    errors, covs = [], []
    for p in make_pairs(scans, 5, 0, 3, "intel"):
        r = merge(p.a, p.b, MergeParams(diagnostics=False))
        if r.accepted:
            errors.append(pose_error(p.truth, r.matrix))
            covs.append(r.covariance)
    assert len(errors) >= 4
    errors, covs = np.array(errors), np.array(covs)
    # mean of n chi2(3) has mean 3, var 6/n: 99.9 % of calibrated sets stay below
    # chi2(3n).ppf(0.999) / n; the Laplace covariance alone scored a mean of ~28
    n = len(errors)
    assert nees(errors, covs).mean() < chi2.ppf(0.999, 3 * n) / n
    assert np.mean(errors[:, 2] ** 2 / covs[:, 2, 2]) < chi2.ppf(0.999, n) / n


def test_calibrated_constants_are_those_the_bench_fitted() -> None:
    import json
    from pathlib import Path

    from pgvd.covariance import CALIBRATED

    doc = json.loads(
        (Path(__file__).resolve().parents[1] / "bench/results/covariance.json").read_text()
    )
    fitted = doc["models"][doc["chosen"]]
    for name, value in fitted.items():
        assert getattr(CALIBRATED, name) == pytest.approx(value, rel=1e-3)
