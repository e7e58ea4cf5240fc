"""Competitor map-merging methods, rebuilt for the side-by-side bench (bench-only code).

Every module exposes ``merge(a: Grid, b: Grid, **params) -> BaselineResult`` whose
``matrix`` maps B pixels to A pixels, the convention of :mod:`pgvd.grid`.
"""
