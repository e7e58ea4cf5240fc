"""The global map is a pure, order-independent function of local maps and links."""

from __future__ import annotations

import itertools
from dataclasses import replace

import numpy as np
import pytest

from agent.fusecache import LayerCache
from agent.globalmap import build_components, map_digest
from agent.links import LinkRecord
from pgvd.fusion import fuse_layers
from pgvd.grid import Grid, rigid_matrix
from pgvd.posegraph import compose_transforms, solve


def link(a: str, b: str, m: np.ndarray, score: float = 0.9, accepted: bool = True) -> LinkRecord:
    return LinkRecord(a, 1, b, 1, accepted, m, np.diag([0.2, 0.2, 1e-5]), score, a)


def test_components_use_every_accepted_link_whatever_the_order() -> None:
    """Was Kruskal's best-score tree; now every accepted link counts (here consistent)."""
    m = np.eye(3)
    links = [
        link("a", "b", m, 0.8),
        link("b", "c", m, 0.9),
        link("a", "c", m, 0.7),
        link("d", "e", m, 0.5, accepted=False),
    ]
    blank = Grid(np.zeros((4, 4), np.float32), 0.1)
    maps = {r: (1, blank) for r in "abcde"}
    layouts = {
        tuple((c.anchor, c.members, c.used, c.rejected) for c in build_components(maps, p))
        for p in itertools.permutations(links)
    }
    assert layouts == {
        (
            ("a", ("a", "b", "c"), (("a", "b"), ("a", "c"), ("b", "c")), ()),
            ("d", ("d",), (), ()),
            ("e", ("e",), (), ()),
        )
    }


def test_compose_transforms_walks_links_both_ways() -> None:
    ab = rigid_matrix(0.3, 10.0, -4.0)  # b px -> a px
    bc = rigid_matrix(-0.1, 2.0, 7.0)  # c px -> b px
    mats, covs = compose_transforms("a", [link("a", "b", ab), link("b", "c", bc)])
    np.testing.assert_allclose(mats["c"], ab @ bc)
    mats, _ = compose_transforms("b", [link("a", "b", ab)])
    np.testing.assert_allclose(mats["a"], np.linalg.inv(ab))
    assert covs["c"][2, 2] == pytest.approx(2e-5)  # heading variances add along the path


def test_component_fuses_local_maps_in_a_fixed_order(halves: tuple) -> None:
    a, b, truth = halves
    maps = {"r2": (4, b), "r1": (7, a)}
    (comp,) = build_components(maps, [link("r1", "r2", truth)])
    assert comp.anchor == "r1" and comp.members == ("r1", "r2")
    assert comp.versions == {"r1": 7, "r2": 4}
    # Exactly one fusion of the two local maps: never a fused map fused again.
    # ... at the placement snapped from the link (agent.placement), which is the link's
    np.testing.assert_allclose(comp.transforms["r2"], truth, atol=1 / 64)
    layer, _ = LayerCache().layer("r2", 4, b, comp.transforms["r2"], comp.covariances["r2"])
    direct = fuse_layers(a, [layer])
    np.testing.assert_array_equal(comp.grid.logodds, direct.logodds)
    assert comp.digest == map_digest(direct)


def test_same_inputs_same_global_map_whatever_the_order(halves: tuple) -> None:
    a, b, truth = halves
    third = Grid(np.roll(a.logodds, 5, axis=1), a.resolution, a.origin)
    links = [link("r1", "r2", truth), link("r1", "r3", rigid_matrix(0, -5, 0), 0.5)]
    first = build_components({"r1": (1, a), "r2": (1, b), "r3": (1, third)}, links)
    second = build_components({"r3": (1, third), "r2": (1, b), "r1": (1, a)}, links[::-1])
    assert [c.digest for c in first] == [c.digest for c in second]
    assert first[0].members == ("r1", "r2", "r3")


