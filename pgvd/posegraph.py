"""Robust SE(2) pose graph: every map's frame from all pairwise transforms at once.

Nodes are maps, each one pixel frame; an edge ``(a, b)`` is a pairwise transform ``Z``
(eq. (1) as a matrix, B pixel -> A pixel) with its covariance over ``(x px, y px, psi)``,
eq. (3), as the merge of Saeedi et al. (IROS 2012) returns it.  In each connected
component the anchor is the node of least ``(rank, id)`` (by default the lowest id); the
unknowns are the matrices ``X_i`` from node ``i``'s pixels to the anchor's, and an edge
predicts ``Z = X_a^-1 X_b``.  Its residual is the difference of the ``(tx, ty, psi)``
parameters of ``X_a^-1 X_b`` and ``Z`` (heading wrapped), the parametrisation of the
covariance, weighted by the inverse covariance: a weighted least-squares pose graph solved
by Gauss-Newton.

Outliers: graduated non-convexity with the truncated least-squares cost (GNC-TLS; Yang,
Antonante, Tzoumas and Carlone, "Graduated Non-Convexity for Robust Spatial Perception:
From Non-Minimal Solvers to Global Outlier Rejection", RA-L 2020), rather than pairwise
consistency maximisation (PCM; Mangelson et al., ICRA 2018), because:

- PCM tests *pairs* of loop closures, each pair closing a cycle through the robots'
  odometry.  Here a map is one frame with no odometry and there is at most one link
  per pair of maps, so no two links ever close a cycle on their own: cycles have three
  or more links, and PCM's pairwise test has nothing to test (its group-k extension
  needs a hypergraph maximum clique, NP-hard, for every k up to the longest cycle);
- GNC works on the pose graph itself, one weighted least squares per step, and is
  deterministic: no random sampling, no clique search whose ties depend on an order.

GNC-TLS is not guaranteed to find the *largest* consistent set (Yang et al. report
failures beyond ~70-80 % outliers), and a lone cycle cannot say *which* of its links is
wrong: the link left with the largest residual by the least squares is dropped, which
need not be the wrong one.  A wrong link is identified where it lies on several cycles
whose other links agree.  After GNC, rejected links are offered back one at a time
(smallest residual first) and kept where every link used stays under the threshold, so
the set used is maximal: no rejected link can be added without breaking a cycle.  Where
the caller grades its links (``strength``, e.g. the merge's margin), a lone cycle's
choice is made by that grade instead: a rejected link stronger than a kept one takes its
place where the set stays consistent (:func:`_stronger_kept`), so the weakest link of an
inconsistent cycle is the one left out, whatever the covariances weigh.

A link lying on no cycle (a bridge) has zero residual and is never rejected, so a graph
without cycles comes out exactly as the composition along its tree
(:func:`compose_transforms`).

What the weighting assumes: the link covariances of today's merge are right in shape
but overconfident (standard deviations of ~0.1 px and ~0.01 deg where real errors on
maps with ground truth reach a pixel and 0.1 deg).  Each link's covariance is therefore
floored, ``Sigma + diag(floor_px^2, floor_px^2, floor_psi^2)``, both for the weights
and for the chi-square test that decides inliers.  The placements' covariances
returned are the links' own covariances propagated to first order through the
estimator (eq. (4)), as the composition along a tree does.  Once covariances are
calibrated the floors can go to zero.

Determinism: edges are sorted by content before anything is computed, nodes by id, and
nothing is random; the same edges in any order give the same result bit for bit.
"""

from __future__ import annotations

import hashlib
import math
import threading
from collections import OrderedDict
from collections.abc import Callable, Collection, Iterable, Sequence
from dataclasses import dataclass
from functools import lru_cache
from typing import Generic, Protocol, TypeVar

import numpy as np
from scipy import sparse
from scipy.sparse.linalg import splu
from scipy.special import gammaincinv

from pgvd.grid import matrix_to_pose, rigid_matrix
from pgvd.uncertainty import check_covariance, compose_covariance, inverse_covariance

#: A node's rank: the anchor of a component is its node of least ``(rank(node), node)``.
Rank = Callable[[str], float]


class Link(Protocol):
    """An edge: ``matrix`` maps pixels of ``b`` to pixels of ``a``, with ``covariance``."""

    @property
    def a(self) -> str: ...
    @property
    def b(self) -> str: ...
    @property
    def matrix(self) -> np.ndarray: ...
    @property
    def covariance(self) -> np.ndarray: ...


#: Unknowns from which the normal equations are solved by a sparse LU rather than a dense
#: one.  A pose graph's normal matrix holds a 3x3 block per node and per link, so its dense
#: LU costs (3n)^3 whatever the links; below this size that dense LU is the faster
#: (``python3 -m bench posegraph`` measures both).
SPARSE_FROM = 96

#: A normal matrix: dense below :data:`SPARSE_FROM` unknowns, sparse from there on.
Matrix = np.ndarray | sparse.csr_array


