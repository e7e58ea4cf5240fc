"""Check a predicted transform instead of searching for one: refine locally, then overlay.

When a chain of accepted links (or a known initial pose) already predicts the B-pixel ->
A-pixel transform of a pair, the full search of :func:`pgvd.merge.merge` -- candidate
headings (10), the PGVD (13)-(24), Gamma (26)-(28) and the rho test (32) -- is not needed
to *find* it; only to *confirm* it.  :func:`verify` does the confirmation, at a fraction of
the cost:

1. ``refine``: trimmed ICP of B's walls onto A's, started at the prediction
   (:func:`pgvd.alignment.refine`), then refined on all its walls as the merge's winner is
   (:func:`pgvd.scoring.decide_finalists`);
2. ``basin``: the refinement must not have moved the prediction by more than
   :data:`BASIN_M` at B's wall centroid or :data:`BASIN_DEG` in heading.  A prediction
   that needed a larger correction was not a prediction of this transform, and ICP far
   from its start may have slid along a corridor to a look-alike place;
3. ``verify``: the merge's own tests: the pose, refined on all its walls, must stand out
   from itself shifted by a few metres by the merge's ``min_margin`` (:mod:`pgvd.decision`,
   :func:`pgvd.scoring.weigh`, the same drift-tolerant evidence), and the overlay must pass
   the merge's ``min_agreement`` and ``min_overlap``.  Checked at the truth turned by
   N(0, 3 deg) and shifted by N(0, 0.5 m) along each axis, on every pair of the merge
   bench (``python -m bench.verify``, ``bench/results/verify.md``), this confirms 59 of
   86 standard, 18 of 48 low-overlap and 14 of 48 drifted pairs; 4 of the 656 checks
   confirm a wrong pose (three mirror images, checked where a map and its mirror image
   look most alike, and a drifted pair).  Fixed floors on the overlay were tried instead
   (``docs/studies-merge-history.md``);
4. ``covariance``: the merge's own, calibrated on real pairs and
   widened where the evidence is thin (:func:`pgvd.inflation.inflated_covariance`).

Maps finer than 3.4 cm are checked pooled to about 5 cm cells, as the merge decides
(:mod:`pgvd.pooling`); the result is in the full maps' pixels.

A rejected result carries the refined matrix for diagnosis only; a prediction is never
accepted as it stands, only the refined transform once it passed every check.
:func:`predicted_overlap` says what the maps show where a rejected prediction put them
(how many metres of walls overlap, how far the refinement moved it), on the same pooled
maps: the agent reads it to tell a chain that puts the maps apart from one that is merely off.
A caller that asks both reads the maps once (:func:`pooled_maps`) and hands them to each.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pgvd.agreement import map_agreement
from pgvd.alignment import refine
from pgvd.grid import Grid, finite_3x3, matrix_to_pose
from pgvd.inflation import inflated_covariance
from pgvd.inputs import check_extent, check_resolutions, registration_probability
from pgvd.parallel import both
from pgvd.params import MergeParams
from pgvd.pooling import covariance_from_pooled, decision_pool, from_pooled, to_pooled
from pgvd.result import MergeResult, merge_result, rejected
from pgvd.scoring import decide_finalists, decision_map, overlay_floors
from pgvd.stage_clock import StageClock
from pgvd.walls import WallMap

#: Largest move (m) of B's wall centroid by the refinement for the prediction to count.
BASIN_M = 1.0
#: Largest change of heading (degrees) by the refinement for the prediction to count.
BASIN_DEG = 5.0


def _check(predicted: np.ndarray) -> np.ndarray:
    """The prediction as a float 3x3 rigid matrix; ``ValueError`` on anything else."""
    m = finite_3x3(predicted, "the prediction")
    if not (
        np.allclose(m[2], (0.0, 0.0, 1.0))
        and np.allclose(m[:2, :2] @ m[:2, :2].T, np.eye(2), atol=1e-6)
    ):
        raise ValueError("the prediction is not a rigid transform (eqs. (1)-(2))")
    return m


def _check_pair(a: Grid, b: Grid, params: MergeParams) -> None:
    """``ValueError`` for maps of different cell sizes, or one too small to check
    (:func:`pgvd.inputs.check_extent`), before either is read."""
    check_resolutions(a, b)
    for name, g in (("A", a), ("B", b)):
        check_extent(name, g, params)


def basin_move(
    predicted: np.ndarray, refined: np.ndarray, walls_b: np.ndarray
) -> tuple[float, float]:
    """How far the refinement moved the prediction: (pixels at B's wall centroid, degrees).

    Measured at the centroid so that a turn about a far-away pixel origin does not count
    as a translation.
    """
    centre = np.append(walls_b.mean(axis=0), 1.0)
    shift = float(np.hypot(*((refined - predicted) @ centre)[:2]))
    turn = matrix_to_pose(refined)[0] - matrix_to_pose(predicted)[0]
    return shift, float(np.degrees(abs(np.angle(np.exp(1j * turn)))))


def _left_basin(
    start: np.ndarray, matrix: np.ndarray, walls_b: np.ndarray, res: float
) -> str | None:
    """Why ``matrix`` is not a refinement of the prediction ``start`` (it moved it farther
    than :data:`BASIN_M` or :data:`BASIN_DEG`, :func:`basin_move`), or None; ``res`` m a cell."""
    shift_px, turn_deg = basin_move(start, matrix, walls_b)
    if shift_px * res <= BASIN_M and turn_deg <= BASIN_DEG:
        return None
    return (
        f"refinement left the prediction's basin: moved {shift_px * res:.2f} m "
        f"and {turn_deg:.1f} deg (> {BASIN_M} m or {BASIN_DEG} deg)"
    )


def wall_maps(a: Grid, b: Grid, params: MergeParams, pool: int = 1) -> tuple[WallMap, WallMap]:
    """A's and B's wall maps, each read as registration reads it
    (:func:`pgvd.inputs.registration_probability`) and pooled ``pool x pool``
    (:func:`pgvd.pooling.decision_pool`; 1: full resolution)."""
    return both(lambda g: decision_map(registration_probability(g, params), params, pool), a, b)


@dataclass(frozen=True)
class PooledMaps:
    """The wall maps of a pair as :func:`verify` decides on them (:func:`pooled_maps`).

    Attributes
    ----------
    a, b : WallMap
        A's and B's wall maps, pooled ``pool x pool``.
    pool : int
        Cells of the full maps per side of a pooled cell (:func:`pgvd.pooling.decision_pool`).
    cell : float
        Side of a pooled cell (m).
    """

    a: WallMap
    b: WallMap
    pool: int
    cell: float


def pooled_maps(a: Grid, b: Grid, params: MergeParams) -> PooledMaps:
    """Read a pair once for :func:`verify` and :func:`predicted_overlap`: pooled to about 5 cm
    cells, as the merge decides (:mod:`pgvd.pooling`).

    Reading is most of a check's cost on fine maps (on the bundled intel pair split 3x3,
    1.67 cm cells, 90 of the 230 ms that a rejected prediction took to verify and then to
    measure), so a caller that does both reads the maps once and hands them to each.

    Parameters
    ----------
    a, b : Grid
        The two maps, with equal resolutions.
    params : MergeParams
        The merge's ``occupied`` and ``free`` thresholds, and how registration reads a map.

    Returns
    -------
    PooledMaps

    Raises
    ------
    ValueError
        Maps of different cell sizes, or one under three search cells a side.
    """
    _check_pair(a, b, params)
    pool = decision_pool(a.resolution)
    wall_a, wall_b = wall_maps(a, b, params, pool)
    return PooledMaps(wall_a, wall_b, pool, a.resolution * pool)


def _held_or_read(a: Grid, b: Grid, params: MergeParams, maps: PooledMaps | None) -> PooledMaps:
    """``maps`` as the caller read them, the pair checked beside them, or the pair read here
    (:func:`pooled_maps` checks it before reading)."""
    if maps is None:
        return pooled_maps(a, b, params)
    _check_pair(a, b, params)
    return maps


@dataclass(frozen=True)
class PredictedOverlap:
    """What two maps show where a prediction puts them, and how far a refinement moved it.

    Attributes
    ----------
    overlap_m : float
        Metres of walls of either map on the other's known space, agreeing or not
        (half the overlay's wall cells, both ways, times the cell size).
    shift_m : float
        How far the refinement moved B's wall centroid (NaN when B has no walls).
    turn_deg : float
        How far it turned B, degrees (NaN when B has no walls).
    """

    overlap_m: float
    shift_m: float
    turn_deg: float


def predicted_overlap(
    a: Grid,
    b: Grid,
    predicted: np.ndarray,
    refined: np.ndarray,
    params: MergeParams,
    maps: PooledMaps | None = None,
) -> PredictedOverlap:
    """The overlap of the maps at ``predicted`` and the move to ``refined`` (module docstring).

    Counted on the maps pooled to about 5 cm cells, as :func:`verify` and the merge decide
    (:mod:`pgvd.pooling`): counted in cells at full resolution, a finer copy of the same
    pair showed 1.4-1.8x more metres of overlap.

    Parameters
    ----------
    a, b : Grid
        The two maps, with equal resolutions.
    predicted, refined : numpy.ndarray
        3x3 rigid matrices, B pixel -> A pixel: a prediction and its refinement by
        :func:`verify`.
    params : MergeParams
        The merge's ``occupied`` and ``free`` thresholds.
    maps : PooledMaps, optional
        :func:`pooled_maps` of ``a`` and ``b`` with ``params``, when the caller has them
        (e.g. from :func:`verify`); read here when None.

    Returns
    -------
    PredictedOverlap
    """
    m0 = _check(predicted)
    maps = _held_or_read(a, b, params, maps)
    start = to_pooled(m0, maps.pool)
    seen = map_agreement(maps.a, maps.b, start)
    overlap_m = 0.5 * (seen.agree + seen.disagree) * maps.cell
    if len(maps.b.walls) == 0:
        return PredictedOverlap(overlap_m, float("nan"), float("nan"))
    shift_px, turn_deg = basin_move(start, to_pooled(refined, maps.pool), maps.b.walls)
    return PredictedOverlap(overlap_m, shift_px * maps.cell, turn_deg)


def verify(
    a: Grid,
    b: Grid,
    predicted: np.ndarray,
    params: MergeParams | None = None,
    maps: PooledMaps | None = None,
) -> MergeResult:
    """Confirm or reject a predicted B-pixel -> A-pixel transform (module docstring).

    Parameters
    ----------
    a, b : Grid
        The two maps, with equal resolutions.
    predicted : numpy.ndarray
        3x3 rigid matrix (eqs. (1)-(2)), B pixel -> A pixel, e.g. a chain of links composed.
    params : MergeParams, optional
        The merge's parameters: how it reads the maps (``occupied``, ``free``), its decision
        (``min_margin`` and the evidence of :func:`pgvd.scoring.score_hypothesis`) and its
        floors (``min_agreement``, ``min_overlap``).
    maps : PooledMaps, optional
        :func:`pooled_maps` of ``a`` and ``b`` with ``params``, read here when None (pass
        them to :func:`predicted_overlap` too, to read the maps once).

    Returns
    -------
    MergeResult
        Accepted with the refined matrix, its overlay agreement as ``score`` and its
        covariance (3), or rejected with a ``reason`` (and no covariance).  The timings
        have ``refine``, ``verify``, ``covariance`` and ``total`` (reading the maps
        included, unless they came as ``maps``).

    Raises
    ------
    ValueError
        A prediction that is not a finite rigid 3x3 matrix, different resolutions, or a
        map under three search cells a side (:func:`pgvd.inputs.check_extent`).

    References
    ----------
    .. [1] Saeedi, S., Paull, L., Trentini, M., Seto, M., and Li, H., "Map merging
       using probabilistic generalized Voronoi diagrams", IROS 2012, eqs. (1)-(3), Sec. VI.
    """
    params = params or MergeParams(diagnostics=False)
    m0 = _check(predicted)
    clock = StageClock(None)
    # checked on maps pooled to about 5 cm cells, as the merge decides (pgvd.pooling)
    maps = _held_or_read(a, b, params, maps)
    pool, res, fine_a, fine_b = maps.pool, maps.cell, maps.a, maps.b

    def result(m: np.ndarray, score: float, why: str, margin: float = np.nan) -> MergeResult:
        # m is in the pooled maps' frame: brought back to the full maps' pixels
        return rejected(why, clock, from_pooled(m, pool), score, margin=margin)

    start = to_pooled(m0, pool)
    if len(fine_a.walls) < 10 or len(fine_b.walls) < 10:
        return result(start, 0.0, "a map has fewer than 10 wall cells")
    matrix = refine(fine_a.tree, fine_b.walls, start)
    clock.lap("refine")
    margin = float("nan")
    # a prediction that ICP alone carries out of the basin is rejected before the decision,
    # which costs more; the decision's final refinement must keep the pose inside it too
    why = _left_basin(start, matrix, fine_b.walls, res)
    if why is None:
        _, decision, matrix = decide_finalists([matrix], fine_a, fine_b, params, res)
        margin = decision.margin
        why = _left_basin(start, matrix, fine_b.walls, res)
    clock.lap("verify")
    if why is not None:
        return result(matrix, 0.0, why, margin)
    agreement = map_agreement(fine_a, fine_b, matrix)
    clock.lap("verify")
    why = overlay_floors(agreement, res, params)
    if why is None and margin < params.decision.min_margin:
        why = (
            f"the predicted pose does not stand out: margin {margin:.2f} < "
            f"{params.decision.min_margin} (best shifted pose {decision.rival:.0f})"
        )
    if why is not None:
        return result(matrix, agreement.ratio, why, margin)
    cov = covariance_from_pooled(inflated_covariance(fine_a, fine_b, matrix, res), matrix, pool)
    clock.lap("covariance")
    full = from_pooled(matrix, pool)
    return merge_result(True, "accepted", clock, full, agreement.ratio, cov, margin=margin)
