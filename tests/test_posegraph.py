"""The robust pose graph: known outliers on synthetic graphs with ground truth."""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass, field

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from bench.posegraph import random_graph
from pgvd import posegraph
from pgvd.grid import matrix_to_pose, rigid_matrix
from pgvd.posegraph import (
    PoseGraphParams,
    Solution,
    components,
    compose_transforms,
    link_problem,
    solve,
    triangle_groups,
)

#: A link's own (overconfident) covariance, as the merge reports them: ~0.1 px, 0.01 deg.
COV = np.diag([0.01, 0.01, 3e-8])


@dataclass(frozen=True)
class Edge:
    a: str
    b: str
    matrix: np.ndarray
    covariance: np.ndarray = field(default_factory=COV.copy)


def world(n: int, seed: int) -> dict[str, np.ndarray]:
    """True placements of ``n`` maps (px -> r0 px): any heading, hundreds of px apart."""
    rng = np.random.default_rng(seed)
    truth = {f"r{i}": rigid_matrix(rng.uniform(-np.pi, np.pi), *rng.uniform(-400, 400, 2))
             for i in range(n)}  # fmt: skip
    truth["r0"] = np.eye(3)
    return truth


def measure(
    truth: dict[str, np.ndarray],
    pairs: list[tuple[str, str]],
    seed: int,
    wrong: dict[tuple[str, str], tuple[float, float, float]] | None = None,
) -> list[Edge]:
    """Links with the errors of real merges (~1 px, ~0.1 deg); ``wrong`` adds
    ``(deg, dx px, dy px)`` to some of them."""
    rng = np.random.default_rng(seed)
    out = []
    for a, b in pairs:
        m = np.linalg.inv(truth[a]) @ truth[b]
        m = m @ rigid_matrix(math.radians(rng.normal(0, 0.1)), *rng.normal(0, 1.0, 2))
        if wrong and (a, b) in wrong:
            deg, dx, dy = wrong[(a, b)]
            m = rigid_matrix(math.radians(deg), dx, dy) @ m
        out.append(Edge(a, b, m))
    return out


def all_pairs(n: int) -> list[tuple[str, str]]:
    return list(itertools.combinations([f"r{i}" for i in range(n)], 2))


def placement_error(truth: dict[str, np.ndarray], got: dict[str, np.ndarray]) -> float:
    """Largest displacement (px) of a map corner, 1000 px out, over all maps."""
    corners = np.array([[0, 1000, 0, 1000], [0, 0, 1000, 1000], [1, 1, 1, 1]])
    return max(float(np.abs((got[r] - truth[r]) @ corners).max()) for r in truth)


def assert_placed_without(
    truth: dict[str, np.ndarray], links: list[Edge], sol: Solution, wrong: set[tuple[str, str]]
) -> None:
    """Placed exactly as if the wrong links had never been given, and near the truth
    (a wrong link of 10 deg alone would move a corner 1000 px out by 170 px)."""
    oracle = solve(truth, [ln for ln in links if (ln.a, ln.b) not in wrong])
    for r in truth:
        assert sol.transforms[r].tobytes() == oracle.transforms[r].tobytes()
    assert placement_error(truth, sol.transforms) < 15.0


def rejected(links: list[Edge], used: tuple[bool, ...]) -> set[tuple[str, str]]:
    return {(ln.a, ln.b) for ln, u in zip(links, used, strict=True) if not u}


# 2-5 m at 0.05 m/cell is 40-100 px.
WRONG = [(10.0, 40.0, -60.0), (-30.0, 0.0, 0.0), (20.0, -100.0, 10.0), (0.0, 60.0, 80.0)]