@dataclass(frozen=True)
class PoseGraphParams:
    """Parameters of :func:`solve`.

    Attributes
    ----------
    floor_px : standard deviation added to each link's translation, pixels.
    floor_deg : standard deviation added to each link's heading, degrees.
    confidence : a link is an inlier while its squared Mahalanobis residual stays under
        the chi-square quantile of 3 degrees of freedom at this confidence.
    mu_factor : GNC's step on the surrogate's parameter (Yang et al. use 1.4).
    max_gnc_steps : GNC steps at most.
    max_gn_steps : Gauss-Newton steps at most per weighted least squares.
    """

    floor_px: float = 2.0
    floor_deg: float = 1.0
    confidence: float = 0.99
    mu_factor: float = 1.4
    max_gnc_steps: int = 200
    max_gn_steps: int = 20

    def __post_init__(self) -> None:
        if not (self.floor_px > 0 and self.floor_deg > 0):
            raise ValueError("covariance floors must be > 0 (the weights invert them)")
        if not 0 < self.confidence < 1:
            raise ValueError(f"confidence must be in (0, 1), got {self.confidence}")
        if not self.mu_factor > 1:
            raise ValueError(f"mu_factor must be > 1, got {self.mu_factor}")

    @property
    def threshold(self) -> float:
        """Squared Mahalanobis residual above which a link is an outlier."""
        # chi2.ppf(p, 3) as scipy.stats computes it; scipy.stats alone costs ~40 MB per agent
        return float(2.0 * gammaincinv(1.5, self.confidence))

    @property
    def floor(self) -> np.ndarray:
        return np.diag([self.floor_px**2, self.floor_px**2, math.radians(self.floor_deg) ** 2])


@dataclass(frozen=True)
class Solution:
    """Placements of every node, and which links the joint solution kept.

    Attributes
    ----------
    components : node ids per component of the links kept, each its anchor first and
        the others sorted by id; components sorted by their anchor's ``(rank, id)``.
    transforms : ``{node: 3x3}`` from the node's pixels to its anchor's pixels.
    covariances : ``{node: 3x3}`` over ``(x px, y px, psi)`` of that transform.
    used : per input link, in the order given: kept in the joint solution.
    residuals : per input link, squared Mahalanobis residual (floored covariance)
        against the placements of the component holding ``a``; NaN where ``b`` ended in
        another component.
    """

    components: tuple[tuple[str, ...], ...]
    transforms: dict[str, np.ndarray]
    covariances: dict[str, np.ndarray]
    used: tuple[bool, ...]
    residuals: tuple[float, ...]


def _lowest_id(node: str) -> float:
    """The default :data:`Rank`: every node alike, so the lowest id anchors."""
    return 0.0


def components(
    nodes: Iterable[str], edges: Iterable[tuple[str, str]], rank: Rank = _lowest_id
) -> list[tuple[str, ...]]:
    """Connected components, each its anchor first and the others sorted by id.

    The anchor is the node of least ``(rank(node), node)``; components are sorted by their
    anchor's ``(rank, id)``.  The default rank makes the lowest id the anchor.
    """

    def order(n: str) -> tuple[float, str]:
        return rank(n), n

    parent = {n: n for n in nodes}

    def find(n: str) -> str:
        while parent[n] != n:
            parent[n] = parent[parent[n]]
            n = parent[n]
        return n

    for a, b in edges:
        ra, rb = find(a), find(b)
        if ra != rb:
            parent[max(ra, rb, key=order)] = min(ra, rb, key=order)
    groups: dict[str, list[str]] = {}
    for n in sorted(parent):
        if n != find(n):
            groups.setdefault(find(n), []).append(n)
    return [(r, *groups.get(r, ())) for r in sorted({find(n) for n in parent}, key=order)]


def triangle_groups(
    nodes: Iterable[str], edges: Iterable[tuple[str, str]]
) -> list[tuple[str, ...]]:
    """Nodes joined through edges that each lie on a triangle of ``edges``.

    A wrong link on a triangle disagrees with the two others of a three-link cycle, where
    the accumulated uncertainty is smallest and the robust solution (GNC-TLS) drops a link
    of a broken cycle.  On a longer cycle alone the error spreads over many links and may
    pass the chi-square test, and a bridge lies on no cycle at all.  Components of the
    edges on a triangle, sorted as :func:`components`; each lies within one 2-edge-connected
    component (no edge on a triangle is a bridge).
    """
    nodes = list(nodes)
    edges = list(edges)
    adjacent: dict[str, set[str]] = {n: set() for n in nodes}
    for a, b in edges:
        adjacent[a].add(b)
        adjacent[b].add(a)
    on_triangle = [(a, b) for a, b in edges if (adjacent[a] & adjacent[b]) - {a, b}]
    return components(nodes, on_triangle)


