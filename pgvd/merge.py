"""The map-merging pipeline of the paper's Fig. 1, with verification and refinement.

Stages (``timings_ms`` keys):

``rotation``
    candidate headings from the angle spectra (10), :mod:`pgvd.rotation`;
    optionally (``OffParams.heading_span``) near each, the heading of best
    whole-map overlay (searched a few degrees around it at 0.4 m) is one too.
``coarsen``
    both maps pooled to the search scale (``SearchParams.coarse_resolution``,
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
    (with a one-coarse-cell tolerance, see :func:`pgvd.edge_matching.similarity`);
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
    distortion of the overlap (:func:`pgvd.alignment.residual_distortion`) is reported
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

from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np

from pgvd.agreement import map_agreement
from pgvd.alignment import residual_distortion
from pgvd.decision import Decision, describe_rival
from pgvd.diagnostics import diagnostics_of
from pgvd.edge_matching import EdgeCorrelator
from pgvd.finalists import choose_finalists, decided
from pgvd.graph import EdgeGraph, build_graph
from pgvd.grid import Grid
from pgvd.heading_search import (
    described,
    known_box,
    ranked,
    rotate,
    translation,
    turned_by,
    with_refined,
)
from pgvd.hypotheses import Hypothesis, keep_edges, search_heading, skeleton
from pgvd.inflation import inflated_covariance
from pgvd.inputs import check_inputs, check_map, registration_probability
from pgvd.overlay import Agreement, MapView, OverlayScores
from pgvd.parallel import both
from pgvd.params import MergeParams
from pgvd.pooling import block_scale, coarsen, covariance_from_pooled, decision_pool, from_pooled
from pgvd.result import MergeResult, merge_result, rejected
from pgvd.retry import Progress, retried
from pgvd.rotation import HeadingCandidate, estimate_headings
from pgvd.scoring import decide_hypotheses, fine_maps, overlay_floors
from pgvd.speckle import DESPECKLE_RADIUS
from pgvd.stage_clock import StageClock
from pgvd.walls import WallMap


@dataclass
class _Coarse:
    """Both maps at the search scale and A's side of the search, built once per pass."""

    k: int  # map cells per coarse cell
    ca: np.ndarray  # coarse A, cropped to its known cells
    cb: np.ndarray  # coarse B
    off_a: np.ndarray  # A's crop -> coarse A
    min_len: int  # shortest edge kept, coarse cells
    radius: int  # the search radius, coarse cells
    sp_a: np.ndarray  # A's PGVD (24) on its crop
    graph_a: EdgeGraph


@dataclass
class _Decided:
    """The decision of one pass, on the maps pooled to about 5 cm (``pool``, ``res`` m)."""

    best: Hypothesis
    decision: Decision
    winner: np.ndarray  # B pixel -> A pixel of the pooled maps
    pool: int
    res: float
    fine_a: WallMap
    fine_b: WallMap
    agreement: Agreement  # of all the walls at the winner
    distortion: float  # pixels of the full maps


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
        them read as unknown (``ReadingParams.speckle_retry``); the result is then the
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
    if result.accepted or params.off.speckle_radius > 0 or params.reading.speckle_retry <= 0:
        return result
    return retried(a, b, result, params, progress, _merge_pass)


def _merge_pass(a: Grid, b: Grid, params: MergeParams, progress: Progress) -> MergeResult:
    """One search and decision of :func:`merge` with ``params`` as they are (no retry)."""
    clock = StageClock(progress)
    pa, pb = _read(a, b, params, progress)
    headings = _headings(pa, pb, params, progress)
    clock.lap("rotation")
    coarse = _coarsen(pa, pb, a.resolution, params, clock)
    if not coarse.graph_a.edges:
        return rejected(_no_edge(params), clock)
    hyps, searched = _search(headings, coarse, params, progress, clock)
    good = [h for h in hyps if h.support >= params.search.min_pairs]
    if not good:
        why = (
            "no edge pair passes the rho test (32)"
            if not hyps
            else (f"no translation is supported by {params.search.min_pairs} edge pairs")
        )
        return rejected(why, clock)
    outcome = _decide(pa, pb, good, coarse, a.resolution, params, progress, clock)
    return _verdict(outcome, coarse, searched, (a.shape, b.shape), params, clock)


def _read(
    a: Grid, b: Grid, params: MergeParams, progress: Progress
) -> tuple[np.ndarray, np.ndarray]:
    """The probabilities registration reads of A and B (:func:`registration_probability`),
    checked (:func:`pgvd.inputs.check_inputs`)."""
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
    check_inputs(a, b, pa, pb, params)
    return pa, pb