@pytest.mark.parametrize("seed", range(4))
def test_one_wrong_link_among_five_maps_is_rejected(seed: int) -> None:
    truth = world(5, seed)
    pairs = all_pairs(5)
    bad = pairs[(3 * seed + 1) % len(pairs)]
    links = measure(truth, pairs, seed, {bad: WRONG[seed]})
    sol = solve(truth, links)
    assert rejected(links, sol.used) == {bad}
    assert sol.components == (tuple(sorted(truth)),)
    assert_placed_without(truth, links, sol, {bad})
    c2 = PoseGraphParams().threshold
    assert all(r <= c2 for r, u in zip(sol.residuals, sol.used, strict=True) if u)
    assert sol.residuals[links.index(next(ln for ln in links if (ln.a, ln.b) == bad))] > 10 * c2


@pytest.mark.parametrize("seed", range(3))
def test_two_wrong_links_among_six_maps_are_rejected(seed: int) -> None:
    truth = world(6, 10 + seed)
    pairs = all_pairs(6)
    bad = {pairs[seed]: WRONG[seed], pairs[7 + seed]: WRONG[seed + 1]}
    links = measure(truth, pairs, seed, bad)
    sol = solve(truth, links)
    assert rejected(links, sol.used) == set(bad)
    assert_placed_without(truth, links, sol, set(bad))


def test_a_lone_cycle_with_a_wrong_link_drops_exactly_one() -> None:
    """A lone cycle says *that* it is broken, not where: exactly one link goes (the one
    with the largest residual, not necessarily the wrong one), and the maps are placed
    by the other three, a tree."""
    truth = world(4, 3)
    ring = [("r0", "r1"), ("r1", "r2"), ("r2", "r3"), ("r0", "r3")]
    links = measure(truth, ring, 3, {("r1", "r2"): (15.0, 50.0, 0.0)})
    sol = solve(truth, links)
    assert len(rejected(links, sol.used)) == 1
    assert sol.components == (("r0", "r1", "r2", "r3"),)
    kept = [ln for ln, u in zip(links, sol.used, strict=True) if u]
    mats, _ = compose_transforms("r0", kept)
    for r in truth:
        np.testing.assert_array_equal(sol.transforms[r], mats[r])


def test_a_tree_keeps_even_a_wrong_link_and_is_its_composition() -> None:
    truth = world(5, 4)
    tree = [("r0", "r1"), ("r1", "r2"), ("r1", "r3"), ("r0", "r4")]
    links = measure(truth, tree, 4, {("r1", "r3"): (25.0, 80.0, -30.0)})
    sol = solve(truth, links)
    assert sol.used == (True,) * 4
    mats, covs = compose_transforms("r0", links)
    for r in truth:
        np.testing.assert_array_equal(sol.transforms[r], mats[r])
        np.testing.assert_array_equal(sol.covariances[r], covs[r])


def test_consistent_cycles_reject_nothing() -> None:
    truth = world(7, 5)
    links = measure(truth, all_pairs(7), 5)
    sol = solve(truth, links)
    assert all(sol.used)
    assert placement_error(truth, sol.transforms) < 15.0


def test_same_links_in_any_order_same_bits() -> None:
    truth = world(5, 6)
    links = measure(truth, all_pairs(5), 6, {("r1", "r3"): WRONG[0]})
    first = solve(list(truth), links)
    for perm in (links[::-1], links[3:] + links[:3]):
        again = solve(sorted(truth, reverse=True), perm)
        assert rejected(perm, again.used) == rejected(links, first.used)
        for r in truth:
            assert first.transforms[r].tobytes() == again.transforms[r].tobytes()
            assert first.covariances[r].tobytes() == again.covariances[r].tobytes()