def compose_transforms(
    anchor: str, tree: Sequence[Link]
) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
    """Matrices node px -> anchor px along ``tree``, and their first-order covariances.

    A link's matrix maps ``b`` to ``a``; walking it from ``b`` to ``a`` uses the inverse
    and its covariance.  Covariances compose to first order, eq. (4), with the Jacobian of
    eq. (1): a parent's heading error also moves the child's translation
    (:func:`pgvd.uncertainty.compose_covariance`).  On a tree this is also the
    least-squares solution of the pose graph, whose residuals are all zero.
    """
    mats = {anchor: np.eye(3)}
    covs = {anchor: np.zeros((3, 3))}
    adjacency: dict[str, list[tuple[str, np.ndarray, np.ndarray]]] = {}
    for ln in tree:
        adjacency.setdefault(ln.a, []).append((ln.b, ln.matrix, ln.covariance))
        adjacency.setdefault(ln.b, []).append(
            (ln.a, np.linalg.inv(ln.matrix), inverse_covariance(ln.matrix, ln.covariance))
        )
    frontier = [anchor]
    while frontier:
        node = frontier.pop(0)
        for child, m, cov in sorted(adjacency.get(node, []), key=lambda t: t[0]):
            if child in mats:
                continue
            mats[child] = mats[node] @ m
            covs[child] = compose_covariance(mats[node], covs[node], m, cov)
            frontier.append(child)
    return mats, covs


@dataclass(frozen=True)
class _Edges:
    """Links of one component as arrays: node indices, measured poses, covariances."""

    ia: np.ndarray  # (m,) int
    ib: np.ndarray  # (m,) int
    z: np.ndarray  # (m, 3) measured (tx, ty, psi)
    info: np.ndarray  # (m, 3, 3) inverse of the floored covariance
    cov: np.ndarray  # (m, 3, 3) the link's own covariance

    def subset(self, keep: np.ndarray) -> _Edges:
        return _Edges(self.ia[keep], self.ib[keep], self.z[keep], self.info[keep], self.cov[keep])


def _wrap(angle: np.ndarray) -> np.ndarray:
    return (angle + np.pi) % (2 * np.pi) - np.pi


def _rot_t(psi: np.ndarray) -> np.ndarray:
    """``R_psi^T`` of eq. (2) for every heading, (m, 2, 2)."""
    c, s = np.cos(psi), np.sin(psi)
    return np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2)


def _residuals(x: np.ndarray, e: _Edges) -> np.ndarray:
    """``pose(X_a^-1 X_b) - pose(Z)`` per edge, (m, 3), heading wrapped."""
    d = x[e.ib, :2] - x[e.ia, :2]
    t = np.einsum("mij,mj->mi", _rot_t(x[e.ia, 2]), d)
    psi = _wrap(x[e.ib, 2] - x[e.ia, 2] - e.z[:, 2])
    return np.column_stack([t - e.z[:, :2], psi])


def _jacobians(x: np.ndarray, e: _Edges) -> tuple[np.ndarray, np.ndarray]:
    """d residual / d x_a and d x_b, each (m, 3, 3)."""
    psi = x[e.ia, 2]
    c, s = np.cos(psi), np.sin(psi)
    rt = _rot_t(psi)
    drt = np.stack([np.stack([-s, -c], -1), np.stack([c, -s], -1)], -2)  # d R^T / d psi
    d = x[e.ib, :2] - x[e.ia, :2]
    ja = np.zeros((len(psi), 3, 3))
    jb = np.zeros((len(psi), 3, 3))
    ja[:, :2, :2] = -rt
    ja[:, :2, 2] = np.einsum("mij,mj->mi", drt, d)
    ja[:, 2, 2] = -1.0
    jb[:, :2, :2] = rt
    jb[:, 2, 2] = 1.0
    return ja, jb


def _block_matrix(n: int, e: _Edges, ja: np.ndarray, jb: np.ndarray, omega: np.ndarray) -> Matrix:
    """``sum_k J_k^T Omega_k J_k`` over the edges, (3n x 3n): one 3x3 block per node and
    one per pair of linked nodes, whatever the number of nodes.  ``ja``, ``jb`` are the
    edges' Jacobians (:func:`_jacobians`).  Dense below :data:`SPARSE_FROM` unknowns, where
    building a sparse matrix costs more than the whole dense solve, sparse from there on.

    The blocks are summed in edge order (:func:`solve` sorts the edges by content), so the
    same edges give the same matrix bit for bit.
    """
    pairs = [
        (i, k, ji.transpose(0, 2, 1) @ omega @ jk)
        for i, ji in ((e.ia, ja), (e.ib, jb))
        for k, jk in ((e.ia, ja), (e.ib, jb))
    ]
    if 3 * n < SPARSE_FROM:
        blocks = np.zeros((n, n, 3, 3))
        for i, k, block in pairs:
            np.add.at(blocks, (i, k), block)
        return blocks.transpose(0, 2, 1, 3).reshape(3 * n, 3 * n)
    three = np.arange(3)
    rows = [np.broadcast_to((3 * i)[:, None, None] + three[:, None], b.shape) for i, _, b in pairs]
    cols = [np.broadcast_to((3 * k)[:, None, None] + three, b.shape) for _, k, b in pairs]
    vals = np.concatenate([b for _, _, b in pairs], None)
    at = (np.concatenate(rows, None), np.concatenate(cols, None))
    return sparse.coo_array((vals, at), shape=(3 * n, 3 * n)).tocsr()


