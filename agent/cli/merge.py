"""``pgvd merge A B``: find the transform from B's pixels to A's of two map files, and fuse them.

Exit 0 when the maps merge (``-o`` and ``--plot`` are written), 3 when they do
not overlap (``--plot`` still shows why), 2 on bad input with one line on stderr.
Only numpy and the map reader load before the files are read; scipy and scikit-image load
once both maps are known good.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import sys
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from agent.cli.common import EXIT_NO_OVERLAP, EXIT_OK, CliError, check_resolution_option
from agent.pose import Pose, parse_pose
from pgvd.grid import Grid, map_frame_covariance, map_frame_pose, matrix_to_pose
from pgvd.io import MAX_CELLS, MapFormatError, read_map, write_map, write_png, written_files
from pgvd.map_yaml import YAML_SUFFIXES, map_image_path
from pgvd.npy_map import NPY_RESOLUTION

if TYPE_CHECKING:
    from agent.multimerge import ManyMerge
    from pgvd.params import MergeParams
    from pgvd.result import MergeResult

_MAP_SUFFIXES = (*YAML_SUFFIXES, ".npy")
#: Largest ``--prior`` offset (m) of B's map frame from A's.
_MAX_PRIOR_M = 1e6


def configure(p: argparse.ArgumentParser) -> None:
    """Add the arguments of ``pgvd merge`` to its parser."""
    p.description = (
        "Find the transform from map B's pixels to map A's pixels with the PGVD method "
        "and fuse B into A. Exit 0: merged; 3: no overlap; 2: bad input."
    )
    p.add_argument(
        "a",
        metavar="A",
        type=Path,
        help="map A: .yaml map_server file, a bare .pgm/.png image (with --resolution), or .npy "
        "probabilities (0.5 unknown)",
    )
    p.add_argument(
        "b", metavar="B", type=Path, help="map B, resampled to A's resolution if it differs"
    )
    p.add_argument(
        "more",
        metavar="C",
        type=Path,
        nargs="*",
        default=[],  # without a default argparse names C among the missing required arguments
        help="more maps: all pairs are registered and placed jointly, as a fleet would "
        "(--json then lists maps and links; -o writes the largest merged group)",
    )
    p.add_argument(
        "-o",
        "--output",
        type=Path,
        metavar="FUSED",
        help="write the fused map: .yaml (map_server, with resolution and origin) or .npy "
        "(probabilities only: no resolution, no origin)",
    )
    p.add_argument(
        "--json", action="store_true", help="print one JSON object (matrix, covariance, ...)"
    )
    p.add_argument("--plot", type=Path, metavar="OUT.png", help="write a PNG of the merge")
    p.add_argument(
        "--despeckle",
        action="store_true",
        help="read lone wall cells as unknown, for raw map images saved without cleaning "
        "(two maps only; not for a laser's own maps, whose far walls are sparse dots). "
        "Without it a rejected merge is retried so when a map's lone wall cells are "
        "0.4 %% of its free cells or more",
    )
    p.add_argument(
        "--prior",
        metavar="X,Y,YAW",
        help="B's map frame in A's (m, m, rad; REP 103; write --prior=X,Y,YAW when X is "
        "negative), e.g. from the robots' known initial poses: the merge is checked there "
        "first (pgvd.verify: confirmed if refining it moves B's walls by at most 1 m and 5 "
        "deg; give it to a few tenths of a metre at B's walls) and searched only if the "
        "check fails (two maps only)",
    )
    p.add_argument(
        "--resolution",
        type=float,
        metavar="M",
        help="cell size (m) of maps whose files carry none: bare .pgm/.png images, read with "
        f"map_saver's classes (required for them), and .npy arrays (default {NPY_RESOLUTION})",
    )
    p.add_argument(
        "--max-cells",
        type=int,
        default=MAX_CELLS,
        metavar="N",
        help=f"refuse maps with more cells than N (default {MAX_CELLS})",
    )
    p.add_argument("-v", "--verbose", action="store_true", help="print stages on stderr")
    p.set_defaults(func=run)


def _progress(args: argparse.Namespace) -> Callable[[str], None] | None:
    if args.json and not args.verbose:
        return None
    if not (args.verbose or sys.stderr.isatty()):
        return None
    return lambda line: print(f"pgvd merge: {line}", file=sys.stderr, flush=True)


def _say_mostly_walls(named: list[tuple[str, Grid]]) -> None:
    """A note (stderr) for each map that is mostly walls, which is how an image that stores
    unknown space black reads: the merge is tried all the same, and likely rejected."""
    from pgvd.params import MergeParams
    from pgvd.unexplored import MOSTLY_WALLS, wall_share

    params = MergeParams()
    for name, grid in named:
        share = wall_share(grid.probability(), params.free, params.occupied)
        if share > MOSTLY_WALLS:
            print(
                f"pgvd merge: note: {100 * share:.0f} % of {name}'s known cells are walls (a "
                "laser's map is mostly free space, its walls a few per cent): does its image "
                "draw unknown space black? "
                "map_server images draw it grey (205), between free_thresh and occupied_thresh",
                file=sys.stderr,
            )


def _read(path: Path, args: argparse.Namespace) -> Grid:
    """One map file, with ``--max-cells`` and, for files that carry none, ``--resolution``."""
    resolution = args.resolution
    try:
        return read_map(
            path,
            args.max_cells,
            npy_resolution=NPY_RESOLUTION if resolution is None else resolution,
            image_resolution=resolution,
        )
    except MapFormatError as exc:
        raise CliError(str(exc)) from None


def _check_resampled(path: Path, grid: Grid, resolution: float, max_cells: int) -> None:
    """Refuse a map that, resampled to ``resolution`` (:func:`pgvd.transform.resample`'s
    size), would hold more than ``--max-cells``: checked before it is built, since a map of
    far coarser cells than the first one's would otherwise be built however large."""
    rows, cols = (round(n * grid.resolution / resolution) for n in grid.shape)
    if rows * cols > max_cells:
        raise CliError(
            f"{path}: resampled to {resolution:g} m/cell, {rows} x {cols} cells, over --max-cells"
        )


