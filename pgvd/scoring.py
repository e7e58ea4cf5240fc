"""The decision's scoring: finalists refined and scored on the maps at about 5 cm cells,
drift-tolerant (:func:`pgvd.agreement.local_agreement`), and the winner weighed against its
rivals (:mod:`pgvd.decision`)."""

from __future__ import annotations

import numpy as np

from pgvd.agreement import local_agreements, map_agreement
from pgvd.decision import Decision, Scored, decide, restate, shifted
from pgvd.hypotheses import Hypothesis
from pgvd.overlay import Agreement
from pgvd.parallel import both
from pgvd.params import MergeParams
from pgvd.pooling import block_scale, pooled
from pgvd.refinement import final_refinement, refine_finalists
from pgvd.walls import WallMap


def score_hypothesis(
    m: np.ndarray, fine_a: WallMap, fine_b: WallMap, params: MergeParams, res: float
) -> Scored:
    """The pose ``m`` (B->A pixels, ``res`` m a cell) with its drift-tolerant overlay counts
    (:func:`score_hypotheses` of that pose alone)."""
    return score_hypotheses([m], fine_a, fine_b, params, res)[0]


def score_hypotheses(
    ms: list[np.ndarray], fine_a: WallMap, fine_b: WallMap, params: MergeParams, res: float
) -> list[Scored]:
    """The poses ``ms`` (B->A pixels, ``res`` m a cell) with their drift-tolerant overlay
    counts.

    Counted on subsamples of ``params.refinement.refine_points`` walls, each
    ``distortion_block`` square re-aligned by up to ``drift_shift`` first (``params.decision``,
    :func:`pgvd.agreement.local_agreements`: all poses in one pass); the rigid overlay when
    that is 0.
    """
    points, decision = params.refinement.refine_points, params.decision
    if decision.drift_shift <= 0:
        return [Scored(m, map_agreement(fine_a, fine_b, m, max_points=points)) for m in ms]
    agreements = local_agreements(
        fine_a,
        fine_b,
        ms,
        block=decision.distortion_block / res,
        max_shift=decision.drift_shift / res,
        max_points=points,
    )
    return [Scored(m, agreement) for m, agreement in zip(ms, agreements, strict=True)]


def weigh(
    scored: list[Scored], fine_a: WallMap, fine_b: WallMap, params: MergeParams, res: float
) -> Decision:
    """The best of ``scored`` against its rivals (:func:`pgvd.decision.decide`).

    The rivals are the other poses of ``scored`` (farther than
    ``rival_distance`` or 2 degrees from the best) and the best pose shifted by
    ``probe_shifts`` times that distance along A's axes (``params.decision``),
    scored by :func:`score_hypotheses`; ``res`` is the cell size (m).
    """
    rival_px = params.decision.rival_distance / res
    centre = fine_b.walls.mean(axis=0)
    weight, noise = params.decision.disagreement_weight, params.decision.margin_noise
    first = decide(scored, weight, centre, px=rival_px, noise=noise)
    steps = tuple(s * rival_px for s in params.decision.probe_shifts)
    probes = score_hypotheses(shifted(first.winner.matrix, steps), fine_a, fine_b, params, res)
    return decide(scored, weight, centre, px=rival_px, probes=probes, noise=noise)


def fine_maps(
    pa: np.ndarray, pb: np.ndarray, params: MergeParams, pool: int = 1
) -> tuple[WallMap, WallMap]:
    """A's and B's maps from their probabilities, as the decision reads them
    (:func:`decision_map`).

    A gets the nearest-wall table (:class:`pgvd.walls.WallMap` ``lookup``): every
    hypothesis is scored against it; B's walls are only counted once per hypothesis.
    """

    def read(job: tuple[np.ndarray, bool]) -> WallMap:
        prob, lookup = job
        return decision_map(prob, params, pool, lookup)

    return both(read, (pa, True), (pb, False))