def _principal(h: Matrix, idx: np.ndarray) -> Matrix:
    """The rows and columns ``idx`` of ``h``."""
    return h[np.ix_(idx, idx)] if isinstance(h, np.ndarray) else h[idx][:, idx]


def _normal_equations(x: np.ndarray, e: _Edges, w: np.ndarray) -> tuple[Matrix, np.ndarray]:
    """``H = sum w J^T Omega J`` (3n x 3n, :func:`_block_matrix`) and
    ``g = sum w J^T Omega r`` over all nodes."""
    r = _residuals(x, e)
    ja, jb = _jacobians(x, e)
    wo = w[:, None, None] * e.info
    wor = (wo @ r[:, :, None])[:, :, 0]
    g = np.zeros((len(x), 3))
    for i, ji in ((e.ia, ja), (e.ib, jb)):
        np.add.at(g, i, (ji.transpose(0, 2, 1) @ wor[:, :, None])[:, :, 0])
    return _block_matrix(len(x), e, ja, jb, wo), g.ravel()


def _solve(h: Matrix, rhs: np.ndarray) -> np.ndarray:
    """``h^-1 rhs``: dense LU below :data:`SPARSE_FROM` unknowns, sparse LU (SuperLU,
    single-threaded and deterministic) from there on."""
    if isinstance(h, np.ndarray):
        return np.linalg.solve(h, rhs)
    if h.shape[0] < SPARSE_FROM:
        return np.linalg.solve(h.toarray(), rhs)
    return splu(sparse.csc_array(h)).solve(np.asarray(rhs, dtype=np.float64))


def _damped_solve(h: Matrix, rhs: np.ndarray) -> np.ndarray:
    """``h^-1 rhs`` with a tiny damping: unknowns no weighted link constrains stay at 0
    (their rows are empty) instead of making ``h`` singular."""
    size = h.shape[0]
    damping = 1e-12 * (1.0 + np.abs(h.diagonal()).max(initial=0.0))
    if isinstance(h, np.ndarray):
        return _solve(h + damping * np.eye(size), rhs)
    diagonal = np.arange(size)
    damped = h + sparse.csr_array((np.full(size, damping), (diagonal, diagonal)), h.shape)
    return _solve(damped, rhs)


def _gauss_newton(x: np.ndarray, e: _Edges, w: np.ndarray, steps: int, free: slice) -> np.ndarray:
    """Weighted least squares from ``x``; node 0 (the anchor) is held fixed.

    ``free`` selects the parameters solved for within each node (all three, or the
    translation alone with the headings held).  A tiny damping keeps nodes whose links
    all carry zero weight where they are instead of making the system singular.
    """
    x = x.copy()
    idx = (np.arange(3 * len(x)).reshape(-1, 3)[1:, free]).ravel()
    for _ in range(steps):
        h, g = _normal_equations(x, e, w)
        dx = _damped_solve(_principal(h, idx), -g[idx])
        x.reshape(-1)[idx] += dx
        if np.abs(dx).max(initial=0.0) < 1e-9:
            break
    return x


def _chordal_headings(n: int, e: _Edges, w: np.ndarray) -> np.ndarray:
    """Headings by chordal relaxation: least squares on ``e^{i psi}``, then projected.

    ``psi_b = psi_a + psi_z`` is linear in unit complex numbers, ``z_b = z_a u``; solving
    it unconstrained and normalising is the usual initialisation of pose graphs (no
    starting point needed, so an outlier on a spanning tree does not bias the start).
    Each link is one row with two entries, so the system is sparse like the pose graph's.
    """
    m = len(e.z)
    weight = np.sqrt(w * e.info[:, 2, 2])
    u = np.exp(1j * e.z[:, 2]) * weight
    rows = np.concatenate([np.arange(m), np.arange(m)])
    cols = np.concatenate([e.ib, e.ia])
    vals = np.concatenate([weight + 0j, -u])
    if 2 * n < SPARSE_FROM:  # as the normal equations (:func:`_block_matrix`)
        a = np.zeros((m, n), complex)
        a[rows, cols] = vals  # a link joins two distinct nodes: no entry twice
        rhs, free = -a[:, 0], a[:, 1:]  # the anchor's z is 1
        real: Matrix = np.block([[free.real, -free.imag], [free.imag, free.real]])
    else:
        a = sparse.csr_array((vals, (rows, cols)), shape=(m, n))
        rhs, free = -a[:, [0]].toarray()[:, 0], a[:, 1:]
        real = sparse.vstack(
            [sparse.hstack([free.real, -free.imag]), sparse.hstack([free.imag, free.real])],
            format="csr",
        )
    sol = _damped_solve(real.T @ real, real.T @ np.concatenate([rhs.real, rhs.imag]))
    z = np.concatenate([[1.0 + 0j], sol[: n - 1] + 1j * sol[n - 1 :]])
    return np.where(np.abs(z) > 1e-12, np.angle(z), 0.0)


def _weighted_solution(n: int, e: _Edges, w: np.ndarray, params: PoseGraphParams) -> np.ndarray:
    """Placements ``(n, 3)`` minimising the weighted squared residuals: chordal headings,
    then translations for those headings (a linear problem: one step), then all."""
    x = np.zeros((n, 3))
    x[:, 2] = _chordal_headings(n, e, w)
    x = _gauss_newton(x, e, w, 1, slice(0, 2))
    return _gauss_newton(x, e, w, params.max_gn_steps, slice(0, 3))