def _finite_or_none(value: object) -> object:
    """JSON has no NaN: a rejected merge's covariance is reported as nulls."""
    if isinstance(value, list):
        return [_finite_or_none(v) for v in value]
    if isinstance(value, dict):
        return {k: _finite_or_none(v) for k, v in value.items()}
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def map_frame(
    a: Grid, b: Grid, matrix: np.ndarray, covariance: np.ndarray | None = None
) -> dict[str, object] | None:
    """``{"x", "y", "yaw"}``: B's map frame in A's (m, m, rad; :func:`pgvd.grid.map_frame_pose`),
    with ``covariance`` over them (:func:`pgvd.grid.map_frame_covariance`) when one is given
    (null when it is not finite); None for a matrix that is not finite (a merge rejected
    before any pose)."""
    if not np.isfinite(matrix).all():
        return None
    frame: dict[str, object] = dict(
        zip(("x", "y", "yaw"), map_frame_pose(a, b, matrix), strict=True)
    )
    if covariance is not None:
        finite = np.isfinite(covariance).all()
        cov = map_frame_covariance(a, b, matrix, covariance) if finite else None
        frame["covariance"] = None if cov is None else [[float(v) for v in row] for row in cov]
    return frame


def report(result: MergeResult, a: Grid, b: Grid, b_scale: np.ndarray | None) -> dict:
    """The ``--json`` object: ``accepted``, ``matrix`` (B pixels -> A pixels), ``rotation_deg``,
    ``translation_px``, ``covariance``, ``score``, ``timings_ms``, ``reason`` and
    ``map_frame`` (B's map frame in A's with its covariance, :func:`map_frame`; null unless
    the merge is accepted).

    ``b`` is B as merged (resampled to A's cells when ``b_scale`` is given); ``matrix`` maps
    the pixels of B *as read from its file*, so it includes that scale (also given as
    ``b_scale``); non-finite numbers are null.
    """
    doc = result.to_json()
    if b_scale is not None:
        m = np.asarray(result.matrix, dtype=np.float64) @ b_scale
        doc["matrix"] = [[float(v) for v in row] for row in m]
        doc["translation_px"] = [float(m[0, 2]), float(m[1, 2])]
        doc["b_scale"] = float(b_scale[0, 0])
    # resampling keeps B's metric origin: its map frame is the file's.  A rejected merge's
    # matrix is there for diagnosis only: it places no frame (a TF from it would be false)
    doc["map_frame"] = (
        map_frame(
            a, b, np.asarray(result.matrix, dtype=np.float64), np.asarray(result.covariance, float)
        )
        if result.accepted
        else None
    )
    return {k: _finite_or_none(v) for k, v in doc.items()}