def test_a_map_whose_links_are_all_wrong_stands_alone() -> None:
    """r3 is linked to r0 and r1 only, both wrong (and mutually inconsistent): r3's
    placement cannot be trusted, and it is not pulled into the others' map.
    The other maps keep their correct links."""
    truth = world(4, 7)
    pairs = [("r0", "r1"), ("r0", "r2"), ("r1", "r2"), ("r0", "r3"), ("r1", "r3")]
    links = measure(truth, pairs, 7, {("r0", "r3"): WRONG[0], ("r1", "r3"): WRONG[2]})
    sol = solve(truth, links)
    # one of r3's two links must go; the other is a bridge the graph cannot check.
    assert len(rejected(links, sol.used) & {("r0", "r3"), ("r1", "r3")}) == 1
    assert rejected(links, sol.used) <= {("r0", "r3"), ("r1", "r3")}
    placed = {r: sol.transforms[r] for r in ("r0", "r1", "r2")}
    assert placement_error({r: truth[r] for r in placed}, placed) < 15.0


def test_unlinked_maps_are_components_of_their_own() -> None:
    truth = world(4, 8)
    links = measure(truth, [("r1", "r3")], 8)
    sol = solve(truth, links)
    assert sol.components == (("r0",), ("r1", "r3"), ("r2",))
    np.testing.assert_array_equal(sol.transforms["r3"], links[0].matrix)
    assert not np.isfinite(sol.residuals).all() or sol.residuals[0] < 1e-12


def test_placement_covariance_matches_monte_carlo_on_a_cycle() -> None:
    """The links' covariances through the least squares to first order, eq. (4)."""
    truth = world(3, 9)
    pairs = [("r0", "r1"), ("r1", "r2"), ("r0", "r2")]
    covs = [np.diag([0.5, 0.3, 2e-5]), np.diag([0.2, 0.6, 1e-5]), np.diag([0.4, 0.4, 4e-5])]
    exact = [np.linalg.inv(truth[a]) @ truth[b] for a, b in pairs]
    sol = solve(truth, [Edge(a, b, m, c) for (a, b), m, c in zip(pairs, exact, covs, strict=True)])
    rng = np.random.default_rng(0)
    samples = []
    for _ in range(500):
        noisy = []
        for (a, b), m, c in zip(pairs, exact, covs, strict=True):
            dx, dy, dpsi = rng.multivariate_normal(np.zeros(3), c)
            psi, tx, ty = matrix_to_pose(m)
            noisy.append(Edge(a, b, rigid_matrix(psi + dpsi, tx + dx, ty + dy), c))
        psi, tx, ty = matrix_to_pose(solve(truth, noisy).transforms["r2"])
        samples.append([tx, ty, psi])
    np.testing.assert_allclose(sol.covariances["r2"], np.cov(np.array(samples).T),
                               rtol=0.25, atol=5e-3)  # fmt: skip


