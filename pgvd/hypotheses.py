"""The translation stage of the search: per searched heading, B's PGVD (13)-(24) and edges,
Gamma (26)-(28) and rho (32), and the translations they and the whole-map overlay propose,
each slid to the best overlay nearby and verified by the edge pairs passing (32) there."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pgvd.edge_matching import (
    EdgeCorrelator,
    PairSupport,
    pair_support,
    rho_test,
    rho_threshold,
)
from pgvd.graph import EdgeGraph, build_graph
from pgvd.gvd import pgvd
from pgvd.heading_search import Rotated, translation
from pgvd.params import MergeParams
from pgvd.rotation import HeadingCandidate
from pgvd.stage_clock import StageClock
from pgvd.uncertainty import rotation_blur


@dataclass
class Hypothesis:
    """One verified translation of B turned by one candidate heading, at the coarse scale."""

    heading: HeadingCandidate
    coarse_matrix: np.ndarray  # coarse B -> A's coarse crop
    evidence: float  # agree - disagreement_weight * disagree (walls only)
    search_evidence: float  # OffParams.search_weights
    ratio: float
    support: int
    passing: np.ndarray
    graph_b: EdgeGraph
    rotation: np.ndarray  # coarse B -> crop of the rotated coarse B (where sp_b lives)
    sp_b: np.ndarray
    gamma: np.ndarray


@dataclass
class _Matching:
    """B's edges at one heading, Gamma (27) against A's and the pairs passing (32)."""

    graph_b: EdgeGraph
    sp_b: np.ndarray
    gamma: np.ndarray
    shift: np.ndarray  # (N1, N2, 2) each pair's peak translation (29)
    passing: np.ndarray


def skeleton(prob: np.ndarray, params: MergeParams) -> tuple[np.ndarray, np.ndarray]:
    """PGVD (13)-(24), or the plain GVD with every cell certain when not ``probabilistic``."""
    s, sp = pgvd(prob, params.reading.free)
    return (s, sp) if params.off.probabilistic else (s, s.astype(np.float64))


def keep_edges(graph: EdgeGraph, n: int) -> EdgeGraph:
    """``graph`` with only its ``n`` longest, most confident edges (``length * confidence``)."""
    edges = sorted(graph.edges, key=lambda e: -e.length * e.confidence)[:n]
    return EdgeGraph(graph.vertices, graph.labels, edges)


def search_heading(
    turned: Rotated,
    graph_a: EdgeGraph,
    correlator: EdgeCorrelator,
    params: MergeParams,
    min_len: int,
    radius: int,
    clock: StageClock,
) -> list[Hypothesis]:
    """All verified translations for one candidate heading (coarse scale)."""
    matching = _match(turned, graph_a, correlator, params, min_len, clock)
    proposals = _proposals(matching, turned, params, radius)
    clock.lap("gamma")
    if not proposals:
        return []
    out = _verified(proposals, turned, matching, graph_a, correlator, params, radius)
    clock.lap("verify")
    return out


def _match(
    turned: Rotated,
    graph_a: EdgeGraph,
    correlator: EdgeCorrelator,
    params: MergeParams,
    min_len: int,
    clock: StageClock,
) -> _Matching:
    """B's PGVD and edges at ``turned``'s heading, their Gamma and the rho test (32)."""
    # eq. (8) with zero translation: the heading uncertainty as a tangential blur
    rb = (
        rotation_blur(turned.prob, float(np.sqrt(turned.heading.variance)), turned.centre)
        if params.off.heading_blur
        else turned.prob
    )
    s_b, sp_b = skeleton(rb, params)
    clock.lap("pgvd")
    graph_b = keep_edges(build_graph(s_b, sp_b, min_len), params.search.max_edges)
    clock.lap("graph")
    sim = correlator.similarity(graph_b.edges)
    passing = (
        rho_test(sim.gamma, graph_a.edges, graph_b.edges, params.search.rho)
        if params.off.rho_veto
        else sim.gamma > 0
    )
    return _Matching(graph_b, sp_b, sim.gamma, sim.shift, passing)


def _proposals(
    matching: _Matching, turned: Rotated, params: MergeParams, radius: int
) -> list[tuple[int, int]]:
    """The translations to verify: the passing pairs' peaks (29), best Gamma first, and the
    whole-map overlay's own peaks."""
    ia, ib = np.nonzero(matching.passing)
    rank = -matching.gamma[ia, ib] if params.off.gamma_ranking else np.arange(ia.size)
    order = np.argsort(rank, kind="stable")
    shifts = matching.shift[ia[order], ib[order]].astype(np.int64)
    _, first = np.unique(shifts, axis=0, return_index=True)
    kept = shifts[np.sort(first)[: params.search.max_hypotheses]]
    proposals = [(int(x), int(y)) for x, y in kept]
    # The whole-map overlay's own peaks propose too: with a small overlap the
    # edge pairs that cross it are few and their correlation peaks (29) can all
    # fall elsewhere; the rho test (32) at the translation still has to pass.
    for weights in params.overlay_rankings():
        proposals += turned.overlay.peaks(params.search.overlay_peaks, radius, weights)
    return proposals


def _verified(
    proposals: list[tuple[int, int]],
    turned: Rotated,
    matching: _Matching,
    graph_a: EdgeGraph,
    correlator: EdgeCorrelator,
    params: MergeParams,
    radius: int,
) -> list[Hypothesis]:
    """Each proposal slid to the best whole-map overlay nearby, with the edge pairs passing
    (32) there."""
    overlay, graph_b, rankings = turned.overlay, matching.graph_b, params.overlay_rankings()
    pairs = PairSupport(correlator, overlay.shape_a, graph_b.edges)
    thresh = rho_threshold(graph_a.edges, graph_b.edges, params.search.rho)
    # A straight edge pair fixes the translation only across the corridor:
    # slide each proposal to the best whole-map agreement nearby.
    # (by each ranking's evidence: each ranking's finalists come from its own slides)
    refined = list(
        dict.fromkeys(t for w in rankings for t in overlay.best_near_each(proposals, radius, w))
    )
    out: list[Hypothesis] = []
    for (tx, ty), corr in zip(refined, pairs.correlations(refined), strict=True):
        ok = corr > thresh
        support = pair_support(ok) if params.off.rho_veto else params.search.min_pairs
        out.append(
            Hypothesis(
                heading=turned.heading,
                coarse_matrix=translation(tx, ty) @ turned.rotation,
                evidence=overlay.evidence_at((tx, ty), rankings[0]),
                search_evidence=overlay.evidence_at((tx, ty), rankings[-1]),
                ratio=overlay.at((tx, ty)).ratio,
                support=support,
                passing=ok,
                graph_b=graph_b,
                rotation=turned.rotation,
                sp_b=matching.sp_b,
                gamma=matching.gamma,
            )
        )
    return out