def _mahalanobis(x: np.ndarray, e: _Edges) -> np.ndarray:
    r = _residuals(x, e)
    return np.einsum("mi,mij,mj->m", r, e.info, r)


def _tls_weights(r2: np.ndarray, mu: float, c2: float) -> np.ndarray:
    """GNC-TLS weight update of Yang et al. (2020), closed form per residual."""
    lo, hi = mu / (mu + 1) * c2, (mu + 1) / mu * c2
    mid = np.sqrt(c2 * mu * (mu + 1) / np.maximum(r2, 1e-300)) - mu
    return np.where(r2 >= hi, 0.0, np.where(r2 <= lo, 1.0, np.clip(mid, 0.0, 1.0)))


def _gnc_inliers(n: int, e: _Edges, x: np.ndarray, params: PoseGraphParams) -> np.ndarray:
    """GNC-TLS: the surrogate starts convex (mu small) and tends to the TLS cost.

    ``x``: the placements with every link weighted 1 (:func:`_unweighted`), where GNC starts.
    """
    c2 = params.threshold
    w = np.ones(len(e.z))
    r2 = _mahalanobis(x, e)
    if r2.max(initial=0.0) <= c2:
        return np.ones(len(w), dtype=bool)
    mu = c2 / max(2.0 * r2.max() - c2, 1e-12)
    for _ in range(params.max_gnc_steps):
        new = _tls_weights(r2, mu, c2)
        x = _weighted_solution(n, e, new, params)
        r2 = _mahalanobis(x, e)
        binary = np.all((new == 0.0) | (new == 1.0))
        if binary and np.array_equal(new, w):
            break
        w = new
        mu *= params.mu_factor
    return w > 0.5


def _consistent(n: int, e: _Edges, keep: np.ndarray, params: PoseGraphParams) -> bool:
    x = _weighted_solution(n, e.subset(keep), np.ones(int(keep.sum())), params)
    return bool(_mahalanobis(x, e.subset(keep)).max(initial=0.0) <= params.threshold)


def _maximal(n: int, e: _Edges, keep: np.ndarray, params: PoseGraphParams) -> np.ndarray:
    """Offer each rejected link back, smallest residual first; keep it where the whole
    set stays consistent.  Links to nodes the kept set does not reach always fit."""
    keep = keep.copy()
    if keep.all():  # nothing to offer back: the common case of a consistent component
        return keep
    x = _weighted_solution(n, e, keep.astype(float), params)
    r2 = _mahalanobis(x, e)
    for k in sorted(np.flatnonzero(~keep), key=lambda k: (r2[k], k)):
        trial = keep.copy()
        trial[k] = True
        if _consistent(n, e, trial, params):
            keep = trial
    return keep


def _stronger_kept(
    n: int, e: _Edges, keep: np.ndarray, grade: np.ndarray, params: PoseGraphParams
) -> np.ndarray:
    """Swap rejected links, strongest first, for kept ones of lower ``grade``, weakest
    first, wherever the swap leaves the set consistent.

    A lone inconsistent cycle is consistent without any one of its links, and GNC drops
    the one the covariances leave with the largest residual: a wrong link with a narrow
    covariance pushes a right one out.  The grades decide instead.  Each swap trades a
    link for a stronger one, so the swaps end; ties go by the links' sorted order.
    """
    keep = keep.copy()
    for d in sorted(np.flatnonzero(~keep), key=lambda k: (-grade[k], k)):
        for k in sorted(np.flatnonzero(keep), key=lambda k: (grade[k], k)):
            if grade[k] >= grade[d]:
                break
            trial = keep.copy()
            trial[k], trial[d] = False, True
            if _consistent(n, e, trial, params):
                keep = trial
                break
    return keep


def _sandwich_covariances(x: np.ndarray, e: _Edges) -> np.ndarray:
    """First-order covariance of the placements, ``A Sigma A^T`` with
    ``A = H^-1 J^T Omega`` the estimator's sensitivity to each link, ``Sigma`` the
    links' own covariances (eq. (4) through the least squares).  Summed over the links,
    that is ``H^-1 M H^-1`` with ``M = sum J^T Omega Sigma Omega J``, as sparse as ``H``.
    (n, 3, 3)."""
    n = len(x)
    h, _ = _normal_equations(x, e, np.ones(len(e.z)))
    spread = _block_matrix(n, e, *_jacobians(x, e), e.info @ e.cov @ e.info)
    # every block of H^-1 is needed: a dense inverse, which a sparse LU's solve of 3n
    # right-hand sides is slower than at any size this fleet reaches
    free = np.arange(3, 3 * n)
    h_free, spread_free = _principal(h, free), _principal(spread, free)
    hinv = np.linalg.inv(h_free if isinstance(h_free, np.ndarray) else h_free.toarray())
    out = hinv @ (spread_free @ hinv)
    covs = np.zeros((n, 3, 3))
    for i in range(1, n):
        block = out[3 * i - 3 : 3 * i, 3 * i - 3 : 3 * i]
        covs[i] = (block + block.T) / 2.0
    return covs