@pytest.mark.parametrize(
    "edge, match",
    [
        (Edge("r0", "rX", np.eye(3)), "distinct known nodes"),
        (Edge("r0", "r0", np.eye(3)), "distinct known nodes"),
        (Edge("r0", "r1", np.diag([2.0, 1.0, 1.0])), "not rigid"),
        (Edge("r0", "r1", np.full((3, 3), np.nan)), "finite 3x3"),
        (Edge("r0", "r1", np.eye(3), -np.eye(3)), "positive semi-definite"),
    ],
)
def test_bad_links_are_refused(edge: Edge, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        solve(["r0", "r1"], [edge])


def test_triangle_groups_need_three_link_cycles() -> None:
    """A triangle r0-r1-r2 with a bridge r2-r3 to a square r3-r4-r5-r6 and a lone r7: only
    the triangle is a group; a chord r3-r5 makes the square two triangles."""
    edges = [("r0", "r1"), ("r1", "r2"), ("r0", "r2"), ("r2", "r3")]
    edges += [("r3", "r4"), ("r4", "r5"), ("r5", "r6"), ("r3", "r6")]
    nodes = [f"r{i}" for i in range(8)]
    alone = [("r3",), ("r4",), ("r5",), ("r6",), ("r7",)]
    assert triangle_groups(nodes, edges) == [("r0", "r1", "r2"), *alone]
    assert triangle_groups(nodes, [*edges, ("r3", "r5")]) == [
        ("r0", "r1", "r2"), ("r3", "r4", "r5", "r6"), ("r7",),
    ]  # fmt: skip


@given(st.integers(1, 9), st.data())
def test_triangle_groups_hold_triangles_and_no_bridge(n: int, data: st.DataObject) -> None:
    """Every triangle of the edges lies in one group, and every group within one component of
    the edges that are not bridges (an edge whose ends fall apart without it)."""
    nodes = [f"r{i}" for i in range(n)]
    pairs = [(a, b) for i, a in enumerate(nodes) for b in nodes[i + 1 :]]
    edges = data.draw(st.lists(st.sampled_from(pairs))) if pairs else []
    groups = triangle_groups(nodes, edges)
    assert sorted(r for g in groups for r in g) == nodes
    held = set(edges)
    for a, b, c in itertools.combinations(nodes, 3):
        if {(a, b), (a, c), (b, c)} <= held:
            assert any({a, b, c} <= set(g) for g in groups)
    kept = [
        (a, b)
        for i, (a, b) in enumerate(edges)
        if any(a in c and b in c for c in components(nodes, edges[:i] + edges[i + 1 :]))
    ]
    blocks = components(nodes, kept)
    assert all(any(set(g) <= set(blk) for blk in blocks) for g in groups)


def _reference_problem(link: Edge, nodes: set[str]) -> str | None:
    """:func:`link_problem` as judged from scratch, without the memo."""
    if link.a == link.b or link.a not in nodes or link.b not in nodes:
        return f"link ({link.a!r}, {link.b!r}) must join two distinct known nodes"
    return posegraph._validated.__wrapped__(posegraph._validation_key(link))[0]


@pytest.mark.parametrize("seed", range(3))
def test_memoised_link_checks_give_what_a_fresh_check_gives(seed: int) -> None:
    """Links sound and broken, met again and again (the memo warm), are judged as a fresh
    check judges them, and a solve over a warm memo is the solve over a cold one, bit for
    bit."""
    rng = np.random.default_rng(seed)
    truth = world(6, seed)
    links = measure(truth, all_pairs(6), seed)
    broken = [
        Edge("r0", "r1", np.diag([2.0, 1.0, 1.0])),
        Edge("r0", "r1", np.full((3, 3), np.nan)),
        Edge("r0", "r1", np.eye(3), -np.eye(3)),
        Edge("r0", "r1", np.eye(2)),
        Edge("r0", "r0", np.eye(3)),
    ]
    nodes = set(truth)
    for _ in range(4):
        for link in rng.permutation(np.array(links + broken, dtype=object)):
            assert link_problem(link, nodes) == _reference_problem(link, nodes)
    posegraph._validated.cache_clear()
    cold = solve(truth, links)
    warm = solve(truth, links)
    assert posegraph._validated.cache_info().hits >= len(links)
    assert cold.used == warm.used and cold.residuals == warm.residuals
    for n in truth:
        assert cold.transforms[n].tobytes() == warm.transforms[n].tobytes()
        assert cold.covariances[n].tobytes() == warm.covariances[n].tobytes()


def test_a_solve_served_from_the_memo_is_a_fresh_one_and_not_shared() -> None:
    """A repeated solve returns what a fresh solve gives, bit for bit, and arrays a caller
    may change without changing the next caller's."""
    nodes, edges = random_graph(12, seed=5, links_per_node=2.0, wrong=True)
    posegraph.forget_solutions()
    fresh = posegraph.solve(nodes, edges)
    served = posegraph.solve(nodes, edges)
    assert served.used == fresh.used and not all(fresh.used)
    for v in nodes:
        assert served.transforms[v].tobytes() == fresh.transforms[v].tobytes()
        assert served.covariances[v].tobytes() == fresh.covariances[v].tobytes()
    served.transforms[nodes[1]][0, 2] += 100.0
    again = posegraph.solve(nodes, edges)
    assert again.transforms[nodes[1]].tobytes() == fresh.transforms[nodes[1]].tobytes()
