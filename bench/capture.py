"""Everything a merge exposes, as JSON, so later analyses need no rerun.

:func:`result_json` serialises every field of :class:`pgvd.merge.MergeResult`
(whatever fields it has today or gains later) except the diagnostics images.

:class:`SearchedHeadings` records which candidate headings went through the
matching stages (PGVD, Gamma, rho) in a merge: the bench wraps
``pgvd.merge._search_heading``, the function each searched heading passes
through, for the duration of one merge.  That is private API: if it is gone,
nothing is recorded (None) rather than something guessed, and a
``candidates`` field of MergeResult, if the method exposes one, is in
:func:`result_json` anyway.
"""

from __future__ import annotations

import contextlib
import dataclasses
import importlib
from collections.abc import Iterator

import numpy as np

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


class SearchedHeadings:
    """Collects the headings (degrees) that went through matching during one merge."""

    def __init__(self) -> None:
        self.degrees: list[float] | None = None

    @contextlib.contextmanager
    def watching(self) -> Iterator[None]:
        # pgvd.merge is the function (pgvd's public API); the module is in sys.modules.
        core = importlib.import_module("pgvd.merge")
        original = getattr(core, "_search_heading", None)
        if original is None:
            self.degrees = None
            yield
            return
        seen: list[float] = []

        def wrapped(turned, *args, **kwargs):
            seen.append(float(np.degrees(turned.heading.psi)))
            return original(turned, *args, **kwargs)

        core._search_heading = wrapped
        try:
            yield
        finally:
            core._search_heading = original
            self.degrees = seen