def _prepare(nodes: Sequence[str], links: Sequence[Link], params: PoseGraphParams) -> _Edges:
    index = {n: i for i, n in enumerate(nodes)}
    z = np.array([matrix_to_pose(ln.matrix) for ln in links]).reshape(-1, 3)[:, [1, 2, 0]]
    cov = np.array([_covariance(ln) for ln in links]).reshape(-1, 3, 3)
    return _Edges(
        ia=np.array([index[ln.a] for ln in links], dtype=int),
        ib=np.array([index[ln.b] for ln in links], dtype=int),
        z=z,
        info=np.linalg.inv(cov + params.floor),
        cov=cov,
    )


def link_problem(link: Link, nodes: Collection[str]) -> str | None:
    """Why :func:`solve` would refuse ``link``, or None if it is fine."""
    return _problem(link, nodes, _validation_key(link))


def _problem(link: Link, nodes: Collection[str], key: _ValidationKey) -> str | None:
    """:func:`link_problem` of ``link``, whose :func:`_validation_key` is ``key``."""
    if link.a == link.b or link.a not in nodes or link.b not in nodes:
        return f"link ({link.a!r}, {link.b!r}) must join two distinct known nodes"
    return _validated(key)[0]


#: A link's ends, and the shape and bytes of its matrix and covariance as float64: all that
#: :func:`_validated` reads of it.
_ValidationKey = tuple[str, str, tuple[int, ...], bytes, tuple[int, ...], bytes]


def _validation_key(link: Link) -> _ValidationKey:
    m = np.asarray(link.matrix, dtype=np.float64)
    c = np.asarray(link.covariance, dtype=np.float64)
    return (link.a, link.b, m.shape, m.tobytes(), c.shape, c.tobytes())


@lru_cache(maxsize=1 << 15)
def _validated(key: _ValidationKey) -> tuple[str | None, np.ndarray | None]:
    """What :func:`link_problem` finds in a link's matrix and covariance, and the covariance
    checked (:func:`pgvd.uncertainty.check_covariance`; None with a problem).

    Memoised by content: a fleet solves its pose graph at every registration, over every
    accepted link held (thousands at 128 robots), and a link's content never changes, so
    judging each anew took half of a solve.  The arrays are rebuilt from the key's bytes,
    so a cached verdict is exactly the one a fresh check gives.
    """
    a, b, m_shape, m_bytes, c_shape, c_bytes = key
    where = f"link ({a!r}, {b!r})"
    m = np.frombuffer(m_bytes, dtype=np.float64).reshape(m_shape)
    if m.shape != (3, 3) or not np.isfinite(m).all():
        return f"{where}: matrix must be a finite 3x3 array", None
    if not np.allclose(m[:2, :2] @ m[:2, :2].T, np.eye(2), atol=1e-6) or not np.allclose(
        m[2], [0.0, 0.0, 1.0]
    ):
        return f"{where}: matrix is not rigid", None
    try:
        cov = check_covariance(np.frombuffer(c_bytes, dtype=np.float64).reshape(c_shape))
    except ValueError as exc:
        return f"{where}: {exc}", None
    cov.setflags(write=False)  # shared by every solve that meets this link
    return None, cov


def _covariance(link: Link) -> np.ndarray:
    """The checked covariance of a link :func:`link_problem` passed (:func:`_validated`)."""
    cov = _validated(_validation_key(link))[1]
    if cov is None:  # only a link solve() refused gets here
        raise ValueError(f"link ({link.a!r}, {link.b!r}) has no sound covariance")
    return cov


#: A link's ends and the bytes of its matrix and covariance as float64 (of its
#: :func:`_validation_key`): what orders the links of a solve and names their content.
_ContentKey = tuple[str, str, bytes, bytes]


T = TypeVar("T")


class _Memo(Generic[T]):
    """The last ``size`` results of one step of :func:`solve`, by a digest of its inputs
    (:func:`_component_digest`).

    A fleet solves the same components again and again: each rebuild of the global map
    and each check of a predicted link solves every component of the links held, and
    between two of them most components' links stay as they were.  A result held is the
    one a fresh solve gives (the solve is a pure function of the digested inputs); it is
    handed out as copies, so no caller can change what the next one gets.  Thread-safe:
    an agent solves on more than one thread.
    """

    def __init__(self, size: int) -> None:
        self._held: OrderedDict[bytes, T] = OrderedDict()
        self._size = size
        self._lock = threading.Lock()

    def get(self, key: bytes) -> T | None:
        with self._lock:
            if key not in self._held:
                return None
            self._held.move_to_end(key)
            return self._held[key]

    def clear(self) -> None:
        with self._lock:
            self._held.clear()

    def put(self, key: bytes, value: T) -> None:
        with self._lock:
            self._held[key] = value
            while len(self._held) > self._size:
                self._held.popitem(last=False)


