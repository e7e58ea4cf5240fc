"""The finalists: the coarse hypotheses refined and compared at full resolution, and the
bound that ends the search once more headings cannot change them."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from pgvd.hypotheses import Hypothesis
from pgvd.params import MergeParams


def _near(h: Hypothesis, chosen: list[Hypothesis]) -> bool:
    """True when ``h`` is within 2 degrees and 3 coarse cells of one of ``chosen``."""
    return any(
        abs(np.angle(np.exp(1j * (h.heading.psi - o.heading.psi)))) < np.radians(2.0)
        and np.hypot(*(h.coarse_matrix[:2, 2] - o.coarse_matrix[:2, 2])) < 3.0
        for o in chosen
    )


def _best(
    hyps: list[Hypothesis],
    n: int,
    key: Callable[[Hypothesis], float],
    chosen: tuple[Hypothesis, ...] = (),
) -> list[Hypothesis]:
    """The ``n`` best hypotheses by ``key``, skipping near-duplicates of better ones and
    of ``chosen``."""
    out: list[Hypothesis] = []
    for h in sorted(hyps, key=lambda h: (-key(h), -h.ratio)):
        if len(out) == n:
            break
        if not _near(h, [*chosen, *out]):
            out.append(h)
    return out


def _rankings(params: MergeParams) -> list[tuple[int, Callable[[Hypothesis], float]]]:
    """How many finalists each ranking chooses, and its key."""
    out = [(params.decision.finalists, lambda h: h.evidence)]
    if params.off.search_finalists > 0:
        out.append((params.off.search_finalists, lambda h: h.search_evidence))
    return out


def choose_finalists(hyps: list[Hypothesis], params: MergeParams) -> list[Hypothesis]:
    """The ``finalists`` best by walls-only evidence, then the ``search_finalists`` best by
    the search evidence (``search_weights``) among those that beat every walls-ranked
    finalist by it.

    The search evidence finds small, consistent overlaps that look-alikes with more
    walls outrank; the walls-only evidence keeps those look-alikes among the
    finalists, where the decision weighs the winner against them (:mod:`pgvd.decision`).
    The bar keeps the extra finalists to pairs where the two rankings disagree: where
    the walls' best is also the search's, more finalists would only be more rivals.
    """
    out: list[Hypothesis] = []
    for n, key in _rankings(params):
        bar = max((key(h) for h in out), default=-np.inf)
        out += _best([h for h in hyps if key(h) > bar], n, key, tuple(out))
    return out


def decided(hyps: list[Hypothesis], params: MergeParams, bounds: tuple[float, ...]) -> bool:
    """True when, by each ranking (:func:`_rankings`), as many supported hypotheses as it
    chooses all score above that ranking's bound in ``bounds``."""
    good = [h for h in hyps if h.support >= params.search.min_pairs]
    for (n, key), bound in zip(_rankings(params), bounds, strict=True):
        chosen = _best(good, n, key)
        if len(chosen) < n or key(chosen[-1]) <= bound:
            return False
    return True