def _summary(result: MergeResult, doc: dict) -> str:
    total = doc["timings_ms"].get("total", float("nan"))
    if not result.accepted:
        return f"no overlap: {result.reason} ({total:.0f} ms)" + _rejected_pose(result, doc)
    psi, tx, ty = matrix_to_pose(np.asarray(result.matrix))
    sd = np.sqrt(np.clip(np.diag(np.asarray(result.covariance, dtype=float)), 0, None))
    frame = doc["map_frame"]
    cov = frame["covariance"]
    fsd = np.sqrt(np.clip(np.diag(np.asarray(cov, dtype=float)), 0, None)) if cov else None
    x, y, yaw = (
        f"{frame[k]:.{d}f}" + ("" if fsd is None else f" (+-{fsd[i]:.{d}f})")
        for i, (k, d) in enumerate((("x", 3), ("y", 3), ("yaw", 4)))
    )
    return (
        f"merged: rotation {math.degrees(psi):.2f} deg (+-{math.degrees(sd[2]):.2f}), "
        f"translation ({tx:.1f}, {ty:.1f}) px (+-{sd[0]:.1f}, {sd[1]:.1f}), "
        f"score {result.score:.3f}, {total:.0f} ms; B's map frame in A's: "
        f"x {x} m, y {y} m, yaw {yaw} rad"
    )


def _rejected_pose(result: MergeResult, doc: dict) -> str:
    """A second line for a rejection whose best pose reached the decision: that pose (B as
    read from its file, as ``doc`` gives it), its margin, and whether it is a candidate (a
    margin in the grey zone); empty when no pose reached the decision."""
    if not math.isfinite(result.margin):
        return ""
    tx, ty = doc["translation_px"]
    kind = "candidate pose (margin in the grey zone)" if result.candidate else "best pose"
    return (
        f"\n{kind}, not merged: rotation {doc['rotation_deg']:.2f} deg, translation "
        f"({tx:.1f}, {ty:.1f}) px, margin {result.margin:.2f}"
    )


def _check_output(what: str, path: Path | None) -> None:
    """Refuse an output that cannot be written before the merge runs rather than after it.

    Missing parent directories are created when writing (:func:`pgvd.atomic.atomic_write`), so
    the nearest existing ancestor is the one that must be a writable directory.
    """
    if path is None:
        return
    if path.is_dir():
        raise CliError(f"cannot write {what} {path}: is a directory")
    ancestor = next(p for p in path.parents if p.exists())
    if not ancestor.is_dir():
        raise CliError(f"cannot write {what} {path}: {ancestor} is not a directory")
    if not os.access(ancestor, os.W_OK | os.X_OK):
        raise CliError(f"cannot write {what} {path}: {ancestor} is not writable")


def _check_inputs_kept(args: argparse.Namespace, files: list[Path]) -> None:
    """Refuse ``-o`` or ``--plot`` where they would overwrite an input map: a robot's map
    lost to a typo is not a merge result.

    An input is its file and, for a map_server YAML, the image it names (a YAML that cannot
    be read names none here; reading it reports why).
    """
    inputs = []
    for f in files:
        inputs.append(f)
        if f.suffix.lower() in YAML_SUFFIXES:
            with contextlib.suppress(MapFormatError):
                inputs.append(map_image_path(f))
    outputs = [("-o", t) for t in written_files(args.output)] if args.output else []
    if args.plot is not None:
        outputs.append(("--plot", args.plot))
    for option, target in outputs:
        for f in inputs:
            # realpath, not samefile alone: "new/../a.yaml" does not exist yet, but writing it
            # creates new/ and lands on a.yaml
            same = os.path.realpath(target) == os.path.realpath(f)
            if same or (target.exists() and f.exists() and os.path.samefile(target, f)):
                raise CliError(f"{option} would overwrite the input map file {f}")


