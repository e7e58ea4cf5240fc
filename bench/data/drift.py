"""Odometry drift of the size real wheel odometry has, independent of how often scans are taken.

The corrected logs carry no raw odometry to measure (their ``odom`` field
equals the corrected pose), so the drift is a model: between consecutive
scans the robot's own estimate of its motion gets random-walk errors whose
variance grows with the distance moved and the angle turned,

    translation (each axis, robot frame): sigma^2 = TRANSLATION^2 * d
    heading:                              sigma^2 = HEADING^2 * d + TURN^2 * |dtheta|

with ``d`` in metres and ``dtheta`` in radians.  Variances add along the path,
so the drift after L metres is the same whether scans come every 0.1 m
(freiburg-079) or every 0.67 m (intel); :func:`pgvd.integrate.perturb_odometry`
scales standard deviations with the step instead, which makes drift depend on
the scan spacing.

Sizes, after the 2-5 % of the distance travelled commonly quoted for
differential-drive wheel odometry (Borenstein and Feng, "Measurement and
correction of systematic odometry errors in mobile robots", IEEE Trans.
Robotics and Automation 12(6), 1996): TRANSLATION = 0.03 m per sqrt(metre)
(wheel slip), TURN = 0.01 rad per sqrt(radian) turned (0.7 deg after a
quarter turn: wheel-base uncertainty) and HEADING = 0.2 deg per sqrt(metre)
driven (wheel-diameter mismatch).  Measured on the development runs over
10-40 m of travel (median and p90 over every start): position error 0.9-1.5 %
(p90 1.8-4.2 %) of the distance travelled, heading error 1.0-2.6 deg (p90
2.5-5.9 deg) -- the lower end of that range.  Twice the TURN gives 1.4-2.5 %
(p90 2.8-7.6 %), but then a pair's maps, cut from segments of up to 250 m,
are distorted by 0.55-1.2 m RMS (median) and no rigid alignment is a fair
test; at this TURN the median residual distortion is 0.3-0.6 m.  Only the
random part of odometry error is modelled; the systematic part is what a
robot's calibration removes.
"""

from __future__ import annotations

import dataclasses

import numpy as np
from scipy.spatial import cKDTree

from pgvd.carmen import LaserScan
from pgvd.integrate import rechain_poses, se2
from pgvd.sampling import subsample

TRANSLATION = 0.03
HEADING = float(np.radians(0.2))
TURN = 0.01


@dataclasses.dataclass(frozen=True)
class Drift:
    """Random-walk odometry errors (module docstring); sigmas per sqrt(metre) or sqrt(radian)."""

    translation: float = TRANSLATION
    heading: float = HEADING
    turn: float = TURN

    def apply(self, scans: list[LaserScan], seed: int) -> list[LaserScan]:
        """The scans with their poses re-chained through noisy steps; the first pose is kept."""
        return rechain_poses(scans, self.step_noise, seed)

    def step_noise(
        self, dist: float, turn: float, rng: np.random.Generator
    ) -> tuple[float, float, float]:
        """``(dx, dy, dtheta)`` of one step of ``dist`` metres and ``turn`` radians."""
        dx, dy = rng.normal(0.0, self.translation * np.sqrt(dist), 2)
        sigma_h = np.sqrt(self.heading**2 * dist + self.turn**2 * turn)
        return dx, dy, rng.normal(0.0, sigma_h)

    def json(self) -> dict:
        return dataclasses.asdict(self)