#: Results each step of :func:`solve` holds (:class:`_Memo`): a few hundred kB at 16 maps.
MEMO_SIZE = 64
#: Unweighted solutions held with their edges (:func:`_unweighted`): the edges of a
#: component of thousands of links take some hundreds of kB, and a solution serves the
#: placements of the same solve.
UNWEIGHTED_SIZE = 4
_UNWEIGHTED: _Memo[tuple[np.ndarray, _Edges]] = _Memo(UNWEIGHTED_SIZE)
_INLIERS: _Memo[np.ndarray] = _Memo(MEMO_SIZE)
_PLACED: _Memo[tuple[dict[str, np.ndarray], dict[str, np.ndarray]]] = _Memo(MEMO_SIZE)


def forget_solutions() -> None:
    """Drop every result :func:`solve` holds (:class:`_Memo`): the next solve computes
    afresh, as a benchmark timing the solve needs."""
    _UNWEIGHTED.clear()
    _INLIERS.clear()
    _PLACED.clear()


def _unweighted(
    digest: bytes, comp: Sequence[str], links: Sequence[Link], params: PoseGraphParams
) -> tuple[np.ndarray, _Edges]:
    """:func:`_weighted_solution` of ``links`` of ``comp``, every link weighted 1, and their
    edges (:func:`_prepare`); held in :data:`_UNWEIGHTED` by the component's ``digest``
    (:func:`_component_digest`).

    GNC starts from it (:func:`_gnc_inliers`), and a component whose links GNC all keeps is
    placed by the very same solution (:func:`_placements`): the same nodes, links and order
    give the same digest, so the placements are those of a fresh solve bit for bit, at a
    third of the cost.  The solution is handed out as a copy; the edges are only read.
    """
    held = _UNWEIGHTED.get(digest)
    if held is None:
        e = _prepare(comp, links, params)
        held = (_weighted_solution(len(comp), e, np.ones(len(e.z)), params), e)
        _UNWEIGHTED.put(digest, held)
    return held[0].copy(), held[1]


def _component_digest(
    comp: Sequence[str], keys: Iterable[_ContentKey], params: PoseGraphParams
) -> bytes:
    """SHA-256 of all a component's solution depends on: its nodes in order (the anchor
    first), its links' content (:data:`_ContentKey`) in the order solved, the parameters."""
    h = hashlib.sha256(repr((tuple(comp), params)).encode())
    for a, b, m, c in keys:
        h.update(repr((a, b)).encode())
        h.update(m)
        h.update(c)
    return h.digest()


def _robust_inliers(
    comp: Sequence[str],
    links: Sequence[Link],
    keys: list[_ContentKey],
    params: PoseGraphParams,
) -> np.ndarray:
    """GNC-TLS's inliers among ``links`` of ``comp``, with every rejected link that fits
    offered back (:func:`_gnc_inliers`, :func:`_maximal`); held in :data:`_INLIERS`."""
    digest = _component_digest(comp, keys, params)
    held = _INLIERS.get(digest)
    if held is None:
        start, e = _unweighted(digest, comp, links, params)
        held = _maximal(len(comp), e, _gnc_inliers(len(comp), e, start, params), params)
        _INLIERS.put(digest, held)
    return np.array(held, dtype=bool)


def _place(
    comp: Sequence[str],
    links: Sequence[Link],
    keys: Iterable[_ContentKey],
    params: PoseGraphParams,
) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
    """Transforms to ``comp[0]`` (the anchor) and covariances of one component from its
    kept ``links``, whose :data:`_ContentKey` are ``keys``; held in :data:`_PLACED`."""
    digest = _component_digest(comp, keys, params)
    held = _PLACED.get(digest)
    if held is None:
        held = _placements(comp, links, digest, params)
        _PLACED.put(digest, held)
    mats, covs = held
    return {n: m.copy() for n, m in mats.items()}, {n: c.copy() for n, c in covs.items()}


def _placements(
    comp: Sequence[str], links: Sequence[Link], digest: bytes, params: PoseGraphParams
) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
    """:func:`_place` computed; ``digest`` names ``comp`` and ``links``."""
    if len(links) == len(comp) - 1:  # a tree: composition is the least-squares optimum
        return compose_transforms(comp[0], links)
    x, e = _unweighted(digest, comp, links, params)
    covs = _sandwich_covariances(x, e)
    mats = {n: rigid_matrix(x[i, 2], x[i, 0], x[i, 1]) for i, n in enumerate(comp)}
    mats[comp[0]] = np.eye(3)
    return mats, {n: covs[i] for i, n in enumerate(comp)}


