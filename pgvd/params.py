"""The parameters of :func:`pgvd.merge.merge`, grouped by the stage that reads them.

Every default was set on the development pairs of the merge bench
(``python -m bench.merge``; results in ``bench/results/``); what was measured for each,
and what was tried instead, is in ``docs/studies-merge-history.md``.  Lengths are in
metres and converted to cells by the merge.

:class:`ReadingParams`
    how registration reads a map (walls, free space, a map painted free, speckle).
:class:`SearchParams`
    the coarse search: candidate headings (10), PGVD (13)-(24), Gamma and rho (26)-(32).
:class:`DecisionParams`
    the finalists, their drift-tolerant scoring and the acceptance (:mod:`pgvd.decision`).
:class:`RefinementParams`
    how many wall cells the full-resolution refinement and scoring use.
:class:`OffParams`
    options kept off in use and switches that exist for ablations only.

:class:`MergeParams` holds one of each.  It takes and gives every field by its own
name as well (``MergeParams(min_margin=0.6)``, ``dataclasses.replace(params,
min_agreement=0.9)``, ``params.min_margin``), so that a caller setting one field needs
not know its group; the stages read their group.
"""

from __future__ import annotations

from dataclasses import dataclass, fields, replace
from typing import Any, ClassVar

from pgvd.overlay import OverlayWeights
from pgvd.rotation import OCCUPIED


@dataclass(frozen=True)
class ReadingParams:
    """How registration reads a map's probabilities (defaults set on the merge bench).

    Attributes
    ----------
    occupied : probability above which a cell is a wall (the headings' threshold).
    free : probability below which a cell is free space.
    min_unknown : a map with a smaller share of unknown cells was painted free: its free
        space outside its walls' convex hull is read as unknown.
    speckle_cells : a wall cell with at most this many wall cells (itself included) in
        its square is speckle (:mod:`pgvd.speckle`).
    speckle_retry : a rejected merge is tried again with speckle read as unknown when a
        map has at least this share of its free cells as lone walls (a raw map image);
        0 turns it off.
    """

    occupied: float = OCCUPIED
    free: float = 0.3
    min_unknown: float = 0.01
    speckle_cells: int = 2
    speckle_retry: float = 0.004


@dataclass(frozen=True)
class SearchParams:
    """The coarse search for hypotheses (defaults set on the merge bench).

    Attributes
    ----------
    coarse_resolution : cell size (m) of the PGVD/Gamma stages: 16x fewer cells than
        0.05 m maps, walls kept.
    max_candidates : candidate headings of the angle spectra (10); indoor maps are
        ambiguous modulo 90 and 180 degrees.
    search_headings : candidates, best whole-map overlay first, that go through the
        PGVD stages.
    overlay_peaks : best whole-map overlay peaks per heading proposed beside the edge
        pairs' translations (29): a small overlap has few crossing edges.
    rho : matching percentage of the existence test (32).
    edge_tolerance : cells by which A's edges are grey-dilated, so that a skeleton moved
        by one cell still matches.
    min_edge_length : edges shorter than this (m) are dropped (Sec. IV-E).
    max_edges : longest, most confident edges kept per map, bounding Gamma's size.
    max_hypotheses : translations proposed per heading, best Gamma first.
    search_radius : each proposal slides (m) to the best whole-map overlay nearby: a
        straight edge pair fixes the translation only across the corridor.
    min_pairs : edge pairs that must pass (32) at a translation; one, since a small
        overlap is crossed by few edges and the decision rejects look-alikes.
    """

    coarse_resolution: float = 0.2
    max_candidates: int = 6
    search_headings: int = 6
    overlay_peaks: int = 5
    rho: float = 0.7
    edge_tolerance: int = 1
    min_edge_length: float = 1.6
    max_edges: int = 80
    max_hypotheses: int = 40
    search_radius: float = 2.4
    min_pairs: int = 1