def _headings(
    pa: np.ndarray, pb: np.ndarray, params: MergeParams, progress: Progress
) -> list[HeadingCandidate]:
    """The candidate headings of the angle spectra (10), turned by ``heading_offset``."""
    found = estimate_headings(pa, pb, params.search.max_candidates)
    headings = turned_by(found, params.off.heading_offset)
    if progress is not None:
        # a heading that is wrong or too uncertain explains a failed merge: say them
        progress("candidate headings (10): " + ", ".join(map(described, headings)))
    return headings


def _coarsen(
    pa: np.ndarray, pb: np.ndarray, resolution: float, params: MergeParams, clock: StageClock
) -> _Coarse:
    """Both maps pooled to the search scale, A cropped to its known cells, and A's PGVD
    (13)-(24) and edges (Sec. IV-D)."""
    k = max(1, round(params.search.coarse_resolution / resolution))
    ca, cb = both(lambda p: coarsen(p, k, params.reading.occupied), pa, pb)
    coarse_res = resolution * k
    ca, off_a, min_len, sp_a, graph_a = _graph_of_a(ca, coarse_res, params, clock)
    radius = max(1, round(params.search.search_radius / coarse_res))
    return _Coarse(k, ca, cb, off_a, min_len, radius, sp_a, graph_a)


def _graph_of_a(
    ca: np.ndarray, coarse_res: float, params: MergeParams, clock: StageClock
) -> tuple[np.ndarray, np.ndarray, int, np.ndarray, EdgeGraph]:
    """A's pooled map cropped to its known cells, the crop's offset, the shortest edge in
    cells, and A's PGVD (13)-(24) and edges (Sec. IV-D)."""
    # Search only the known part of A; cells of A's crop are offset by off_a.
    rows, cols = known_box(ca)
    ca = ca[rows, cols]
    off_a = translation(cols.start, rows.start)
    min_len = max(3, round(params.search.min_edge_length / coarse_res))
    clock.lap("coarsen")
    s_a, sp_a = skeleton(ca, params)
    clock.lap("pgvd")
    graph_a = keep_edges(build_graph(s_a, sp_a, min_len), params.search.max_edges)
    clock.lap("graph")
    return ca, off_a, min_len, sp_a, graph_a


def _no_edge(params: MergeParams) -> str:
    """Why a map A without a GVD edge long enough to match is rejected."""
    return f"map A has no GVD edge of {params.search.min_edge_length} m or more"


def a_side_rejection(a: Grid, params: MergeParams | None = None) -> str | None:
    """Why :func:`merge` rejects every pair whose map A is ``a``, whatever map B; None when
    some map B may pass.

    A map the merge cannot read (:func:`pgvd.inputs.check_map`), or whose PGVD has no edge
    of ``min_edge_length`` (the search matches A's edges, Sec. IV-D), is rejected before
    B's content counts; when a rejection would be retried with speckle read as unknown
    (:func:`pgvd.retry.retried`, which depends on B as well), ``a`` must fail that reading
    too.  The same stages as :func:`merge` on the same arrays, so the answer is the merge's
    own: a fleet asks it once per map version rather than paying a search per pair.
    """
    params = params or MergeParams()
    why, unreadable = _a_side(a, params)
    retry_off = params.off.speckle_radius > 0 or params.reading.speckle_retry <= 0
    if why is None or unreadable or retry_off:
        return why  # an unreadable map raises before any retry
    again, _ = _a_side(a, replace(params, speckle_radius=DESPECKLE_RADIUS))
    return None if again is None else why


def _a_side(a: Grid, params: MergeParams) -> tuple[str | None, bool]:
    """:func:`a_side_rejection` of one reading of ``a``, and whether the map is unreadable."""
    pa = registration_probability(a, params)
    try:
        check_map("A", a, pa, params)
    except ValueError as exc:
        return str(exc), True
    k = max(1, round(params.search.coarse_resolution / a.resolution))
    ca = coarsen(pa, k, params.reading.occupied)
    graph_a = _graph_of_a(ca, a.resolution * k, params, StageClock(None))[4]
    return (None if graph_a.edges else _no_edge(params)), False