def test_robot_overlapping_nobody_stays_its_own_component(halves: tuple) -> None:
    a, b, truth = halves
    maps = {"r1": (1, a), "r2": (1, b), "r0": (1, b)}
    comps = build_components(maps, [link("r1", "r2", truth), link("r0", "r1", truth, 0.2, False)])
    assert [(c.anchor, c.members) for c in comps] == [("r0", ("r0",)), ("r1", ("r1", "r2"))]
    lonely = comps[0]
    assert lonely.grid is b and lonely.transforms == {"r0": pytest.approx(np.eye(3))}


def test_digest_changes_with_the_map() -> None:
    g = Grid(np.zeros((4, 5), np.float32), 0.1)
    h = Grid(np.where(np.eye(4, 5) > 0, 2.0, 0.0).astype(np.float32), 0.1)
    assert map_digest(g) != map_digest(h)
    assert map_digest(g) == map_digest(Grid(g.logodds.copy(), 0.1))


def test_composed_covariance_matches_monte_carlo_along_a_reversed_chain() -> None:
    """Eq. (4) through a chain: a parent's heading error moves the child's translation."""
    rng = np.random.default_rng(7)
    # a <- c by link (a, c), then c -> b by link (b, c) walked backwards, then b <- d.
    m_ac, cov_ac = rigid_matrix(0.4, 120.0, -30.0), np.diag([0.3, 0.2, 1e-4])
    m_bc, cov_bc = rigid_matrix(0.7, -50.0, 200.0), np.diag([0.4, 0.4, 2e-4])
    m_bd, cov_bd = rigid_matrix(-1.1, 300.0, 80.0), np.diag([0.5, 0.1, 4e-4])
    tree = [
        LinkRecord("a", 1, "c", 1, True, m_ac, cov_ac, 0.9, "a"),
        LinkRecord("b", 1, "c", 1, True, m_bc, cov_bc, 0.9, "b"),
        LinkRecord("b", 1, "d", 1, True, m_bd, cov_bd, 0.9, "b"),
    ]
    mats, covs = compose_transforms("a", tree)
    np.testing.assert_allclose(mats["d"], m_ac @ np.linalg.inv(m_bc) @ m_bd, atol=1e-9)

    def perturbed(m: np.ndarray, cov: np.ndarray) -> np.ndarray:
        dx, dy, dpsi = rng.multivariate_normal(np.zeros(3), cov)
        psi = np.arctan2(m[0, 1], m[0, 0]) + dpsi
        return rigid_matrix(psi, m[0, 2] + dx, m[1, 2] + dy)

    chains = {
        "b": lambda: perturbed(m_ac, cov_ac) @ np.linalg.inv(perturbed(m_bc, cov_bc)),
        "d": lambda: (
            perturbed(m_ac, cov_ac)
            @ np.linalg.inv(perturbed(m_bc, cov_bc))
            @ perturbed(m_bd, cov_bd)
        ),
    }
    for child, chain in chains.items():
        poses = [chain() for _ in range(20000)]
        samples = np.array([[m[0, 2], m[1, 2], np.arctan2(m[0, 1], m[0, 0])] for m in poses])
        np.testing.assert_allclose(covs[child], np.cov(samples.T), rtol=0.1, atol=2e-3)
    # Summing the links' translation covariances (rotated) misses the heading terms:
    # here that alone would understate the translation variance of d by pixels squared.
    naive = sum(np.trace(c[:2, :2]) for c in (cov_ac, cov_bc, cov_bd))
    assert np.trace(covs["d"][:2, :2]) > naive + 2.0


def rolled(g: Grid, dx: int, dy: int) -> tuple[Grid, np.ndarray]:
    """A copy of ``g`` shifted by ``(dx, dy)`` cells, and the copy-px -> g-px matrix."""
    # (x, y) of g is (x + dx, y + dy) of the copy: copy px -> g px is a shift back
    return Grid(np.roll(g.logodds, (dy, dx), axis=(0, 1)), g.resolution, g.origin), (
        rigid_matrix(0.0, -dx, -dy)
    )


