"""The pose graph's sparse normal equations give the dense solution, bit-stable in input order."""

from __future__ import annotations

import numpy as np
import pytest

from bench.posegraph import Edge, random_graph
from pgvd import posegraph
from pgvd.posegraph import Solution, solve


def solved_with(monkeypatch, sparse_from: int, nodes: list[str], edges: list[Edge]) -> Solution:
    monkeypatch.setattr(posegraph, "SPARSE_FROM", sparse_from)
    return solve(nodes, edges)


@pytest.mark.parametrize("n", [4, 16, 64])
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