def rigid_fit(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """3x3 SE(2) minimising ``sum |R src_i + t - dst_i|^2`` (Kabsch/Umeyama, no scale)."""
    mu_s, mu_d = src.mean(axis=0), dst.mean(axis=0)
    u, _, vt = np.linalg.svd((dst - mu_d).T @ (src - mu_s))
    r = u @ np.diag([1.0, np.sign(np.linalg.det(u @ vt))]) @ vt
    m = np.eye(3)
    m[:2, :2] = r
    m[:2, 2] = mu_d - r @ mu_s
    return m


def _corrections(true: list[LaserScan], drifted: list[LaserScan]) -> np.ndarray:
    """Per scan, the 3x3 map taking true world points to where the drifted robot puts them."""
    return np.array(
        [se2(*d.pose) @ np.linalg.inv(se2(*t.pose)) for t, d in zip(true, drifted, strict=True)]
    )


def _endpoints(scans: list[LaserScan], max_range: float) -> tuple[np.ndarray, np.ndarray]:
    """World positions of every beam's hit (true poses) and the index of its scan."""
    pts, idx = [], []
    for i, s in enumerate(scans):
        hit = s.ranges < max_range
        ang = s.beam_angles()[hit]
        r = s.ranges[hit].astype(np.float64)
        pts.append(s.pose[:2] + np.column_stack([r * np.cos(ang), r * np.sin(ang)]))
        idx.append(np.full(len(r), i))
    return np.concatenate(pts), np.concatenate(idx)


def _apply(m: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """Per-point 3x3 maps ``m`` (N, 3, 3) applied to points (N, 2)."""
    return np.einsum("nij,nj->ni", m[:, :2, :2], pts) + m[:, :2, 2]


#: Two hits closer than this (m) are on the same piece of wall; up to NEIGHBOURS of them count.
SAME_WALL = 0.1
NEIGHBOURS = 16


def _placed(
    true: list[LaserScan], drifted: list[LaserScan], pts: np.ndarray, max_range: float
) -> tuple[np.ndarray, np.ndarray]:
    """Where a drifted robot's map puts each true-world wall point, and whether it saw it.

    A wall point is drawn by every scan of the robot that hit it; its place in the
    map is the mean of where those scans (the robot's hits within SAME_WALL of it)
    put it.
    """
    hits, scan = _endpoints(true, max_range)
    dist, idx = cKDTree(hits).query(pts, k=NEIGHBOURS, distance_upper_bound=SAME_WALL)
    near = np.isfinite(dist)
    seen = near.any(axis=1)
    corr = _corrections(true, drifted)
    out = np.zeros((len(pts), 2))
    for j in range(NEIGHBOURS):
        rows = np.flatnonzero(near[:, j])
        out[rows] += _apply(corr[scan[idx[rows, j]]], pts[rows])
    count = np.maximum(near.sum(axis=1), 1)
    return out / count[:, None], seen


def overlap_fit(
    true_a: list[LaserScan],
    drifted_a: list[LaserScan],
    true_b: list[LaserScan],
    drifted_b: list[LaserScan],
    max_range: float,
    max_points: int = 4000,
) -> tuple[np.ndarray, float, int]:
    """Rigid map from B's drifted world to A's drifted world, fitted on the walls both saw.

    A drifted pair has no exact rigid truth; the truth a merge should find is the
    alignment *on the overlap*.  Every wall point both robots hit (true world) is put
    where each drifted robot's map has it (:func:`_placed`), and the least-squares
    rigid fit of B's positions onto A's is returned, with the RMS residual (metres:
    the distortion no rigid transform removes) and the number of points.  Falls back
    to the identity with ``n = 0`` when the robots share no wall.
    """
    pts, _ = _endpoints(true_b, max_range)
    pts = subsample(pts, 4 * max_points)
    in_a, seen = _placed(true_a, drifted_a, pts, max_range)
    pts, in_a = pts[seen], in_a[seen]
    if len(pts) < 3:
        return np.eye(3), float("nan"), 0
    pts, in_a = subsample(pts, max_points), subsample(in_a, max_points)
    in_b, _ = _placed(true_b, drifted_b, pts, max_range)
    fit = rigid_fit(in_b, in_a)
    resid = in_a - (in_b @ fit[:2, :2].T + fit[:2, 2])
    return fit, float(np.sqrt(np.mean(np.sum(resid**2, axis=1)))), len(pts)