def _write(what: str, path: Path, write: Callable[[], None]) -> None:
    try:
        write()
    except OSError as exc:
        raise CliError(f"cannot write {what} {path}: {exc.strerror or exc}") from None


def _prior(args: argparse.Namespace) -> Pose | None:
    """``--prior`` as a pose, None without it; ``CliError`` for a bad one or with more maps."""
    if args.prior is None:
        return None
    if args.more:
        raise CliError("--prior places B in A: two maps, not more")
    try:
        pose = parse_pose(args.prior)
    except ValueError as exc:
        raise CliError(f"--prior: {exc}") from None
    if max(abs(pose[0]), abs(pose[1])) > _MAX_PRIOR_M:
        # farther than any map reaches, and past it the pixel matrix overflows
        raise CliError(f"--prior: B's map frame {_MAX_PRIOR_M:g} m or more away from A's")
    return pose


def _merge_from_prior(
    a: Grid,
    b: Grid,
    prior: Pose,
    params: MergeParams,
    say: Callable[[str], None],
    progress: Callable[[str], None] | None,
) -> MergeResult:
    """The merge checked at B's map frame ``prior`` in A's first (:func:`pgvd.verify.verify`),
    as an agent checks a ``--known-pose``, and searched (:func:`pgvd.merge.merge`) only if the
    check does not confirm it: a wrong prior is neither taken as it stands nor in the way."""
    from agent.priors import prior_matrix
    from pgvd.merge import merge
    from pgvd.verify import verify

    checked = verify(a, b, prior_matrix(a, (0.0, 0.0, 0.0), b, prior), params)
    if checked.accepted:
        say("confirmed at the prior (pgvd.verify); no search")
        return replace(checked, reason="confirmed at the prior")
    say(f"not confirmed at the prior: {checked.reason}; searching")
    # the check's time is part of the work: "prior" beside the search's stages, in the total
    return merge(a, b, params, progress=progress).with_time("prior", checked.timings_ms["total"])


def run(args: argparse.Namespace) -> int:
    if args.output is not None and args.output.suffix.lower() not in _MAP_SUFFIXES:
        raise CliError(f"-o {args.output}: the fused map must end in .yaml, .yml or .npy")
    if args.plot is not None and args.plot.suffix.lower() != ".png":
        raise CliError(f"--plot {args.plot}: the picture is a PNG, its name must end in .png")
    if args.max_cells <= 0:
        raise CliError(f"--max-cells must be > 0, got {args.max_cells}")
    if args.resolution is not None:
        check_resolution_option(args.resolution)
    _check_output("plot", args.plot)
    _check_output("fused map", args.output)
    files = [args.a, args.b, *args.more]
    _check_inputs_kept(args, files)
    if args.resolution is not None and all(f.suffix.lower() in YAML_SUFFIXES for f in files):
        # not an error (the merge is the same), but the user believed it set something
        print(
            f"pgvd merge: note: --resolution {args.resolution:g} is not used: each map's YAML "
            "gives its own cell size",
            file=sys.stderr,
        )
    if args.despeckle and args.more:
        raise CliError("--despeckle merges two maps, not more")
    prior = _prior(args)
    progress = _progress(args)
    say = progress or (lambda line: None)
    if args.more:
        return _run_many(args, say)
    say(f"reading {args.a} and {args.b}")
    a = _read(args.a, args)
    b = _read(args.b, args)
    # imported after the files are read: bad input is refused without loading scipy
    from pgvd.fusion import fuse_maps
    from pgvd.merge import merge
    from pgvd.params import MergeParams
    from pgvd.render import merge_figure
    from pgvd.transform import resample, scale_matrix

    _say_mostly_walls([("map A", a), ("map B", b)])
    b_scale = None
    if not math.isclose(a.resolution, b.resolution, rel_tol=1e-6):
        _check_resampled(args.b, b, a.resolution, args.max_cells)
        say(f"resampling B from {b.resolution} to {a.resolution} m/cell")
        resampled = resample(b, a.resolution)
        b_scale = scale_matrix(b.resolution, a.resolution, b.shape[0], resampled.shape[0])
        b = resampled
    try:
        # the PGVD and edge images (MergeResult.diagnostics) are drawn only by --plot;
        # painting them back at full resolution took 10 ms of a 0.56 s merge at 1000^2
        # cells and 50 ms of 1.4 s at 2000^2 (bench.merge's scaling pair, busy machine)
        from pgvd.speckle import DESPECKLE_RADIUS

        params = MergeParams(
            diagnostics=args.plot is not None,
            speckle_radius=DESPECKLE_RADIUS if args.despeckle else 0.0,
        )
        result = (
            merge(a, b, params, progress=progress)
            if prior is None
            else _merge_from_prior(a, b, prior, params, say, progress)
        )
    except ValueError as exc:
        raise CliError(str(exc)) from None
    doc = report(result, a, b, b_scale)
    if args.json:
        print(json.dumps(doc, allow_nan=False))
    else:
        print(_summary(result, doc))
    if args.plot is not None:
        say(f"drawing {args.plot}")
        _write("plot", args.plot, lambda: write_png(args.plot, merge_figure(a, b, result)))
    if not result.accepted:
        return EXIT_NO_OVERLAP
    if args.output is not None:
        say(f"fusing into {args.output}")
        try:
            fused = fuse_maps(a, b, result.matrix, result.covariance)
        except ValueError as exc:  # e.g. a covariance that is not finite
            raise CliError(f"cannot fuse the maps: {exc}") from None
        _write("fused map", args.output, lambda: write_map(args.output, fused))
    return EXIT_OK