@dataclass(frozen=True)
class DecisionParams:
    """The finalists, their scoring and the acceptance (defaults set on the merge bench).

    Attributes
    ----------
    finalists : best coarse hypotheses, by walls-only evidence, refined and compared at
        full resolution.
    disagreement_weight : a wall on clear free space weighs this many walls on walls:
        walls are everywhere in a building, conflicts are not.
    drift_shift : largest shift (m) of each square of the overlap before counting, so
        that a drifted map's walls beside the other's are not conflicts (0: rigid).
    distortion_block : side (m) of those squares and of the residual distortion's.
    rival_distance : finalists moving B's wall centroid by more than this (m), or turning
        it by more than 2 degrees, are rivals; closer ones are the winner again.
    probe_shifts : the winner shifted by these multiples of ``rival_distance`` is a rival
        too, so that a corridor alike along its length does not pass.
    min_margin : the returned pose's margin over its best rival, per overlapping wall,
        must reach this: just above the largest margin of a wrong or negative winner.
    GREY_MARGIN : a rejected pose of margin in ``[GREY_MARGIN, min_margin)`` is a
        candidate, worth a look but no merge: right poses the bench rejects have margins
        0.05-0.56, and wrong winners reach 0.53 (a constant, not a parameter).
    margin_noise : the margin is lowered by this over the square root of the overlap's
        wall count: a small overlap's margin swings more.
    min_agreement : floor on agree / (agree + disagree) of the final overlay; 0, the
        margin decides alone (``pgvd agent --min-agreement`` sets it).
    min_overlap : minimum length (m) of agreeing walls; small, so that a short but crisp
        overlap can pass.
    """

    finalists: int = 8
    disagreement_weight: float = 4.0
    drift_shift: float = 0.75
    distortion_block: float = 5.0
    rival_distance: float = 1.0
    probe_shifts: tuple[float, ...] = (1.5, 3.0)
    min_margin: float = 0.57
    GREY_MARGIN: ClassVar[float] = 0.0
    margin_noise: float = 3.0
    min_agreement: float = 0.0
    min_overlap: float = 3.0


@dataclass(frozen=True)
class RefinementParams:
    """Wall cells of the full-resolution stages (defaults set on the merge bench).

    Attributes
    ----------
    refine_points : wall cells per map used to refine and score the finalists.
    fine_points : wall cells per map, at most, of the winner's last refinement, overlay
        and distortion: every cell of a 0.05 m development map, and a time that stops
        growing on finer maps.
    """

    refine_points: int = 1500
    fine_points: int = 20000


@dataclass(frozen=True)
class OffParams:
    """Options kept off in use, and switches for ablations only (the bench measured both).

    Attributes
    ----------
    heading_span, heading_step : near each candidate heading, the heading of best
        whole-map overlay within ``heading_span`` degrees, in ``heading_step`` steps, is a
        candidate too; off (0): it loses as many pairs in the decision as it finds.
    search_finalists : finalists more, chosen by the search evidence below; off (0): the
        extra finalists are rivals too and lower true winners' margins.
    search_conflict_weight, search_free_weight : with ``search_finalists``, the weights of
        the search evidence ``agree + free_weight * free_agree - conflict_weight *
        disagree``: free space seen by both maps is evidence too.
    speckle_radius : half-side (m) of the square in which a lone wall cell is speckle,
        read as unknown (``pgvd merge --despeckle``); off (0): a laser's far walls are
        sparse dots too.
    heading_offset : degrees added to every candidate heading, to measure how much the
        outcome hangs on the heading estimate; 0 in use.
    probabilistic : False: the plain GVD, the paper's deterministic Gamma_det of (41)
        (ablation).
    rho_veto : False: no existence test (32), every correlating pair proposes (ablation).
    gamma_ranking : False: translations proposed in edge order, not best Gamma (27) first
        (ablation).
    heading_blur : False: B's PGVD without the heading variance's tangential blur, eq.
        (8) (ablation).
    """

    heading_span: float = 0.0
    heading_step: float = 3.0
    search_finalists: int = 0
    search_conflict_weight: float = 24.0
    search_free_weight: float = 0.5
    speckle_radius: float = 0.0
    heading_offset: float = 0.0
    probabilistic: bool = True
    rho_veto: bool = True
    gamma_ranking: bool = True
    heading_blur: bool = True

    @property
    def search_weights(self) -> OverlayWeights:
        """The search evidence (``search_conflict_weight``, ``search_free_weight``)."""
        return OverlayWeights(self.search_conflict_weight, self.search_free_weight)


