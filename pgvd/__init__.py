"""PGVD map merging: pure functions on numpy occupancy grids, no network, no clocks.

This package implements the map merging of Saeedi, Paull, Trentini, Seto and
Li, "Map merging using probabilistic generalized Voronoi diagrams", IROS 2012
(equation numbers in the docstrings are that paper's), with a verification
step of its own.  Read two maps, find the transform between them, fuse them::

    import pgvd

    a = pgvd.read_map("examples/intel_a.yaml")
    b = pgvd.read_map("examples/intel_b.yaml")
    result = pgvd.merge(a, b)  # result.matrix maps B pixels to A pixels
    if result.accepted:
        fused = pgvd.fuse_maps(a, b, result.matrix, result.covariance)
        pgvd.write_map("fused.yaml", fused)

Maps
    :class:`Grid` (log-odds, eq. (9)), :func:`read_map`, :func:`write_map`,
    :func:`write_png`, :class:`MapFormatError`, :func:`resample`.
Frames (x = column, y = row; a relative transform maps B pixels to A pixels)
    :func:`rigid_matrix`, :func:`heading`, :func:`matrix_to_pose`, :func:`relative_matrix`,
    :func:`map_frame_pose`, :func:`map_frame_covariance`, :func:`pixel_to_world`,
    :func:`world_to_pixel`, :func:`warp`, :func:`union_canvas`.
Merging (the paper's Fig. 1, eqs. (10)-(32))
    :func:`merge`, :class:`MergeParams`, :class:`MergeResult`, :class:`MergeDiagnostics`;
    :func:`verify` confirms or rejects a pose known beforehand (a chain of links, a known
    initial pose) without the search.
Fusion (eqs. (4)-(8) and (33)-(37))
    :func:`fuse_maps`, :func:`fuse`, :func:`fuse_many`, :func:`propagate`,
    :func:`compose_covariance`, :func:`inverse_covariance`.
Laser logs
    :func:`read_carmen`, :class:`LaserScan`, :class:`LogFormatError`,
    :func:`frame_for`, :func:`integrate`.
Pictures
    :func:`merge_figure` (an RGB array; write it with :func:`write_png`).

The paper's blocks live in submodules, one concept per function:
:mod:`pgvd.rotation` (10), :mod:`pgvd.uncertainty` (4)-(8), :mod:`pgvd.gvd`
(13)-(24), :mod:`pgvd.graph` (Sec. IV-D, (25)), :mod:`pgvd.edge_matching`
(26)-(32), :mod:`pgvd.fusion` (33)-(37).  The merge's own stages (Fig. 1, and the
verification the paper leaves to future work) are listed in :mod:`pgvd.merge`; its
parameters, by stage, in :mod:`pgvd.params`.

``import pgvd`` loads none of them: each name above is imported from its
submodule on first use (PEP 562), so a program that only reads a map does
not pay for scipy and scikit-image.
"""

from __future__ import annotations

import importlib
import sys
import types

#: Public name -> the submodule that defines it.
_HOME = {
    "Grid": "pgvd.grid",
    "heading": "pgvd.grid",
    "map_frame_covariance": "pgvd.grid",
    "map_frame_pose": "pgvd.grid",
    "matrix_to_pose": "pgvd.grid",
    "pixel_to_world": "pgvd.grid",
    "relative_matrix": "pgvd.grid",
    "rigid_matrix": "pgvd.grid",
    "world_to_pixel": "pgvd.grid",
    "MapFormatError": "pgvd.io",
    "read_map": "pgvd.io",
    "write_map": "pgvd.io",
    "write_png": "pgvd.io",
    "LaserScan": "pgvd.carmen",
    "LogFormatError": "pgvd.carmen",
    "read_carmen": "pgvd.carmen",
    "frame_for": "pgvd.integrate",
    "integrate": "pgvd.integrate",
    "resample": "pgvd.transform",
    "union_canvas": "pgvd.transform",
    "warp": "pgvd.transform",
    "MergeDiagnostics": "pgvd.diagnostics",
    "MergeParams": "pgvd.params",
    "MergeResult": "pgvd.result",
    "merge": "pgvd.merge",
    "verify": "pgvd.verify",
    "compose_covariance": "pgvd.uncertainty",
    "inverse_covariance": "pgvd.uncertainty",
    "propagate": "pgvd.uncertainty",
    "fuse": "pgvd.fusion",
    "fuse_many": "pgvd.fusion",
    "fuse_maps": "pgvd.fusion",
    "merge_figure": "pgvd.render",
}

__all__ = [
    "Grid",
    "LaserScan",
    "LogFormatError",
    "MapFormatError",
    "MergeDiagnostics",
    "MergeParams",
    "MergeResult",
    "compose_covariance",
    "frame_for",
    "fuse",
    "fuse_many",
    "fuse_maps",
    "heading",
    "integrate",
    "inverse_covariance",
    "map_frame_covariance",
    "map_frame_pose",
    "matrix_to_pose",
    "merge",
    "merge_figure",
    "pixel_to_world",
    "propagate",
    "read_carmen",
    "read_map",
    "relative_matrix",
    "resample",
    "rigid_matrix",
    "union_canvas",
    "verify",
    "warp",
    "world_to_pixel",
    "write_map",
    "write_png",
]


def __getattr__(name: str) -> object:
    """Import a public name from its submodule on first use (PEP 562)."""
    home = _HOME.get(name)
    if home is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(home), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted({*globals(), *__all__})


class _Package(types.ModuleType):
    """The package, refusing to let a submodule hide the function of the same name.

    Importing the submodule ``pgvd.merge`` binds it as the package's attribute
    ``merge``, which would replace the function :func:`merge` -- or not,
    depending on what was imported first.  The binding is skipped, so
    ``pgvd.merge`` is always the function; the submodule stays importable
    (``from pgvd.merge import coarsen``, ``importlib.import_module``).  So is
    ``pgvd.verify``.
    """

    def __setattr__(self, name: str, value: object) -> None:
        if name in _HOME and isinstance(value, types.ModuleType):
            return
        super().__setattr__(name, value)


sys.modules[__name__].__class__ = _Package