def decision_map(prob: np.ndarray, params: MergeParams, pool: int, lookup: bool = False) -> WallMap:
    """One map's probabilities as the decision reads them: pooled ``pool x pool``
    (:func:`pgvd.pooling.decision_pool`: about 5 cm cells, where the decision was set),
    walls and free space at ``params``' thresholds; ``lookup`` as in
    :class:`pgvd.walls.WallMap`."""
    occupied, free = params.reading.occupied, params.reading.free
    return WallMap(pooled(prob, pool, occupied), occupied, free, lookup)


def decide_finalists(
    refined: list[np.ndarray], fine_a: WallMap, fine_b: WallMap, params: MergeParams, res: float
) -> tuple[int, Decision, np.ndarray]:
    """The decision among finalists already refined on a subsample, and the winner refined.

    Each pose is scored by :func:`score_hypotheses` (each square of the overlap
    re-aligned by up to ``params.decision.drift_shift`` first: a drifted map has no
    single rigid fit) and the best is weighed against its rivals
    (:func:`weigh`).  The winner is then refined on all its wall cells,
    point-to-point and then point-to-line with a robust loss
    (:func:`pgvd.alignment.refine_point_to_line`), and scored again: the margin
    is that of the pose returned (:func:`pgvd.decision.restate`).

    Parameters
    ----------
    refined : list of numpy.ndarray
        The finalists' 3x3 B->A pixel matrices (at least one).
    fine_a, fine_b : WallMap
        The two maps at full resolution.
    params : MergeParams
        The merge's parameters.
    res : float
        Cell size (m).

    Returns
    -------
    tuple of (int, Decision, numpy.ndarray)
        The index of the winner in ``refined``, the decision of the refined winner
        and its B->A pixel matrix.
    """
    scored = score_hypotheses(refined, fine_a, fine_b, params, res)
    decision = weigh(scored, fine_a, fine_b, params, res)
    index = next(i for i, s in enumerate(scored) if s is decision.winner)
    matrix = final_refinement(decision.winner.matrix, fine_a, fine_b, params)
    final = score_hypothesis(matrix, fine_a, fine_b, params, res)
    weight, noise = params.decision.disagreement_weight, params.decision.margin_noise
    restated = restate(decision, final, weight, noise)
    return index, restated, matrix


def decide_hypotheses(
    finalists: list[Hypothesis],
    fine_a: WallMap,
    fine_b: WallMap,
    to_fine: np.ndarray,
    k: float,
    params: MergeParams,
    res: float,
) -> tuple[Hypothesis, Decision, np.ndarray]:
    """Refine every finalist on the decision's maps and weigh the best against its rivals.

    ``to_fine`` maps A's coarse crop to the pixels of A's decision map, ``k`` is
    the coarse cell over the decision's cell (:func:`fine_maps`).  Finalists are refined on
    a subsample of B's walls, then decided by :func:`decide_finalists`;
    ``res`` is the cell size (m).  Finalists within ``params.decision.rival_distance``
    (and 2 degrees) of the winner are its own, the others its rivals.  Returns
    the winner, the :class:`pgvd.decision.Decision` (of the refined winner)
    and the winner's B->A pixel matrix.
    """
    starts = [to_fine @ h.coarse_matrix @ np.linalg.inv(block_scale(k)) for h in finalists]
    refined = refine_finalists(starts, fine_a, fine_b, params)
    index, decision, matrix = decide_finalists(refined, fine_a, fine_b, params, res)
    return finalists[index], decision, matrix


def overlay_floors(agreement: Agreement, res: float, params: MergeParams) -> str | None:
    """Why the whole-map overlay of a decided pose fails the decision's floors, or None.

    ``agreement`` counts the walls of both maps (:func:`pgvd.agreement.map_agreement`) on
    maps of ``res`` m cells: the share that agrees must reach ``min_agreement``, and the
    agreeing walls, counted once per map, ``min_overlap`` metres (``params.decision``).
    """
    limits = params.decision
    if agreement.ratio < limits.min_agreement:
        return f"overlaid maps disagree: agreement {agreement.ratio:.2f} < {limits.min_agreement}"
    overlap_m = 0.5 * agreement.agree * res
    if overlap_m < limits.min_overlap:
        return f"overlap too small: {overlap_m:.1f} m of agreeing walls < {limits.min_overlap} m"
    return None
