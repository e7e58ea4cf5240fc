"""The map-merging pipeline of the paper's Fig. 1, with verification and refinement.

Stages (``timings_ms`` keys):

``rotation``
    candidate headings from the angle spectra (10), :mod:`pgvd.rotation`;
    optionally (``MergeParams.heading_span``) near each, the heading of best
    whole-map overlay (searched a few degrees around it at 0.4 m) is one too.
``coarsen``
    both maps pooled to the search scale (``MergeParams.coarse_resolution``,
    0.2 m by default): a coarse cell is a wall if any of its cells is one
    (walls are one cell thick and must survive), else it holds the mean
    probability.  All PGVD/Gamma/rho stages run at this scale, as the paper
    defines them, only on 16x fewer cells; maps are cropped to their known
    cells.
``pgvd``
    for A once and for B once per candidate heading: B is rotated (12) and
    the heading variance is propagated as the tangential blur of (8)
    (:func:`pgvd.uncertainty.rotation_blur`), then the PGVD (13)-(24).
``graph``
    vertices and edges (Sec. IV-D); the ``max_edges`` longest, most
    confident edges are kept.
``gamma``
    the similarity matrix (26)-(28) by batched FFT and the rho test (32)
    (with a one-coarse-cell tolerance, see :func:`pgvd.matching.similarity`);
    every passing pair proposes its correlation-peak translation (29), best
    Gamma first.
``verify``
    the paper's future work.  A straight edge pair fixes a translation only
    across the corridor, so each proposal first slides (within
    ``search_radius``) to the best whole-map overlay nearby; it then counts
    only if at least ``min_pairs`` edge pairs pass (32) *at that
    translation*.  Hypotheses of all headings are ranked by the coarse overlay
    evidence ``agree - disagreement_weight * disagree`` (walls on walls vs
    walls on clear free space, both ways); with ``search_finalists``, those that
    beat them all by a second evidence, which also counts the cells free in both
    maps, join them.  The finalists are refined and
    scored again at full resolution, on maps finer than 3.4 cm pooled to about
    5 cm cells first (:mod:`pgvd.pooling`: the decision's distances in cells were
    set on 5 cm maps), each 5 m square of the overlap re-aligned by
    up to ``drift_shift`` first, so that a drifted map's walls running beside
    the other's are not counted as conflict; and the winner, once refined (see
    ``refine``) and scored again, is accepted only if it stands out from its rivals on
    the same pair (:mod:`pgvd.decision`): ``margin >= min_margin``, the margin
    lowered by ``margin_noise / sqrt(n)`` for an overlap of ``n`` walls.  The residual
    distortion of the overlap (:func:`pgvd.matching.residual_distortion`) is reported
    beside the pose.  A rejection of a raw map image, many of whose free cells are lone
    walls, is decided again with them read as unknown (``speckle_retry``).
``refine``
    trimmed ICP of the wall cells at the decision's resolution, then a robust (Cauchy)
    point-to-line alignment that does not stop short along corridors.
``covariance``
    covariance of ``(x, y, psi)`` at the optimum: the Gauss-Newton (point-to-line)
    curvature, inflated by the misfit and its heading widened, calibrated on real
    pairs, widened where the evidence is thin (:func:`pgvd.inflation.inflated_covariance`).
``speckle_share``, ``as_drawn``
    after a rejection, the lone wall cells of both maps counted (``speckle_retry``);
    when that retries the merge, the stages are the retry's and ``as_drawn`` is the
    first try's total.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np

from pgvd.decision import Decision, Scored, decide, describe_rival, restate, shifted
from pgvd.graph import EdgeGraph, build_graph
from pgvd.grid import Grid, check_cell_size, matrix_to_pose, rigid_matrix
from pgvd.gvd import pgvd
from pgvd.inflation import inflated_covariance
from pgvd.matching import (
    EdgeCorrelator,
    MapView,
    Overlay,
    OverlayScores,
    OverlayWeights,
    PairSupport,
    WallMap,
    local_agreement,
    map_agreement,
    pair_support,
    refine,
    refine_point_to_line,
    residual_distortion,
    rho_test,
    rho_threshold,
)
from pgvd.parallel import both
from pgvd.pooling import (
    block_scale,
    coarsen,
    covariance_from_pooled,
    decision_pool,
    from_pooled,
    pooled,
)
from pgvd.rotation import OCCUPIED, HeadingCandidate, estimate_headings
from pgvd.sampling import subsample
from pgvd.speckle import DESPECKLE_RADIUS, radius_cells, speckle_share, without_speckle
from pgvd.transform import warp
from pgvd.uncertainty import rotation_blur
from pgvd.unexplored import restore_unexplored, unknown_share

#: ICP iterations per correspondence radius when the finalists are refined (each stops
#: early once it no longer moves).  With the decision as it was before its noise term,
#: 8 instead of 3 succeeded on 20/48 drifted pairs instead of 16 at 0 wrong and 0 false
#: accepts (``python -m bench.merge --methods pgvd --no-scaling``): a finalist started a
#: few cells off stops short of its optimum with 3.  With the decision of
#: :mod:`pgvd.decision` of 6db4ec5 (threshold 0.62, set on finalists refined with 3),
#: 8 succeeds on 74/12/20 (standard/low/drifted) against 75/12/19 with 3, and accepts
#: uos_avz's low-overlap ov00 7.7 cells off (margin 0.66) and fr079's map against its
#: mirror image (margin 0.73): better-refined rivals move every margin, so the two are
#: set together, and 3 is what the threshold was set on.
FINALIST_ICP_ITERATIONS = 3


@dataclass(frozen=True)
class MergeParams:
    """Parameters of :func:`merge` (lengths in metres are converted to cells).

    Attributes
    ----------
    coarse_resolution : cell size (m) of the PGVD/Gamma search stages.
    max_candidates : candidate headings (:func:`pgvd.rotation.estimate_headings`).
    heading_span, heading_step : near each Radon candidate, the heading of best whole-map
        overlay evidence (degrees: within ``heading_span``, in steps of ``heading_step``, at
        twice the coarse cell) is a candidate too (:func:`_with_refined`).  The spectrum's
        peak is broad and a partial or drifted map shifts it: 28 of 182 development pairs
        had no searched heading within 2 degrees of the truth, most 3-6 degrees off.  Off
        (``heading_span=0``) by default: in the run of ``bench/results/merge.md``
        (``python -m bench.merge``, every method), ``heading_span=6`` succeeds on 76/11/15
        (standard/low/drifted) against 74/12/16 by default, accepts one wrong pose at
        margin 0.82 (stata's drifted ov03, 13 cells off, tolerance 7: a crisp fit of part
        of a drifted overlap) and takes 0.52 s at 1000^2 instead of 0.41: the decision,
        not the search, loses most of the pairs it helps (``python -m bench.recall
        --method pgvd-heading`` shows what it finds).
    search_headings : candidates that go through the PGVD stages: those whose whole-map
        overlay (best ``agree - disagreement_weight * disagree`` over all translations)
        is largest.
    overlay_peaks : the best local maxima of the whole-map overlay, per searched heading,
        proposed as translations beside the edge pairs' correlation peaks (29).
    rho : matching percentage of the existence test (32).
    edge_tolerance : cells of tolerance when correlating edges (A's edges are grey-dilated).
    min_edge_length : edges shorter than this (m) are dropped (Sec. IV-E).
    max_edges : longest edges kept per map, bounding Gamma's size.
    max_hypotheses : translations proposed per heading (best Gamma first).
    search_radius : each proposal slides (m) to the best whole-map agreement within this.
    min_pairs : edge pairs that must pass (32) at an accepted translation.  One: a small
        overlap is crossed by few edges, and with two required the true translation of
        most 15-35 % overlaps never reached the decision (intel low-overlap pairs: 2 of
        10 found with two, 4 of 10 with one; no false accept more on the development
        negatives); the margin of :mod:`pgvd.decision` now rejects look-alikes.
    min_margin : the margin of the returned pose (the winner after its last refinement)
        over its best rival, per overlapping wall cell, less ``margin_noise`` over the
        square root of its overlay count (:mod:`pgvd.decision`), at least this.  Set on
        the development pairs of the merge bench (``python -m bench.merge``,
        ``bench/results/acceptance.md``), their finalists replayed by ``bench.redecide``:
        the largest margin of a wrong or negative winner is 0.53 (uos_avz against its
        mirror image, a building alike under a mirror, and a drifted ritsumeikan pair 2.3
        degrees off), and 0.54 in runs with every candidate heading turned by 0.1 degree
        or read another way; 0.57 keeps a gap of 0.03 above them.  Leaving one building
        out, the threshold just above the others' worst (0.54-0.55) accepts no wrong or
        negative winner of the building left out, in any of those runs.
    margin_noise : the margin is lowered by this over the square root of the winner's
        overlay count ``agree + disagree`` (about 100 to 3000 on the subsample): the
        evidence of a small overlap is a few hundred walls, and its margin, a mean over
        them, swings more from one scoring to the next (uos_avz's low-overlap pair ov00,
        a wrong pose on 130 walls: margin 0.51 with ``drift_shift`` 0.75, 0.86 with
        0.9).  3: with it the largest margin of a wrong or negative winner stays within
        0.58-0.61 for ``drift_shift`` 0.5-0.9 (with 0: 0.65-0.86; with 2: 0.60-0.69).
    min_agreement : optional floor on agreement / (agreement + disagreement) of the final
        overlay (0: the margin decides alone; ``pgvd agent --min-agreement`` sets it).
    min_overlap : minimum length (m) of agreeing walls; small, so that a short but crisp
        overlap can pass: the margin, not the size, decides.
    rival_distance : finalists whose pose moves B's wall centroid by more than this (m), or
        turns it by more than 2 degrees, are rivals of the winner; closer ones are the
        winner itself, reached again from another start.
    probe_shifts : the winner shifted by these multiples of ``rival_distance`` along A's
        axes is scored as a rival too (:func:`pgvd.decision.shifted`).
    distortion_block : side (m) of the squares of :func:`pgvd.matching.residual_distortion`
        and of :func:`pgvd.matching.local_agreement`.
    drift_shift : largest shift (m) of one such square when hypotheses are scored
        (:func:`pgvd.matching.local_agreement`): walls that a drifted map puts this far
        beside the other map's are not counted as walls on free space.  0.75 m: the
        development drifted pairs keep 0.1-0.85 m (RMS) of residual distortion at their
        true pose (bench records' ``info.drift_rms_m``); with 0.5 m, 18 of 48 drifted
        pairs were accepted right, with 0.75 m 19, the other sets alike (replayed,
        ``python3 -m bench.redecide --param drift_shift=0.75``).  0 scores the rigid
        overlay (ablation: without drift tolerance).  In the run of
        ``bench/results/merge.md`` that accepts 76/12/12 standard/low/drifted pairs against
        74/12/16, and a uos_avz look-alike at margin 0.60 (before walls were their faces it
        also accepted the two disjoint halves of fr079_albertB's map312).
    disagreement_weight : refined finalists are scored by ``agree - weight * disagree``
        (:mod:`pgvd.decision`): a wall on clear free space is strong evidence against, a
        wall on a wall weak evidence for (walls are everywhere in a building), so a large
        overlap with some conflicts must not outrank a smaller, consistent one.
    search_conflict_weight, search_free_weight : with ``search_finalists``, the weights of
        the search evidence ``agree + free_weight * free_agree - conflict_weight *
        disagree`` (:class:`pgvd.matching.OverlayWeights`; ``free_agree`` counts cells
        free in both maps).  With walls alone (``agree - 4 disagree``) a look-alike
        translation with more walls outranks a small true overlap despite its conflicts:
        at the exact true heading, the true translation of the 48 development low-overlap
        pairs was the best overlay peak in 19 and among the best 8 in 36.  Free space
        seen by both is evidence too, and conflicts weigh more once it counts.  Best peak
        / best 8 peaks (low 48, drifted 48, standard 80 pairs): ``4, 0`` 19/36, 41/47,
        75/79; ``12, 1`` 26/44, 42/48, 76/80; ``24, 0.5`` 33/47, 37/40, 80/80.  Drifted
        maps conflict where they drift, so these weights rank only the extra finalists;
        the ``finalists`` stay ranked by walls alone.
    search_finalists : finalists more, the best by the search evidence among the
        hypotheses that beat every walls-ranked finalist by it (:func:`_finalists`),
        proposed from the overlay peaks and slides by that evidence too.  Off (0) by
        default: in the run of ``bench/results/merge.md`` (``python -m bench.merge``,
        every method; ``python -m bench.recall --method pgvd-search`` shows what it
        finds), 4 succeed on 74/14/16 (standard/low/drifted) against 74/12/16, with no
        wrong or false accept, at 0.54 s at 1000^2 instead of 0.41: the extra finalists
        are rivals too, and lower true winners' margins.  With an earlier decision they
        also accepted fr079-log's low-overlap ov05 3.6 cells off and a disjoint pair of
        the intel log.
    finalists : best coarse hypotheses (by walls only, ``agree - disagreement_weight *
        disagree``) refined and compared at full resolution.
    refine_points : wall cells per map used when refining and scoring the finalists.
    fine_points : wall cells per map, at most, of the winner's full-resolution stages (its
        last point-to-point refinement, the overlay score, the residual distortion): an
        even subsample beyond it, each kept cell counting for those it stands for.  The
        development maps (0.05 m) have at most about 15 500, so there every cell counts; on
        finer maps these stages' time stops growing with the cell count (on the intel
        scaling pair at 2x and 4x the cells, the pose moved by at most 0.08 cells of the
        base map).
    occupied, free : probability thresholds of walls and free space.
    min_unknown : a map with a smaller share of unknown cells is read with its free space
        outside its walls' convex hull unknown: a map image whose unexplored area was
        painted free (:func:`registration_probability`).
    speckle_radius, speckle_cells : with ``speckle_radius > 0`` (m), a wall cell with at
        most ``speckle_cells`` wall cells (itself included) in the square of that
        half-side (at least 2 cells) is speckle, read as unknown by registration
        (:mod:`pgvd.speckle`), for raw map images (``pgvd merge --despeckle`` sets
        0.15).  Off by default: a laser draws far walls as sparse dots and small objects
        as lone cells, and on the development bench reading them as unknown loses pairs
        and accepts a wrong pose (``bench/results/merge-despeckle.md``); how many of a
        map's walls are lone does not tell a raw image from a laser's map.
    speckle_retry : a merge rejected with ``speckle_radius`` 0 is tried once more with
        lone wall cells read as unknown (:data:`pgvd.speckle.DESPECKLE_RADIUS`) when
        either map has at least this share of its free cells as lone wall cells
        (:func:`pgvd.speckle.speckle_share`): a raw map image.  The development map images
        with 0.5 % of their free cells turned into walls have 0.44-0.81 %, with 2 %
        1.25-2.2 %; the laser's and the simulated laser's maps 0.07-0.30 % (median per
        source), at most 0.82 %, so the retry also runs on a few of their rejections (12
        of 190 on the wide bench), where it accepted nothing.  On the wide bench's pairs
        with that speckle (``python3 -m bench.merge --speckle 0.005`` and ``0.02``) the
        retry takes standard pairs from 46 to 66 and from 6 to 32 of 86, with no wrong
        accept and none of the 110 negatives.  A retry only after a rejection: reading a
        laser's real lone cells (far walls, chair legs) as unknown from the start loses
        pairs (``speckle_radius``).  0 turns it off.
    probabilistic : False matches the plain GVD (every GVD cell certain), the paper's
        deterministic comparison Gamma_det of (41) (ablation: without PGVD weighting).
    rho_veto : False drops the existence test (32): every edge pair with a positive
        correlation proposes its translation and no translation needs ``min_pairs``
        supporting pairs (ablation).
    gamma_ranking : False proposes translations in edge order instead of best Gamma (27)
        first (ablation).
    heading_offset : degrees added to every candidate heading of the spectrum (10), to measure
        how much the search and the decision hang on the heading estimate (``python -m
        bench.merge --methods pgvd pgvd-turned+0.1 pgvd-turned-0.1``); 0 in use.  A tenth of
        a degree, well inside the heading sigma, changes the outcome of about 11 of the 292
        development pairs either way (``bench/results/merge-turned.md``).  With the
        acceptance rule up to 0eb44ed it also accepted one wrong and one false pose each
        way, at margins 0.75-1.13: the coarse search's hypotheses move with the heading,
        and a winner whose rivals the maps contradicted took their contradiction as margin.
    heading_blur : False builds B's PGVD without the tangential blur of the heading
        variance, eq. (8) (ablation).
    diagnostics : fill :attr:`MergeResult.diagnostics`.
    """

    coarse_resolution: float = 0.2
    max_candidates: int = 6
    rho: float = 0.7
    edge_tolerance: int = 1
    min_edge_length: float = 1.6
    max_edges: int = 80
    max_hypotheses: int = 40
    search_radius: float = 2.4
    min_pairs: int = 1
    min_margin: float = 0.57
    margin_noise: float = 3.0
    min_agreement: float = 0.0
    min_overlap: float = 3.0
    rival_distance: float = 1.0
    probe_shifts: tuple[float, ...] = (1.5, 3.0)
    distortion_block: float = 5.0
    drift_shift: float = 0.75
    disagreement_weight: float = 4.0
    search_conflict_weight: float = 24.0
    search_free_weight: float = 0.5
    heading_span: float = 0.0
    heading_step: float = 3.0
    heading_offset: float = 0.0
    search_headings: int = 6
    overlay_peaks: int = 5
    finalists: int = 8
    search_finalists: int = 0
    refine_points: int = 1500
    fine_points: int = 20000
    occupied: float = OCCUPIED
    free: float = 0.3
    min_unknown: float = 0.01
    speckle_radius: float = 0.0
    speckle_cells: int = 2
    speckle_retry: float = 0.004
    probabilistic: bool = True
    rho_veto: bool = True
    gamma_ranking: bool = True
    heading_blur: bool = True
    diagnostics: bool = True

    @property
    def search_weights(self) -> OverlayWeights:
        """The coarse overlay's evidence (``search_conflict_weight``, ``search_free_weight``)."""
        return OverlayWeights(self.search_conflict_weight, self.search_free_weight)


@dataclass
class MergeDiagnostics:
    """What a person wants to look at after a merge (all at full resolution).

    Attributes
    ----------
    pgvd_a : A's PGVD (24) in A's pixel frame.
    pgvd_b : B's PGVD in B's own pixel frame (computed on rotated B, mapped back).
    edges_a : bool mask (A frame) of A's edges in the edge pairs supporting the result.
    edges_b : bool mask (B frame) of B's edges in those pairs.
    gamma : Gamma (27) of the chosen heading.
    support : number of distinct edge pairs passing (32) at the chosen translation.
    """

    pgvd_a: np.ndarray
    pgvd_b: np.ndarray
    edges_a: np.ndarray
    edges_b: np.ndarray
    gamma: np.ndarray
    support: int = 0


@dataclass
class MergeResult:
    """Outcome of :func:`merge`; ``matrix`` maps B pixels to A pixels.

    Attributes
    ----------
    margin : float
        The acceptance statistic of :mod:`pgvd.decision`: the winner's overlay
        evidence beyond its best rival's, per overlapping wall cell; NaN when no
        hypothesis reached the full-resolution stage.
    distortion_px : float
        Largest local misfit of the overlap after the rigid fit, pixels
        (:func:`pgvd.matching.residual_distortion`): a drifted map has no single
        rigid fit.  NaN when no hypothesis reached the full-resolution stage.
    headings_deg : tuple of float
        The candidate headings (degrees) that went through the PGVD/Gamma stages.
    """

    accepted: bool
    matrix: np.ndarray
    rotation_deg: float
    translation_px: tuple[float, float]
    covariance: np.ndarray
    score: float
    timings_ms: dict[str, float]
    reason: str
    diagnostics: MergeDiagnostics | None = field(default=None, repr=False)
    margin: float = float("nan")
    distortion_px: float = float("nan")
    headings_deg: tuple[float, ...] = ()

    def with_time(self, step: str, ms: float) -> MergeResult:
        """This result with ``ms`` milliseconds of work done beside its stages (a check
        before the search, a retry's first try) as ``timings_ms[step]``, in the total."""
        total = self.timings_ms["total"] + ms
        return replace(self, timings_ms={**self.timings_ms, step: ms, "total": total})

    def to_json(self) -> dict:
        """The object ``pgvd merge --json`` prints, plus ``reason``.

        A rejected result has no covariance: its entries are ``None`` (JSON null).
        """
        return {
            "accepted": bool(self.accepted),
            "matrix": [[float(v) for v in row] for row in self.matrix],
            "rotation_deg": float(self.rotation_deg),
            "translation_px": [float(self.translation_px[0]), float(self.translation_px[1])],
            "covariance": [
                [float(v) if np.isfinite(v) else None for v in row] for row in self.covariance
            ],
            "score": float(self.score),
            "timings_ms": {k: round(float(v), 3) for k, v in self.timings_ms.items()},
            "reason": self.reason,
            "margin": float(self.margin) if np.isfinite(self.margin) else None,
            "distortion_px": float(self.distortion_px) if np.isfinite(self.distortion_px) else None,
        }


@dataclass
class _Hypothesis:
    heading: HeadingCandidate
    coarse_matrix: np.ndarray  # coarse B -> A's coarse crop
    evidence: float  # agree - disagreement_weight * disagree (walls only)
    search_evidence: float  # MergeParams.search_weights
    ratio: float
    support: int
    passing: np.ndarray
    graph_b: EdgeGraph
    rotation: np.ndarray  # coarse B -> crop of the rotated coarse B (where sp_b lives)
    sp_b: np.ndarray
    gamma: np.ndarray


def _translation(tx: float, ty: float) -> np.ndarray:
    return np.array([[1.0, 0.0, tx], [0.0, 1.0, ty], [0.0, 0.0, 1.0]])


def _rotation_about_centre(
    psi: float, shape: tuple[int, int]
) -> tuple[np.ndarray, tuple[int, int]]:
    """Rotation by ``psi`` (eq. (2)) of a map of ``shape`` into a canvas that holds it whole."""
    h, w = shape
    side = int(np.ceil(np.hypot(h, w))) + 2
    rot = rigid_matrix(psi, 0.0, 0.0)
    centre = np.array([(w - 1) / 2.0, (h - 1) / 2.0])
    rot[:2, 2] = (side - 1) / 2.0 - rot[:2, :2] @ centre
    return rot, (side, side)


def registration_probability(
    grid: Grid, params: MergeParams, say: Callable[[str], None] | None = None
) -> np.ndarray:
    """The probabilities (34) of ``grid`` that registration reads.

    With ``params.speckle_radius``, lone wall cells (speckle, :mod:`pgvd.speckle`) are
    unknown.  A map with less than ``params.min_unknown`` of its cells unknown (an image
    whose unexplored area was painted free) gets its unexplored space back
    (:func:`pgvd.unexplored.restore_unexplored`).  ``say`` is told of both.
    """
    prob = grid.probability()
    # measured as drawn: speckle read as unknown must not hide a map painted free
    painted = unknown_share(prob, params.free, params.occupied) < params.min_unknown
    if params.speckle_radius > 0:
        radius = radius_cells(params.speckle_radius, grid.resolution)
        prob, lone = without_speckle(prob, params.occupied, radius, params.speckle_cells)
        if lone and say is not None:
            say(f"{lone} lone wall cells (speckle) read as unknown")
    if not painted:
        return prob
    if say is not None:
        say("no unknown cells: free space outside the convex hull of its walls read as unknown")
    return restore_unexplored(prob, params.free, params.occupied)


def _turned(headings: list[HeadingCandidate], degrees: float) -> list[HeadingCandidate]:
    """``headings`` each turned by ``degrees`` (``MergeParams.heading_offset``)."""
    if not degrees:
        return headings
    turn = np.radians(degrees)
    return [replace(h, psi=float(np.angle(np.exp(1j * (h.psi + turn))))) for h in headings]


def _described(h: HeadingCandidate) -> str:
    """``"147.0 deg (sigma 1.11)"``: a candidate heading and its sigma (10), in degrees."""
    return f"{np.degrees(h.psi):.1f} deg (sigma {np.degrees(np.sqrt(h.variance)):.2f})"


def _pgvd(prob: np.ndarray, params: MergeParams) -> tuple[np.ndarray, np.ndarray]:
    """PGVD (13)-(24), or the plain GVD with every cell certain when not ``probabilistic``."""
    s, sp = pgvd(prob, params.free)
    return (s, sp) if params.probabilistic else (s, s.astype(np.float64))


def _known_box(p: np.ndarray, margin: int = 2) -> tuple[slice, slice]:
    """Row and column slices of the cells that are not unknown, grown by ``margin``."""
    known = np.abs(p - 0.5) > 0.05
    rows, cols = np.flatnonzero(known.any(axis=1)), np.flatnonzero(known.any(axis=0))
    if rows.size == 0:
        return slice(0, p.shape[0]), slice(0, p.shape[1])
    return (
        slice(max(0, rows[0] - margin), min(p.shape[0], rows[-1] + margin + 1)),
        slice(max(0, cols[0] - margin), min(p.shape[1], cols[-1] + margin + 1)),
    )


def _keep_edges(graph: EdgeGraph, n: int) -> EdgeGraph:
    edges = sorted(graph.edges, key=lambda e: -e.length * e.confidence)[:n]
    return EdgeGraph(graph.vertices, graph.labels, edges)


class _Clock:
    def __init__(self, progress: Callable[[str], None] | None) -> None:
        self.timings: dict[str, float] = {}
        self.progress = progress
        self.t0 = self.last = time.perf_counter()

    def lap(self, stage: str) -> None:
        """Add the time since the last lap to ``stage``; progress shows both (a stage such as
        gamma runs once per searched heading, so its running total alone reads as steps)."""
        now = time.perf_counter()
        step = 1e3 * (now - self.last)
        self.timings[stage] = self.timings.get(stage, 0.0) + step
        self.last = now
        if self.progress is not None:
            self.progress(f"{stage}: {step:.1f} ms ({self.timings[stage]:.1f} ms so far)")

    def total(self) -> dict[str, float]:
        self.timings["total"] = 1e3 * (time.perf_counter() - self.t0)
        return self.timings


def check_extent(name: str, grid: Grid, params: MergeParams) -> None:
    """Refuse a map under three search cells (``params.coarse_resolution``) a side, or one
    whose cell size is no occupancy grid's (:func:`pgvd.grid.check_cell_size`).

    The search pools each map to those cells and the decision to about 5 cm
    (:mod:`pgvd.pooling`): a map a few search cells across has no GVD edge to match, and a
    cell size far outside a grid's (a wrong ``resolution``, or a hostile one) would make
    that pooling ask for a canvas of astronomic size instead of failing.

    Parameters
    ----------
    name : str
        How the message names the map ("A", "B").
    grid : Grid
        The map.
    params : MergeParams
        Its ``coarse_resolution``.

    Raises
    ------
    ValueError
        Naming the map, its extent and its cell size.
    """
    try:
        check_cell_size(grid.resolution)
    except ValueError as exc:
        raise ValueError(f"map {name}: {exc}") from None
    least = 3 * params.coarse_resolution
    h, w = (n * grid.resolution for n in grid.shape)
    if min(h, w) < least:
        raise ValueError(
            f"map {name} spans {w:.3g} x {h:.3g} m, under {least:.3g} m a side: too small "
            f"to merge at {grid.resolution:g} m/cell (is the cell size right?)"
        )


def check_resolutions(a: Grid, b: Grid) -> None:
    """``ValueError`` unless the two maps have one cell size (to a part in a million)."""
    if not np.isclose(a.resolution, b.resolution, rtol=1e-6, atol=0.0):
        raise ValueError(
            f"maps have different resolutions ({a.resolution} vs {b.resolution} m/cell); "
            "resample B first (pgvd.transform.resample)"
        )


def _check_inputs(a: Grid, b: Grid, pa: np.ndarray, pb: np.ndarray, params: MergeParams) -> None:
    check_resolutions(a, b)
    for name, g, p in (("A", a, pa), ("B", b, pb)):
        if g.logodds.size == 0:
            raise ValueError(f"map {name} is empty")
        check_extent(name, g, params)
        if not np.isfinite(g.logodds).all():
            raise ValueError(f"map {name} contains NaN or infinite values")
        if not (p > params.occupied).any():
            raise ValueError(f"map {name} has no occupied cells")


@dataclass
class _Rotated:
    """B turned by one candidate heading, at the coarse scale, cropped to its known cells."""

    heading: HeadingCandidate
    prob: np.ndarray  # rotated coarse B (not yet blurred)
    rotation: np.ndarray  # coarse B -> this crop
    centre: tuple[float, float]  # rotation centre in the crop, (x, y)
    overlay: Overlay


def _rotate(
    heading: HeadingCandidate,
    cb: np.ndarray,
    scores: OverlayScores,
    params: MergeParams,
    canvases: dict[float, np.ndarray],
) -> _Rotated:
    """Rotate coarse B by a candidate heading (12) and overlay it on A for all translations.

    ``canvases`` holds the whole rotated canvases by heading.  Headings come in
    pairs ``psi``, ``psi + pi`` (:func:`pgvd.rotation.estimate_headings`), and
    the canvas is centred on a cell-centre grid, so a half-turn twin is the
    canvas flipped on both axes: it is taken from there instead of warped again.
    """
    rot, shape = _rotation_about_centre(heading.psi, cb.shape)
    twin = next(
        (
            c
            for psi, c in canvases.items()
            if abs(np.angle(np.exp(1j * (heading.psi - psi - np.pi)))) < 1e-9
        ),
        None,
    )
    rb = warp(cb, rot, shape, order=1, cval=0.5) if twin is None else twin[::-1, ::-1].copy()
    canvases[heading.psi] = rb
    # The heading blur spreads walls by a few cells at most: keep that margin.
    rows, cols = _known_box(rb, margin=2 + int(np.ceil(3 * np.sqrt(heading.variance) * shape[0])))
    rb = rb[rows, cols]
    centre = ((shape[1] - 1) / 2.0 - cols.start, (shape[0] - 1) / 2.0 - rows.start)
    overlay = scores.overlay(MapView(rb, params.occupied, params.free, 1))
    rot = _translation(-cols.start, -rows.start) @ rot
    return _Rotated(heading, rb, rot, centre, overlay)


def _overlay_evidence(
    psi: float, cb: np.ndarray, scores: OverlayScores, params: MergeParams
) -> float:
    """Best whole-map overlay evidence over all translations of coarse B turned by ``psi`` (12)."""
    rot, shape = _rotation_about_centre(psi, cb.shape)
    rb = warp(cb, rot, shape, order=1, cval=0.5)
    rows, cols = _known_box(rb)
    view = MapView(rb[rows, cols], params.occupied, params.free, 1)
    return scores.overlay(view).best_evidence(_weights(params)[0])


def _refined_heading(
    heading: HeadingCandidate, cb: np.ndarray, scores: OverlayScores, params: MergeParams
) -> HeadingCandidate | None:
    """The heading of best whole-map overlay evidence near a Radon candidate (10); None if
    that is the candidate itself.

    Headings ``psi + i * heading_step`` within ``heading_span`` of the candidate are
    overlaid on A (best evidence over all translations), and a parabola through the
    best one and its neighbours places the maximum between steps.  The refined heading
    keeps the candidate's variance.
    """
    step = np.radians(params.heading_step)
    reach = int(params.heading_span / params.heading_step)
    steps = np.arange(-reach, reach + 1)
    ev = np.array([_overlay_evidence(heading.psi + i * step, cb, scores, params) for i in steps])
    j = int(np.argmax(ev))
    if steps[j] == 0:
        return None
    offset = 0.0
    if 0 < j < steps.size - 1:
        y0, y1, y2 = ev[j - 1 : j + 2]
        curve = y0 - 2 * y1 + y2
        offset = 0.5 * (y0 - y2) / curve if curve < 0 else 0.0
    psi = float(np.angle(np.exp(1j * (heading.psi + (steps[j] + offset) * step))))
    return HeadingCandidate(psi, heading.variance, heading.score)


def _with_refined(
    headings: list[HeadingCandidate], ca: np.ndarray, cb: np.ndarray, params: MergeParams
) -> list[HeadingCandidate]:
    """The Radon candidates and, after them, their refined headings (:func:`_refined_heading`).

    Both are kept: near a candidate that is right, the best overlay of a partial map
    is sometimes a look-alike a few degrees away.  The refinement runs at twice the
    coarse cell (4x fewer cells per overlay); a refined heading within half a step of
    another candidate is dropped.
    """
    if params.heading_span <= 0:
        return headings
    view = MapView(coarsen(ca, 2, params.occupied), params.occupied, params.free, 1)
    scores, cb2 = OverlayScores(view), coarsen(cb, 2, params.occupied)
    gap = np.radians(params.heading_step / 2)
    out = list(headings)
    for h in headings:
        r = _refined_heading(h, cb2, scores, params)
        if r is not None and all(abs(np.angle(np.exp(1j * (r.psi - o.psi)))) >= gap for o in out):
            out.append(r)
    return out


def _ranked(turned: list[_Rotated], weights: OverlayWeights) -> list[_Rotated]:
    """Rotated B's, best whole-map overlay evidence first."""
    return sorted(turned, key=lambda r: -r.overlay.best_evidence(weights))


def _search_heading(
    turned: _Rotated,
    graph_a: EdgeGraph,
    correlator: EdgeCorrelator,
    params: MergeParams,
    min_len: int,
    radius: int,
    clock: _Clock,
) -> list[_Hypothesis]:
    """All verified translations for one candidate heading (coarse scale)."""
    heading, rot, overlay = turned.heading, turned.rotation, turned.overlay
    # eq. (8) with zero translation: the heading uncertainty as a tangential blur
    rb = (
        rotation_blur(turned.prob, float(np.sqrt(heading.variance)), turned.centre)
        if params.heading_blur
        else turned.prob
    )
    s_b, sp_b = _pgvd(rb, params)
    clock.lap("pgvd")
    graph_b = _keep_edges(build_graph(s_b, sp_b, min_len), params.max_edges)
    clock.lap("graph")
    sim = correlator.similarity(graph_b.edges)
    passing = (
        rho_test(sim.gamma, graph_a.edges, graph_b.edges, params.rho)
        if params.rho_veto
        else sim.gamma > 0
    )
    ia, ib = np.nonzero(passing)
    rank = -sim.gamma[ia, ib] if params.gamma_ranking else np.arange(ia.size)
    order = np.argsort(rank, kind="stable")
    shifts = sim.shift[ia[order], ib[order]].astype(np.int64)
    _, first = np.unique(shifts, axis=0, return_index=True)
    proposals = [(int(x), int(y)) for x, y in shifts[np.sort(first)[: params.max_hypotheses]]]
    # The whole-map overlay's own peaks propose too: with a small overlap the
    # edge pairs that cross it are few and their correlation peaks (29) can all
    # fall elsewhere; the rho test (32) at the translation still has to pass.
    rankings = _weights(params)
    for weights in rankings:
        proposals += overlay.peaks(params.overlay_peaks, radius, weights)
    clock.lap("gamma")
    out: list[_Hypothesis] = []
    if not proposals:
        return out
    pairs = PairSupport(correlator, overlay.shape_a, graph_b.edges)
    thresh = rho_threshold(graph_a.edges, graph_b.edges, params.rho)
    # A straight edge pair fixes the translation only across the corridor:
    # slide each proposal to the best whole-map agreement nearby.
    # (by each ranking's evidence: each ranking's finalists come from its own slides)
    refined = list(
        dict.fromkeys(t for w in rankings for t in overlay.best_near_each(proposals, radius, w))
    )
    for (tx, ty), corr in zip(refined, pairs.correlations(refined), strict=True):
        ok = corr > thresh
        support = pair_support(ok) if params.rho_veto else params.min_pairs
        agreement = overlay.at((tx, ty))
        out.append(
            _Hypothesis(
                heading=heading,
                coarse_matrix=_translation(tx, ty) @ rot,
                evidence=overlay.evidence_at((tx, ty), rankings[0]),
                search_evidence=overlay.evidence_at((tx, ty), rankings[-1]),
                ratio=agreement.ratio,
                support=support,
                passing=ok,
                graph_b=graph_b,
                rotation=rot,
                sp_b=sp_b,
                gamma=sim.gamma,
            )
        )
    clock.lap("verify")
    return out


def _weights(params: MergeParams) -> tuple[OverlayWeights, ...]:
    """The rankings of the coarse hypotheses: walls only (``agree - disagreement_weight *
    disagree``), then, with ``search_finalists``, ``params.search_weights``."""
    walls = OverlayWeights(params.disagreement_weight)
    return (walls, params.search_weights) if params.search_finalists > 0 else (walls,)


def _near(h: _Hypothesis, chosen: list[_Hypothesis]) -> bool:
    """True when ``h`` is within 2 degrees and 3 coarse cells of one of ``chosen``."""
    return any(
        abs(np.angle(np.exp(1j * (h.heading.psi - o.heading.psi)))) < np.radians(2.0)
        and np.hypot(*(h.coarse_matrix[:2, 2] - o.coarse_matrix[:2, 2])) < 3.0
        for o in chosen
    )


def _best(
    hyps: list[_Hypothesis],
    n: int,
    key: Callable[[_Hypothesis], float],
    chosen: tuple[_Hypothesis, ...] = (),
) -> list[_Hypothesis]:
    """The ``n`` best hypotheses by ``key``, skipping near-duplicates of better ones and
    of ``chosen``."""
    out: list[_Hypothesis] = []
    for h in sorted(hyps, key=lambda h: (-key(h), -h.ratio)):
        if len(out) == n:
            break
        if not _near(h, [*chosen, *out]):
            out.append(h)
    return out


def _rankings(params: MergeParams) -> list[tuple[int, Callable[[_Hypothesis], float]]]:
    """How many finalists each ranking chooses, and its key."""
    out = [(params.finalists, lambda h: h.evidence)]
    if params.search_finalists > 0:
        out.append((params.search_finalists, lambda h: h.search_evidence))
    return out


def _finalists(hyps: list[_Hypothesis], params: MergeParams) -> list[_Hypothesis]:
    """The ``finalists`` best by walls-only evidence, then the ``search_finalists`` best by
    the search evidence (``search_weights``) among those that beat every walls-ranked
    finalist by it.

    The search evidence finds small, consistent overlaps that look-alikes with more
    walls outrank; the walls-only evidence keeps those look-alikes among the
    finalists, where the decision weighs the winner against them (:mod:`pgvd.decision`).
    The bar keeps the extra finalists to pairs where the two rankings disagree: where
    the walls' best is also the search's, more finalists would only be more rivals.
    """
    out: list[_Hypothesis] = []
    for n, key in _rankings(params):
        bar = max((key(h) for h in out), default=-np.inf)
        out += _best([h for h in hyps if key(h) > bar], n, key, tuple(out))
    return out


def _decided(hyps: list[_Hypothesis], params: MergeParams, bounds: tuple[float, ...]) -> bool:
    """True when, by each ranking (:func:`_rankings`), as many supported hypotheses as it
    chooses all score above that ranking's bound in ``bounds``."""
    good = [h for h in hyps if h.support >= params.min_pairs]
    for (n, key), bound in zip(_rankings(params), bounds, strict=True):
        chosen = _best(good, n, key)
        if len(chosen) < n or key(chosen[-1]) <= bound:
            return False
    return True


def score_hypothesis(
    m: np.ndarray, fine_a: WallMap, fine_b: WallMap, params: MergeParams, res: float
) -> Scored:
    """The pose ``m`` (B->A pixels, ``res`` m a cell) with its drift-tolerant overlay counts.

    Counted on subsamples of ``params.refine_points`` walls, each
    ``params.distortion_block`` square re-aligned by up to ``params.drift_shift``
    (:func:`pgvd.matching.local_agreement`); the rigid overlay when that is 0.
    """
    if params.drift_shift <= 0:
        return Scored(m, map_agreement(fine_a, fine_b, m, max_points=params.refine_points))
    agreement = local_agreement(
        fine_a,
        fine_b,
        m,
        block=params.distortion_block / res,
        max_shift=params.drift_shift / res,
        max_points=params.refine_points,
    )
    return Scored(m, agreement)


def weigh(
    scored: list[Scored], fine_a: WallMap, fine_b: WallMap, params: MergeParams, res: float
) -> Decision:
    """The best of ``scored`` against its rivals (:func:`pgvd.decision.decide`).

    The rivals are the other poses of ``scored`` (farther than
    ``params.rival_distance`` or 2 degrees from the best) and the best pose
    shifted by ``params.probe_shifts`` times that distance along A's axes,
    scored by :func:`score_hypothesis`; ``res`` is the cell size (m).
    """
    rival_px = params.rival_distance / res
    centre = fine_b.walls.mean(axis=0)
    noise = params.margin_noise
    first = decide(scored, params.disagreement_weight, centre, px=rival_px, noise=noise)
    steps = tuple(s * rival_px for s in params.probe_shifts)
    probes = [
        score_hypothesis(m, fine_a, fine_b, params, res)
        for m in shifted(first.winner.matrix, steps)
    ]
    return decide(
        scored, params.disagreement_weight, centre, px=rival_px, probes=probes, noise=noise
    )


def fine_maps(
    pa: np.ndarray, pb: np.ndarray, params: MergeParams, pool: int = 1
) -> tuple[WallMap, WallMap]:
    """A's and B's maps from their probabilities, as the decision reads them
    (:func:`decision_map`).

    A gets the nearest-wall table (:class:`pgvd.matching.WallMap` ``lookup``): every
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
    :class:`pgvd.matching.WallMap`."""
    return WallMap(pooled(prob, pool, params.occupied), params.occupied, params.free, lookup)


def final_refinement(
    matrix: np.ndarray, fine_a: WallMap, fine_b: WallMap, params: MergeParams
) -> np.ndarray:
    """The winner refined on all its wall cells: the pose a merge returns.

    Point-to-point ICP at 3 and 2 cells on ``params.fine_points`` of B's walls,
    then the robust point-to-line fit (:func:`pgvd.matching.refine_point_to_line`,
    eqs. (1)-(2)) on all of them.

    Parameters
    ----------
    matrix : numpy.ndarray
        3x3 B pixel -> A pixel, the decision's winner.
    fine_a, fine_b : WallMap
        The two maps at full resolution.
    params : MergeParams
        The merge's parameters.

    Returns
    -------
    numpy.ndarray
        The refined 3x3 B pixel -> A pixel matrix.
    """
    start = refine(fine_a, subsample(fine_b.walls, params.fine_points), matrix, radii=(3.0, 2.0))
    # the pose returned is fitted on A's exact nearest walls (the tree): the table's
    # lookups at the four cells around a point miss the nearest wall for ~0.5 % of points
    return refine_point_to_line(fine_a.tree, fine_b.walls, start)


def decide_finalists(
    refined: list[np.ndarray], fine_a: WallMap, fine_b: WallMap, params: MergeParams, res: float
) -> tuple[int, Decision, np.ndarray]:
    """The decision among finalists already refined on a subsample, and the winner refined.

    Each pose is scored by :func:`score_hypothesis` (each square of the overlap
    re-aligned by up to ``params.drift_shift`` first: a drifted map has no
    single rigid fit) and the best is weighed against its rivals
    (:func:`weigh`).  The winner is then refined on all its wall cells,
    point-to-point and then point-to-line with a robust loss
    (:func:`pgvd.matching.refine_point_to_line`), and scored again: the margin
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
    scored = [score_hypothesis(m, fine_a, fine_b, params, res) for m in refined]
    decision = weigh(scored, fine_a, fine_b, params, res)
    index = next(i for i, s in enumerate(scored) if s is decision.winner)
    matrix = final_refinement(decision.winner.matrix, fine_a, fine_b, params)
    final = score_hypothesis(matrix, fine_a, fine_b, params, res)
    restated = restate(decision, final, params.disagreement_weight, params.margin_noise)
    return index, restated, matrix


def _decide(
    finalists: list[_Hypothesis],
    fine_a: WallMap,
    fine_b: WallMap,
    to_fine: np.ndarray,
    k: float,
    params: MergeParams,
    res: float,
) -> tuple[_Hypothesis, Decision, np.ndarray]:
    """Refine every finalist on the decision's maps and weigh the best against its rivals.

    ``to_fine`` maps A's coarse crop to the pixels of A's decision map, ``k`` is
    the coarse cell over the decision's cell (:func:`fine_maps`).  Finalists are refined on
    a subsample of B's walls, then decided by :func:`decide_finalists`;
    ``res`` is the cell size (m).  Finalists within ``params.rival_distance``
    (and 2 degrees) of the winner are its own, the others its rivals.  Returns
    the winner, the :class:`pgvd.decision.Decision` (of the refined winner)
    and the winner's B->A pixel matrix.
    """
    sub_b = subsample(fine_b.walls, params.refine_points)
    starts = [to_fine @ h.coarse_matrix @ np.linalg.inv(block_scale(k)) for h in finalists]
    refined = [
        refine(fine_a, sub_b, m, radii=(12.0, 6.0, 3.0), iterations=FINALIST_ICP_ITERATIONS)
        for m in starts
    ]
    index, decision, matrix = decide_finalists(refined, fine_a, fine_b, params, res)
    return finalists[index], decision, matrix


def _edge_mask(graph: EdgeGraph, idx: np.ndarray) -> np.ndarray:
    mask = np.zeros(graph.labels.shape, bool)
    for i in np.unique(idx):
        r, c = graph.edges[i].cells()
        mask[r, c] = True
    return mask


def _paint(coarse: np.ndarray, matrix: np.ndarray, k: int, shape: tuple[int, int]) -> np.ndarray:
    """Draw the nonzero coarse cells as ``k x k`` blocks into a full-resolution frame.

    ``matrix`` maps full-resolution pixels of the coarse array's frame to the target frame.
    """
    r, c = np.nonzero(coarse)
    m = matrix @ block_scale(k)
    centres = np.column_stack([c, r]).astype(float) @ m[:2, :2].T + m[:2, 2]
    out = np.zeros(shape, coarse.dtype)
    offsets = np.arange(k) - (k - 1) / 2.0
    for dy in offsets:
        for dx in offsets:
            x = np.rint(centres[:, 0] + dx).astype(np.int64)
            y = np.rint(centres[:, 1] + dy).astype(np.int64)
            ok = (x >= 0) & (x < shape[1]) & (y >= 0) & (y < shape[0])
            out[y[ok], x[ok]] = coarse[r[ok], c[ok]]
    return out


def _diagnostics(
    best: _Hypothesis,
    graph_a: EdgeGraph,
    sp_a: np.ndarray,
    off_a: np.ndarray,
    k: int,
    shapes: tuple[tuple[int, int], tuple[int, int]],
) -> MergeDiagnostics:
    ia, ib = np.nonzero(best.passing)
    to_fine = block_scale(k)
    crop_a = to_fine @ off_a @ np.linalg.inv(to_fine)
    # B's PGVD lives in the rotated coarse frame: draw it back in B's pixels.
    back = np.linalg.inv(to_fine @ best.rotation @ np.linalg.inv(to_fine))
    return MergeDiagnostics(
        pgvd_a=_paint(sp_a, crop_a, k, shapes[0]),
        pgvd_b=_paint(best.sp_b, back, k, shapes[1]),
        edges_a=_paint(_edge_mask(graph_a, ia), crop_a, k, shapes[0]),
        edges_b=_paint(_edge_mask(best.graph_b, ib), back, k, shapes[1]),
        gamma=best.gamma,
        support=best.support,
    )


def _result(
    accepted: bool,
    reason: str,
    clock: _Clock,
    matrix: np.ndarray,
    score: float,
    covariance: np.ndarray,
    diagnostics: MergeDiagnostics | None = None,
    **extra: object,
) -> MergeResult:
    psi, tx, ty = matrix_to_pose(matrix)
    return MergeResult(
        accepted=accepted,
        matrix=matrix,
        rotation_deg=float(np.degrees(psi)),
        translation_px=(tx, ty),
        covariance=covariance,
        score=score,
        timings_ms=clock.total(),
        reason=reason,
        diagnostics=diagnostics,
        **extra,
    )


def _rejected(
    reason: str,
    clock: _Clock,
    matrix: np.ndarray | None = None,
    score: float = 0.0,
    **extra: object,
) -> MergeResult:
    m = np.eye(3) if matrix is None else matrix
    return _result(False, reason, clock, m, score, np.full((3, 3), np.nan), **extra)


def merge(
    a: Grid,
    b: Grid,
    params: MergeParams | None = None,
    progress: Callable[[str], None] | None = None,
) -> MergeResult:
    """Find the B-pixel -> A-pixel transform of two occupancy grids and verify it (Fig. 1).

    The paper's pipeline: candidate headings (10), the rotation blur (8), the
    PGVD (13)-(24), edges (25), Gamma (26)-(28), the existence test (32) and
    the translation (29); then a check of its own (several edge pairs and the
    overlaid maps must agree), refinement and the covariance (3).  The stages
    are described in the module docstring.

    Parameters
    ----------
    a, b : Grid
        The two maps, with equal resolutions.
    params : MergeParams, optional
        Defaults when None.
    progress : callable, optional
        Called with one line (``"stage: 12.3 ms"``) per finished stage.

    Returns
    -------
    MergeResult
        ``matrix`` maps B pixels to A pixels.  ``accepted`` is False, with a
        ``reason``, when no transform passes the rho test (32) and the edge-pair
        agreement, or when the best one does not stand out from its rivals on
        the same pair (:mod:`pgvd.decision`).  A rejection of maps with many lone
        wall cells in their free space (a raw map image) is retried once with
        them read as unknown (``MergeParams.speckle_retry``); the result is then the
        retry's, its ``reason`` says so, and ``timings_ms["as_drawn"]`` is the first pass.

    Raises
    ------
    TypeError
        A map that is not a :class:`pgvd.grid.Grid`.
    ValueError
        Different resolutions, an empty map, NaN, or a map without occupied cells.

    References
    ----------
    .. [1] Saeedi, S., Paull, L., Trentini, M., Seto, M., and Li, H., "Map merging
       using probabilistic generalized Voronoi diagrams", IROS 2012.  Fig. 1,
       eqs. (8), (10)-(32).

    Examples
    --------
    Two robots' partial maps of the Intel Research Lab, each in a frame of its
    own, bundled in the repository's ``examples/`` with their true transform:

    >>> import json
    >>> import numpy as np
    >>> from pgvd import merge, read_map
    >>> a = read_map("examples/intel_a.yaml")
    >>> b = read_map("examples/intel_b.yaml")
    >>> result = merge(a, b)
    >>> result.accepted, round(result.rotation_deg)
    (True, -69)

    How far from the truth B's walls land in A, in cells:

    >>> with open("examples/truth.json") as f:
    ...     truth = np.array(json.load(f)["matrix"])
    >>> rows, cols = np.nonzero(b.probability() > 0.65)
    >>> walls = np.stack([cols, rows, np.ones_like(cols)])
    >>> error = np.hypot(*((result.matrix - truth) @ walls)[:2])
    >>> bool(error.max() < 1.5)
    True
    """
    for name, g in (("A", a), ("B", b)):
        if not isinstance(g, Grid):  # e.g. a probability array, which has no resolution
            raise TypeError(
                f"map {name} must be a pgvd.Grid (pgvd.read_map, or pgvd.Grid.from_probability "
                f"for an array), got {type(g).__name__}"
            )
    params = params or MergeParams()
    result = _merge_pass(a, b, params, progress)
    if result.accepted or params.speckle_radius > 0 or params.speckle_retry <= 0:
        return result
    return _retried(a, b, result, params, progress)


def _retried(
    a: Grid,
    b: Grid,
    first: MergeResult,
    params: MergeParams,
    progress: Callable[[str], None] | None,
) -> MergeResult:
    """The rejection ``first`` tried again with speckle read as unknown if a map is raw
    (``params.speckle_retry``), else as it is; measuring the maps is timed into its total
    (``timings_ms["speckle_share"]``)."""
    t0 = time.perf_counter()
    share = _raw_share(a, b, params)
    first = first.with_time("speckle_share", 1e3 * (time.perf_counter() - t0))
    if share < params.speckle_retry:
        return first
    if progress is not None:
        progress(
            f"{share:.1%} of a map's free cells are lone wall cells (a raw map?): trying "
            "again with them read as unknown (as --despeckle)"
        )
    try:
        again = _merge_pass(a, b, replace(params, speckle_radius=DESPECKLE_RADIUS), progress)
    except ValueError as exc:  # e.g. every wall of a map was lone: nothing left to register
        why = f"{first.reason}; with lone wall cells read as unknown: {exc}"
        return replace(first, reason=why)
    return _after_retry(first, again, share)


def _raw_share(a: Grid, b: Grid, params: MergeParams) -> float:
    """The larger share of lone wall cells among the two maps' free cells, read as the
    despeckle reading finds them (:func:`pgvd.speckle.speckle_share`)."""
    return max(
        speckle_share(
            g.probability(),
            params.occupied,
            params.free,
            radius_cells(DESPECKLE_RADIUS, g.resolution),
            params.speckle_cells,
        )
        for g in (a, b)
    )


def _after_retry(first: MergeResult, again: MergeResult, share: float) -> MergeResult:
    """The outcome of a merge retried with speckle read as unknown: the retry's, its reason
    saying so (and, if it too is rejected, why the maps as drawn were), its stages' times,
    the first pass's total as ``as_drawn`` and the total of both."""
    read = f"lone wall cells read as unknown ({share:.1%} of free cells)"
    if again.accepted:
        reason = f"accepted with {read}"
    else:
        reason = f"{again.reason}, with {read}; as drawn: {first.reason}"
    return replace(again.with_time("as_drawn", first.timings_ms["total"]), reason=reason)


def _merge_pass(
    a: Grid, b: Grid, params: MergeParams, progress: Callable[[str], None] | None
) -> MergeResult:
    """One search and decision of :func:`merge` with ``params`` as they are (no retry)."""
    clock = _Clock(progress)
    # the two maps' long array loops at once (pgvd.parallel), here and below; what the
    # reading says is told afterwards, A's first, on this thread: progress need not be
    # thread-safe, and its lines come in one order

    def read(grid: Grid) -> tuple[np.ndarray, list[str]]:
        said: list[str] = []
        return registration_probability(grid, params, said.append), said

    (pa, said_a), (pb, said_b) = both(read, a, b)
    if progress is not None:
        for name, said in (("A", said_a), ("B", said_b)):
            for line in said:
                progress(f"map {name}: {line}")
    _check_inputs(a, b, pa, pb, params)
    headings = _turned(estimate_headings(pa, pb, params.max_candidates), params.heading_offset)
    if progress is not None:
        # a heading that is wrong or too uncertain explains a failed merge: say them
        progress("candidate headings (10): " + ", ".join(map(_described, headings)))
    clock.lap("rotation")
    k = max(1, round(params.coarse_resolution / a.resolution))
    ca, cb = both(lambda p: coarsen(p, k, params.occupied), pa, pb)
    # Search only the known part of A; cells of A's crop are offset by off_a.
    rows, cols = _known_box(ca)
    ca = ca[rows, cols]
    off_a = _translation(cols.start, rows.start)
    coarse_res = a.resolution * k
    min_len = max(3, round(params.min_edge_length / coarse_res))
    clock.lap("coarsen")
    s_a, sp_a = _pgvd(ca, params)
    clock.lap("pgvd")
    graph_a = _keep_edges(build_graph(s_a, sp_a, min_len), params.max_edges)
    clock.lap("graph")
    if not graph_a.edges:
        return _rejected(f"map A has no GVD edge of {params.min_edge_length} m or more", clock)
    scores = OverlayScores(
        MapView(ca, params.occupied, params.free, 1), free=params.search_finalists > 0
    )
    correlator = EdgeCorrelator(graph_a.edges, params.edge_tolerance)
    radius = max(1, round(params.search_radius / coarse_res))
    clock.lap("verify")
    headings = _with_refined(headings, ca, cb, params)
    clock.lap("rotation")
    canvases: dict[float, np.ndarray] = {}
    turned = _ranked(
        [_rotate(h, cb, scores, params, canvases) for h in headings], _weights(params)[0]
    )
    clock.lap("verify")
    hyps: list[_Hypothesis] = []
    searched: tuple[float, ...] = ()
    turned = turned[: params.search_headings]
    for i, t in enumerate(turned):
        # A heading's hypotheses score at most its best overlay evidence, and the
        # finalists are the best by evidence: once that many supported ones beat
        # everything this heading and the ones after it could offer, by either
        # ranking, they cannot change the outcome, so their PGVD/Gamma stages are skipped.
        bounds = tuple(
            max(r.overlay.best_evidence(w) for r in turned[i:]) for w in _weights(params)
        )
        if _decided(hyps, params, bounds):
            break
        searched += (float(np.degrees(t.heading.psi)),)
        if progress is not None:
            progress(f"searching heading {_described(t.heading)}")
        hyps += _search_heading(t, graph_a, correlator, params, min_len, radius, clock)
    good = [h for h in hyps if h.support >= params.min_pairs]
    if not good:
        why = (
            "no edge pair passes the rho test (32)"
            if not hyps
            else (f"no translation is supported by {params.min_pairs} edge pairs")
        )
        return _rejected(why, clock)
    # the decision runs on maps pooled to about the cell size it was set on
    # (pgvd.pooling); its pose, distortion and covariance are brought back to A's pixels
    pool = decision_pool(a.resolution)
    res = a.resolution * pool
    if pool > 1 and progress is not None:
        progress(f"decision on the maps pooled {pool}x{pool}: {res:.3f} m cells")
    fine_a, fine_b = fine_maps(pa, pb, params, pool)
    clock.lap("verify")
    # a coarse cell is k / pool cells of the decision's maps, for A (cropped) as for B
    to_fine = block_scale(k / pool) @ off_a
    finalists = _finalists(good, params)
    best, decision, winner = _decide(finalists, fine_a, fine_b, to_fine, k / pool, params, res)
    clock.lap("refine")
    agreement = map_agreement(fine_a, fine_b, winner, max_points=params.fine_points, scaled=True)
    overlap_m = 0.5 * agreement.agree * res
    distortion = pool * residual_distortion(
        fine_a,
        fine_b.walls,
        winner,
        block=params.distortion_block / res,
        max_points=params.fine_points,
    )
    clock.lap("verify")
    matrix = from_pooled(winner, pool)
    extra = {"margin": decision.margin, "distortion_px": distortion, "headings_deg": searched}
    if decision.margin < params.min_margin:
        evidence = decision.winner.evidence(params.disagreement_weight)
        return _rejected(
            f"the best pose does not stand out: margin {decision.margin:.2f} < "
            f"{params.min_margin} (evidence {evidence:.0f}, best rival {decision.rival:.0f}: "
            f"{describe_rival(decision, fine_b.walls.mean(axis=0), res)})",
            clock,
            matrix,
            agreement.ratio,
            **extra,
        )
    if agreement.ratio < params.min_agreement:
        return _rejected(
            f"overlaid maps disagree: agreement {agreement.ratio:.2f} < {params.min_agreement}",
            clock,
            matrix,
            agreement.ratio,
            **extra,
        )
    if overlap_m < params.min_overlap:
        return _rejected(
            f"overlap too small: {overlap_m:.1f} m of agreeing walls < {params.min_overlap} m",
            clock,
            matrix,
            agreement.ratio,
            **extra,
        )
    cov = covariance_from_pooled(inflated_covariance(fine_a, fine_b, winner, res), winner, pool)
    clock.lap("covariance")
    diag = (
        _diagnostics(best, graph_a, sp_a, off_a, k, (a.shape, b.shape))
        if params.diagnostics
        else None
    )
    if diag is not None:
        clock.lap("diagnostics")
    return _result(True, "accepted", clock, matrix, agreement.ratio, cov, diag, **extra)