def _search(
    headings: list[HeadingCandidate],
    coarse: _Coarse,
    params: MergeParams,
    progress: Progress,
    clock: StageClock,
) -> tuple[list[Hypothesis], tuple[float, ...]]:
    """The verified hypotheses of the searched headings, best whole-map overlay first, and
    those headings (degrees)."""
    reading = params.reading
    scores = OverlayScores(
        MapView(coarse.ca, reading.occupied, reading.free, 1), free=params.off.search_finalists > 0
    )
    correlator = EdgeCorrelator(coarse.graph_a.edges, params.search.edge_tolerance)
    clock.lap("verify")
    headings = with_refined(headings, coarse.ca, coarse.cb, params)
    clock.lap("rotation")
    canvases: dict[float, np.ndarray] = {}
    turned = ranked(
        [rotate(h, coarse.cb, scores, params, canvases) for h in headings],
        params.overlay_rankings()[0],
    )
    clock.lap("verify")
    hyps: list[Hypothesis] = []
    searched: tuple[float, ...] = ()
    turned = turned[: params.search.search_headings]
    for i, t in enumerate(turned):
        # A heading's hypotheses score at most its best overlay evidence, and the
        # finalists are the best by evidence: once that many supported ones beat
        # everything this heading and the ones after it could offer, by either
        # ranking, they cannot change the outcome, so their PGVD/Gamma stages are skipped.
        bounds = tuple(
            max(r.overlay.best_evidence(w) for r in turned[i:]) for w in params.overlay_rankings()
        )
        if decided(hyps, params, bounds):
            break
        searched += (float(np.degrees(t.heading.psi)),)
        if progress is not None:
            progress(f"searching heading {described(t.heading)}")
        graph_a, min_len, radius = coarse.graph_a, coarse.min_len, coarse.radius
        hyps += search_heading(t, graph_a, correlator, params, min_len, radius, clock)
    return hyps, searched


def _decide(
    pa: np.ndarray,
    pb: np.ndarray,
    good: list[Hypothesis],
    coarse: _Coarse,
    resolution: float,
    params: MergeParams,
    progress: Progress,
    clock: StageClock,
) -> _Decided:
    """The finalists of the supported hypotheses ``good`` refined and decided, and the
    winner's overlay and residual distortion."""
    # the decision runs on maps pooled to about the cell size it was set on
    # (pgvd.pooling); its pose, distortion and covariance are brought back to A's pixels
    pool = decision_pool(resolution)
    res = resolution * pool
    if pool > 1 and progress is not None:
        progress(f"decision on the maps pooled {pool}x{pool}: {res:.3f} m cells")
    fine_a, fine_b = fine_maps(pa, pb, params, pool)
    clock.lap("verify")
    # a coarse cell is k / pool cells of the decision's maps, for A (cropped) as for B
    k = coarse.k / pool
    to_fine = block_scale(k) @ coarse.off_a
    finalists = choose_finalists(good, params)
    best, decision, winner = decide_hypotheses(finalists, fine_a, fine_b, to_fine, k, params, res)
    clock.lap("refine")
    points = params.refinement.fine_points
    agreement = map_agreement(fine_a, fine_b, winner, max_points=points, scaled=True)
    distortion = pool * residual_distortion(
        fine_a,
        fine_b.walls,
        winner,
        block=params.decision.distortion_block / res,
        max_points=points,
    )
    clock.lap("verify")
    return _Decided(best, decision, winner, pool, res, fine_a, fine_b, agreement, distortion)


def _why_rejected(outcome: _Decided, params: MergeParams) -> str | None:
    """Why the decided pose is not accepted (its margin, agreement or overlap), or None."""
    decision, agreement, limits = outcome.decision, outcome.agreement, params.decision
    if decision.margin < limits.min_margin:
        evidence = decision.winner.evidence(limits.disagreement_weight)
        centre = outcome.fine_b.walls.mean(axis=0)
        return (
            f"the best pose does not stand out: margin {decision.margin:.2f} < "
            f"{limits.min_margin} (evidence {evidence:.0f}, best rival {decision.rival:.0f}: "
            f"{describe_rival(decision, centre, outcome.res)})"
        )
    return overlay_floors(agreement, outcome.res, params)


def _verdict(
    outcome: _Decided,
    coarse: _Coarse,
    searched: tuple[float, ...],
    shapes: tuple[tuple[int, int], tuple[int, int]],
    params: MergeParams,
    clock: StageClock,
) -> MergeResult:
    """The result of a decided pass, in the full maps' pixels: accepted with its covariance
    (3) and diagnostics, or rejected with why."""
    o = outcome
    matrix = from_pooled(o.winner, o.pool)
    extra = {"margin": o.decision.margin, "distortion_px": o.distortion, "headings_deg": searched}
    why = _why_rejected(o, params)
    if why is not None:
        limits = params.decision
        grey = limits.GREY_MARGIN <= o.decision.margin < limits.min_margin
        return rejected(why, clock, matrix, o.agreement.ratio, candidate=grey, **extra)
    cov = inflated_covariance(o.fine_a, o.fine_b, o.winner, o.res)
    cov = covariance_from_pooled(cov, o.winner, o.pool)
    clock.lap("covariance")
    diag = (
        diagnostics_of(o.best, coarse.graph_a, coarse.sp_a, coarse.off_a, coarse.k, shapes)
        if params.diagnostics
        else None
    )
    if diag is not None:
        clock.lap("diagnostics")
    return merge_result(True, "accepted", clock, matrix, o.agreement.ratio, cov, diag, **extra)