def solve(
    nodes: Iterable[str],
    links: Sequence[Link],
    params: PoseGraphParams | None = None,
    rank: Rank = _lowest_id,
    strength: Callable[[Link], float] | None = None,
) -> Solution:
    """Place every node in its component's anchor frame from all links at once.

    Parameters
    ----------
    nodes : node ids (maps); nodes no link reaches are components of their own.
    links : pairwise transforms, ``matrix`` B px -> A px and its 3x3 covariance over
        ``(x px, y px, psi rad)``, eq. (3).  Several links may join the same pair.
    params : thresholds and floors, :class:`PoseGraphParams`.
    rank : each component is anchored at its node of least ``(rank(node), node)``
        (:func:`components`); by default at its lowest id.  The placements and their
        covariances, eq. (4), are relative to that anchor.
    strength : a grade of each link (higher: more trusted); where a cycle is inconsistent,
        its weakest links are the ones left out (:func:`_stronger_kept`).  None: GNC's
        choice stands.

    Returns
    -------
    :class:`Solution`; components are those of the links kept.

    Raises
    ------
    ValueError
        On a link :func:`link_problem` finds fault with.
    """
    params = params or PoseGraphParams()
    node_list = sorted(set(nodes))
    known = set(node_list)
    # a link's bytes are read once, both to judge it and as its content
    keys = [_validation_key(ln) for ln in links]
    for ln, key in zip(links, keys, strict=True):
        problem = _problem(ln, known, key)
        if problem:
            raise ValueError(problem)
    content = [(a, b, m, c) for a, b, _, m, _, c in keys]
    order = sorted(range(len(links)), key=content.__getitem__)
    ordered = [links[i] for i in order]
    keep = np.zeros(len(ordered), dtype=bool)
    grouped = components(node_list, [(ln.a, ln.b) for ln in ordered], rank)
    for comp, idx in zip(grouped, _by_component(grouped, ordered), strict=True):
        if len(idx) == len(comp) - 1:
            keep[idx] = True  # no cycle: nothing can be checked, nothing rejected
            continue
        inside = [ordered[k] for k in idx]
        inliers = _robust_inliers(comp, inside, [content[order[k]] for k in idx], params)
        if strength is not None and not inliers.all():
            e = _prepare(comp, inside, params)
            grade = np.array([strength(ordered[k]) for k in idx], dtype=np.float64)
            inliers = _stronger_kept(len(comp), e, inliers, grade, params)
        keep[idx] = inliers
    kept = [k for k in range(len(ordered)) if keep[k]]
    final = components(node_list, [(ordered[k].a, ordered[k].b) for k in kept], rank)
    transforms: dict[str, np.ndarray] = {}
    covariances: dict[str, np.ndarray] = {}
    for comp, idx in zip(final, _by_component(final, [ordered[k] for k in kept]), strict=True):
        inside = [kept[i] for i in idx]
        mats, covs = _place(
            comp, [ordered[k] for k in inside], [content[order[k]] for k in inside], params
        )
        transforms.update(mats)
        covariances.update(covs)
    checked = [_validated(keys[i])[1] for i in order]
    r2 = _link_residuals(ordered, checked, final, transforms, params)
    used = np.zeros(len(links), dtype=bool)
    residuals = np.full(len(links), np.nan)
    used[order] = keep
    residuals[order] = r2
    return Solution(
        components=tuple(final),
        transforms={n: transforms[n] for n in node_list},
        covariances={n: covariances[n] for n in node_list},
        used=tuple(bool(u) for u in used),
        residuals=tuple(float(r) for r in residuals),
    )


def _by_component(comps: Sequence[tuple[str, ...]], links: Sequence[Link]) -> list[list[int]]:
    """The indices of ``links`` in each of ``comps``, in order: a link lies in the component
    of its ``a``.  One pass over the links, not one per component (most components of a
    fleet's first links are single robots)."""
    where = {n: i for i, comp in enumerate(comps) for n in comp}
    out: list[list[int]] = [[] for _ in comps]
    for k, ln in enumerate(links):
        out[where[ln.a]].append(k)
    return out


def _link_residuals(
    links: Sequence[Link],
    covs: Sequence[np.ndarray | None],
    final: Sequence[tuple[str, ...]],
    transforms: dict[str, np.ndarray],
    params: PoseGraphParams,
) -> np.ndarray:
    """Squared Mahalanobis residual (floored covariance) of each link against the
    placements, NaN where its ends lie in two components of ``final``; all links at once
    (a solve reports one per link held, thousands at 128 robots).  ``covs``: each link's
    checked covariance (:func:`_validated`)."""
    anchor_of = {n: comp[0] for comp in final for n in comp}
    r2 = np.full(len(links), np.nan)
    inside = [k for k, ln in enumerate(links) if anchor_of[ln.a] == anchor_of[ln.b]]
    if not inside:
        return r2
    held = [links[k] for k in inside]
    pred = np.linalg.inv(np.stack([transforms[ln.a] for ln in held])) @ np.stack(
        [transforms[ln.b] for ln in held]
    )
    z = np.stack([np.asarray(ln.matrix, dtype=np.float64) for ln in held])
    # the heading as pgvd.grid.heading reads one matrix, of every matrix at once
    turn = np.arctan2(pred[:, 0, 1], pred[:, 0, 0]) - np.arctan2(z[:, 0, 1], z[:, 0, 0])
    r = np.column_stack([pred[:, 0, 2] - z[:, 0, 2], pred[:, 1, 2] - z[:, 1, 2], _wrap(turn)])
    info = np.linalg.inv(np.stack([covs[k] for k in inside]) + params.floor)
    r2[inside] = np.einsum("mi,mij,mj->m", r, info, r)
    return r2
