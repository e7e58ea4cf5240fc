"""The pose graph's sparse normal equations give the dense solution, bit-stable in input order."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import pytest

from pgvd import posegraph
from pgvd.grid import rigid_matrix
from pgvd.posegraph import Solution, solve


@dataclass(frozen=True)
class Edge:
    a: str
    b: str
    matrix: np.ndarray
    covariance: np.ndarray


def random_graph(n: int, seed: int, wrong: bool = False) -> tuple[list[str], list[Edge]]:
    """A connected graph of ``n`` maps: a chain plus as many random chords, with the errors
    of real merges (~1 px, ~0.1 deg) and varied covariances; ``wrong`` turns one chord by
    25 degrees and 60 px (an outlier the robust solution must drop)."""
    rng = np.random.default_rng(seed)
    nodes = [f"r{i:02d}" for i in range(n)]
    truth = {v: rigid_matrix(rng.uniform(-np.pi, np.pi), *rng.uniform(-400, 400, 2)) for v in nodes}
    pairs = {(nodes[i], nodes[i + 1]) for i in range(n - 1)}
    while len(pairs) < min(2 * n, n * (n - 1) // 2):
        i, j = sorted(rng.choice(n, 2, replace=False))
        pairs.add((nodes[i], nodes[j]))
    edges = []
    for k, (a, b) in enumerate(sorted(pairs)):
        m = np.linalg.inv(truth[a]) @ truth[b]
        m = m @ rigid_matrix(math.radians(rng.normal(0, 0.1)), *rng.normal(0, 1.0, 2))
        if wrong and k == len(pairs) // 2:
            m = rigid_matrix(math.radians(25.0), 60.0, 0.0) @ m
        cov = np.diag([*rng.uniform(0.01, 0.5, 2), rng.uniform(1e-8, 1e-5)])
        edges.append(Edge(a, b, m, cov))
    return nodes, edges


def solved_with(monkeypatch, sparse_from: int, nodes: list[str], edges: list[Edge]) -> Solution:
    monkeypatch.setattr(posegraph, "SPARSE_FROM", sparse_from)
    return solve(nodes, edges)


@pytest.mark.parametrize("n", [4, 8, 16, 32, 64])
@pytest.mark.parametrize("wrong", [False, True])
def test_the_sparse_solve_is_the_dense_solve(monkeypatch, n: int, wrong: bool) -> None:
    nodes, edges = random_graph(n, seed=n, wrong=wrong)
    dense = solved_with(monkeypatch, 10**9, nodes, edges)
    sparse = solved_with(monkeypatch, 0, nodes, edges)
    assert sparse.used == dense.used
    assert all(sparse.used) != wrong  # the outlier is dropped by both
    assert sparse.components == dense.components == (tuple(nodes),)
    for v in nodes:
        np.testing.assert_allclose(sparse.transforms[v], dense.transforms[v], rtol=0, atol=1e-9)
        scale = np.abs(dense.covariances[v]).max()
        np.testing.assert_allclose(
            sparse.covariances[v], dense.covariances[v], rtol=0, atol=1e-9 * max(scale, 1.0)
        )


def test_the_sparse_solve_is_bit_identical_in_any_input_order(monkeypatch) -> None:
    nodes, edges = random_graph(48, seed=3, wrong=True)
    first = solved_with(monkeypatch, 0, nodes, edges)
    shuffled = [edges[i] for i in np.random.default_rng(1).permutation(len(edges))]
    again = solved_with(monkeypatch, 0, nodes[::-1], shuffled)
    order = {id(e): k for k, e in enumerate(edges)}
    assert again.used == tuple(first.used[order[id(e)]] for e in shuffled)
    for v in nodes:
        assert again.transforms[v].tobytes() == first.transforms[v].tobytes()
        assert again.covariances[v].tobytes() == first.covariances[v].tobytes()