def _run_many(args: argparse.Namespace, say: Callable[[str], None]) -> int:
    """``pgvd merge A B C ...``: :func:`agent.multimerge.merge_many`, the agents' path."""
    files = [args.a, args.b, *args.more]
    say(f"reading {len(files)} maps")
    grids = [_read(f, args) for f in files]
    for f, g in zip(files, grids, strict=True):
        _check_resampled(f, g, grids[0].resolution, args.max_cells)
    _say_mostly_walls([(str(f), g) for f, g in zip(files, grids, strict=True)])
    from agent.multimerge import merge_many
    from pgvd.render import grid_image

    try:
        res = merge_many(grids, progress=say)
    except ValueError as exc:
        raise CliError(str(exc)) from None
    doc = res.report([str(f) for f in files])
    _add_map_frames(doc, res)
    if args.json:
        print(json.dumps(doc, allow_nan=False))
    else:
        print(_many_summary(doc))
    largest = res.largest()
    if args.plot is not None:
        say(f"drawing {args.plot}")
        image = grid_image(largest.grid.probability())
        _write("plot", args.plot, lambda: write_png(args.plot, image))
    if not res.merged:
        return EXIT_NO_OVERLAP
    if args.output is not None:
        say(f"writing the group of {len(largest.members)} maps to {args.output}")
        _write("fused map", args.output, lambda: write_map(args.output, largest.grid))
    return EXIT_OK


def _add_map_frames(doc: dict, res: ManyMerge) -> None:
    """Each map entry's ``map_frame``: its map frame in its group's anchor map's (the group's
    first input), with the covariance of its placement, as :func:`map_frame` gives them for
    two maps (on the maps as registered, where the transforms and covariances are defined)."""
    index = {r: i for i, r in enumerate(res.ids)}
    for comp in res.components:
        anchor = res.frames[index[comp.anchor]]
        for robot in comp.members:
            i = index[robot]
            doc["maps"][i]["map_frame"] = map_frame(
                anchor, res.frames[i], comp.transforms[robot], comp.covariances[robot]
            )


def _many_summary(doc: dict) -> str:
    lines = []
    for i, m in enumerate(doc["maps"]):
        psi, tx, ty = matrix_to_pose(np.asarray(m["matrix"]))
        lines.append(
            f"map {i} {m['file']}: group {m['component']}, rotation {math.degrees(psi):.2f} deg, "
            f"translation ({tx:.1f}, {ty:.1f}) px"
        )
    for ln in doc["links"]:
        verdict = "no overlap"
        if ln["accepted"]:
            verdict = "used" if ln["used"] else "dropped: inconsistent around a cycle"
        lines.append(f"maps {ln['a']}-{ln['b']}: score {ln['score']:.3f}, {verdict}")
    return "\n".join(lines)
