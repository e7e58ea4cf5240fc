"""Everything a merge exposes, as JSON, so later analyses need no rerun.

:func:`result_json` serialises every field of :class:`pgvd.result.MergeResult`
(whatever fields it has today or gains later) except the diagnostics images.

:class:`SearchedHeadings` records which candidate headings went through the
matching stages (PGVD, Gamma, rho) in a merge: the bench wraps
``pgvd.hypotheses.search_heading``, the function each searched heading passes
through, for the duration of one merge.  That is private API: if it is gone,
nothing is recorded (None) rather than something guessed, and a
``candidates`` field of MergeResult, if the method exposes one, is in
:func:`result_json` anyway.

:class:`Finalists` records, the same way, the refined B->A matrices of the
finalists that reach the decision: the ``scored`` hypotheses handed to
``pgvd.scoring.decide`` (:func:`pgvd.decision.decide`).  With them the bench
separates "the search did not find the pose" from "the decision did not pick
or accept it" (pose recall, :mod:`bench.studies.recall`).
"""

from __future__ import annotations

import contextlib
import dataclasses
import importlib
from collections.abc import Callable, Iterator

import numpy as np

from pgvd.pooling import from_pooled

#: MergeResult fields not worth storing per pair (images for a person to look at).
SKIPPED_FIELDS = {"diagnostics"}


def to_json(value: object, depth: int = 0) -> object:
    """numpy arrays, scalars, dataclasses, dicts and lists to plain JSON values (NaN -> None)."""
    if depth > 6:
        return repr(value)
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {
            f.name: to_json(getattr(value, f.name), depth + 1) for f in dataclasses.fields(value)
        }
    if isinstance(value, dict):
        return {str(k): to_json(v, depth + 1) for k, v in value.items()}
    if isinstance(value, np.ndarray):
        return to_json(value.tolist(), depth + 1)
    if isinstance(value, (list, tuple)):
        return [to_json(v, depth + 1) for v in value]
    if isinstance(value, (np.bool_, bool)):
        return bool(value)
    if isinstance(value, (np.integer, int)):
        return int(value)
    if isinstance(value, (np.floating, float)):
        return float(value) if np.isfinite(value) else None
    if value is None or isinstance(value, str):
        return value
    return repr(value)


def result_json(result: object) -> dict:
    """Every field of a MergeResult but the diagnostics images."""
    return {
        f.name: to_json(getattr(result, f.name))
        for f in dataclasses.fields(result)
        if f.name not in SKIPPED_FIELDS
    }


@contextlib.contextmanager
def _wrapping(name: str, seen: Callable[..., None], module: str = "pgvd.merge") -> Iterator[bool]:
    """Wrap ``<module>.<name>`` so that ``seen`` gets each call's arguments first.

    Yields False (and wraps nothing) when the private function is gone.
    """
    # pgvd.merge is the function (pgvd's public API); the module is in sys.modules.
    core = importlib.import_module(module)
    original = getattr(core, name, None)
    if original is None:
        yield False
        return

    def wrapped(*args, **kwargs):
        seen(*args, **kwargs)
        return original(*args, **kwargs)

    setattr(core, name, wrapped)
    try:
        yield True
    finally:
        setattr(core, name, original)


class SearchedHeadings:
    """Collects the headings (degrees) that went through matching during one merge, and
    their standard deviations (degrees, the square root of the candidates' variance)."""

    def __init__(self) -> None:
        self.degrees: list[float] | None = None
        self.sigmas: list[float] | None = None

    @contextlib.contextmanager
    def watching(self) -> Iterator[None]:
        seen: list = []
        # a merge retried (a raw map, MergeParams.speckle_retry) reports its last pass
        with (
            _wrapping("_merge_pass", lambda *_, **__: seen.clear()),
            _wrapping("search_heading", lambda turned, *_, **__: seen.append(turned.heading)) as ok,
        ):
            yield
        self.degrees = [float(np.degrees(h.psi)) for h in seen] if ok else None
        self.sigmas = [float(np.degrees(np.sqrt(h.variance))) for h in seen] if ok else None


class Finalists:
    """Collects the refined B->A matrices of the finalists of one merge (before the decision).

    ``matrices`` is None when the hook is gone, an empty list when no hypothesis
    reached the decision.
    """

    def __init__(self) -> None:
        self.matrices: list[np.ndarray] | None = None

    @contextlib.contextmanager
    def watching(self) -> Iterator[None]:
        # decide() is called once for the finalists and again with the shifted probes:
        # the finalists are the ``scored`` argument of the last call.
        calls: list[list] = []
        # of a merge retried (a raw map), the last pass's
        with (
            _wrapping("_merge_pass", lambda *_, **__: calls.clear()),
            _wrapping(
                "decide", lambda scored, *_, **__: calls.append(list(scored)), "pgvd.scoring"
            ) as ok,
        ):
            yield
        self.matrices = [np.asarray(s.matrix) for s in calls[-1]] if calls else []
        if not ok:
            self.matrices = None

    def full_frame(self, pool: int) -> list[np.ndarray] | None:
        """:attr:`matrices` in the full maps' pixels: the decision sees its maps pooled
        ``pool x pool`` (:func:`pgvd.pooling.decision_pool`)."""
        if self.matrices is None:
            return None
        return [from_pooled(m, pool) for m in self.matrices]