#: The groups of :class:`MergeParams`, by attribute name.
_GROUPS: dict[str, type] = {
    "reading": ReadingParams,
    "search": SearchParams,
    "decision": DecisionParams,
    "refinement": RefinementParams,
    "off": OffParams,
}


def _group_of() -> dict[str, str]:
    """Each field's (and public property's) own name -> the group holding it."""
    out: dict[str, str] = {}
    for group, cls in _GROUPS.items():
        for name in (n for n in dir(cls) if not n.startswith("_")):
            if name in out:
                raise TypeError(f"{name!r} is in both {out[name]!r} and {group!r}")
            out[name] = group
    return out


_GROUP_OF = _group_of()


@dataclass(frozen=True, init=False)
class MergeParams:
    """Parameters of :func:`pgvd.merge.merge`: one group per stage, plus ``diagnostics``.

    Built from groups, from fields by their own name, or both
    (``MergeParams(diagnostics=False, min_margin=0.6)``); a field named alone goes to
    its group, and ``dataclasses.replace`` takes field names the same way.  Reading a
    field by its own name (``params.min_margin``) reads it from its group.

    Attributes
    ----------
    reading, search, decision, refinement, off : the groups (see :mod:`pgvd.params`).
    diagnostics : fill :attr:`pgvd.result.MergeResult.diagnostics`.

    Raises
    ------
    TypeError
        A keyword that is neither a group nor a field of one.
    """

    reading: ReadingParams
    search: SearchParams
    decision: DecisionParams
    refinement: RefinementParams
    off: OffParams
    diagnostics: bool

    def __init__(
        self,
        reading: ReadingParams | None = None,
        search: SearchParams | None = None,
        decision: DecisionParams | None = None,
        refinement: RefinementParams | None = None,
        off: OffParams | None = None,
        diagnostics: bool = True,
        **by_name: Any,
    ) -> None:
        given = {
            "reading": reading,
            "search": search,
            "decision": decision,
            "refinement": refinement,
            "off": off,
        }
        unknown = sorted(set(by_name) - {n for n, g in _GROUP_OF.items() if _is_field(g, n)})
        if unknown:
            raise TypeError(f"MergeParams has no field {unknown[0]!r}")
        for group, cls in _GROUPS.items():
            value = given[group] if given[group] is not None else cls()
            own = {n: v for n, v in by_name.items() if _GROUP_OF[n] == group}
            object.__setattr__(self, group, replace(value, **own) if own else value)
        object.__setattr__(self, "diagnostics", diagnostics)

    def __getattr__(self, name: str) -> Any:
        """A field (or property) of a group, by its own name."""
        group = _GROUP_OF.get(name)
        if group is None or name in _GROUPS:
            raise AttributeError(f"'MergeParams' object has no attribute {name!r}")
        return getattr(getattr(self, group), name)

    @staticmethod
    def field_names() -> tuple[str, ...]:
        """Every field a caller may set by its own name (the groups' fields and
        ``diagnostics``)."""
        return (*(n for n, g in _GROUP_OF.items() if _is_field(g, n)), "diagnostics")

    def overlay_rankings(self) -> tuple[OverlayWeights, ...]:
        """The rankings of the coarse hypotheses: walls only (``agree -
        disagreement_weight * disagree``), then, with ``search_finalists``, the search
        evidence (:attr:`OffParams.search_weights`)."""
        walls = OverlayWeights(self.decision.disagreement_weight)
        return (walls, self.off.search_weights) if self.off.search_finalists > 0 else (walls,)


def _is_field(group: str, name: str) -> bool:
    """Whether ``name`` is a dataclass field of the group ``group`` (not a property)."""
    return name in {f.name for f in fields(_GROUPS[group])}