def test_a_lone_inconsistent_cycle_drops_its_link_of_lowest_margin(halves: tuple) -> None:
    """Three real maps on one triangle; the link of lowest margin is a look-alike 30 px and
    10 deg off with a narrow covariance, the two right ones wide (the model-error term).
    GNC alone keeps the look-alike and drops a right link; graded by margin, the look-alike
    leaves, in any order, and the global map is the one without it."""
    a, b, truth = halves
    c, c_to_a = rolled(a, 7, 4)
    place = {"r1": np.eye(3), "r2": truth, "r3": c_to_a}
    maps = {"r1": (1, a), "r2": (1, b), "r3": (1, c)}
    wide = np.diag([4.0, 4.0, 1e-3])

    def graded(p: str, q: str, m: np.ndarray, cov: np.ndarray, margin: float) -> LinkRecord:
        return replace(link(p, q, m), covariance=cov, margin=margin)

    right = [
        graded(p, q, np.linalg.inv(place[p]) @ place[q], wide, margin)
        for (p, q), margin in ((("r1", "r3"), 0.85), (("r2", "r3"), 0.82))
    ]
    off = rigid_matrix(np.radians(10.0), 30.0, 0.0) @ truth
    wrong = graded("r1", "r2", off, np.diag([0.2, 0.2, 1e-5]), 0.62)
    plain = solve(maps, [wrong, *right])
    assert plain.used[0] and not all(plain.used)  # the covariances alone keep the look-alike
    outcomes = {
        (comp.used, comp.rejected, comp.digest)
        for order in itertools.permutations([wrong, *right])
        for comp in build_components(maps, list(order))
    }
    (clean,) = build_components(maps, right)
    assert outcomes == {((("r1", "r3"), ("r2", "r3")), (("r1", "r2"),), clean.digest)}


def test_a_wrong_link_on_cycles_is_dropped_and_the_global_map_is_the_right_one(
    halves: tuple,
) -> None:
    """Four real maps, every pair linked; one link 3 m and 10 deg off (a plausible false
    link) is inconsistent with the three cycles it lies on, and the global map comes out
    bit for bit as if it had never been published."""
    a, b, truth = halves
    c, c_to_a = rolled(a, 7, 4)
    d, d_to_b = rolled(b, -6, 3)
    place = {"r1": np.eye(3), "r2": truth, "r3": c_to_a, "r4": truth @ d_to_b}
    maps = {"r1": (1, a), "r2": (1, b), "r3": (1, c), "r4": (1, d)}
    good = [
        link(p, q, np.linalg.inv(place[p]) @ place[q]) for p, q in itertools.combinations(place, 2)
    ]
    wrong = link("r2", "r3", rigid_matrix(np.radians(10.0), 30.0, 0.0) @ good[3].matrix)
    assert wrong.pair == good[3].pair
    (comp,) = build_components(maps, [*good[:3], wrong, *good[4:]])
    assert comp.rejected == (("r2", "r3"),)
    assert comp.used == tuple(ln.pair for ln in good if ln.pair != ("r2", "r3"))
    (clean,) = build_components(maps, [ln for ln in good if ln.pair != ("r2", "r3")])
    assert comp.digest == clean.digest
    np.testing.assert_allclose(comp.transforms["r4"], place["r4"], atol=1 / 64)  # snapped


def test_a_link_that_is_not_rigid_is_left_out_not_fatal() -> None:
    """A peer's record can carry any finite matrix; a scaled one is dropped and reported."""
    blank = Grid(np.zeros((4, 4), np.float32), 0.1)
    maps = {r: (1, blank) for r in ("r1", "r2", "r3")}
    good = link("r1", "r2", rigid_matrix(0.1, 2.0, 1.0))
    scaled = link("r1", "r3", np.diag([2.0, 2.0, 1.0]))
    comps = build_components(maps, [good, scaled])
    assert [(c.members, c.used, c.rejected) for c in comps] == [
        (("r1", "r2"), (("r1", "r2"),), (("r1", "r3"),)),
        (("r3",), (), (("r1", "r3"),)),
    ]
