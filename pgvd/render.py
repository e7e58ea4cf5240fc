"""Pictures of maps and merges as RGB ``uint8`` arrays (write them with :func:`pgvd.io.write_png`).

Pure functions, no plotting library: a person looks at the overlay of A and
the transformed B, at both PGVDs (24) and at the matched edge pair (Sec. IV-E).
"""

from __future__ import annotations

from typing import Protocol

import numpy as np
from scipy import ndimage

from pgvd.grid import Grid
from pgvd.map_shades import FREE_THRESH, OCCUPIED_THRESH
from pgvd.transform import union_canvas, warp

#: Colours (RGB) of the overlay classes.
A_WALL = (30, 90, 230)  # blue
B_WALL = (245, 130, 20)  # orange
BOTH_WALL = (40, 40, 40)  # dark: A and B agree on a wall
EDGE = (0, 190, 60)  # green: the matched edge pair
SEPARATOR = (90, 90, 90)
#: PGVD colour ramp, low -> high probability (pale yellow, orange, red, deep purple).
_RAMP = np.array([[255, 230, 120], [250, 150, 40], [215, 40, 40], [90, 10, 110]], np.float64)
#: Below this PGVD probability the map shows through.
_SP_VISIBLE = 0.05
#: Larger canvases than this many cells are not overlaid (a wild rejected candidate).
_MAX_CANVAS = 4000 * 4000


class _Diagnostics(Protocol):
    pgvd_a: np.ndarray
    pgvd_b: np.ndarray
    edges_a: np.ndarray
    edges_b: np.ndarray


class _Result(Protocol):
    accepted: bool
    matrix: np.ndarray
    rotation_deg: float
    translation_px: tuple[float, float]
    score: float
    reason: str
    diagnostics: _Diagnostics | None


def grid_image(prob: np.ndarray) -> np.ndarray:
    """Gray map: white free, black occupied, mid-gray unknown (``255 (1 - p)``)."""
    p = np.clip(np.nan_to_num(np.asarray(prob, dtype=np.float64), nan=0.5), 0.0, 1.0)
    g = np.rint(255.0 * (1.0 - p)).astype(np.uint8)
    return np.repeat(g[..., None], 3, axis=2)


def _paint(img: np.ndarray, mask: np.ndarray, colour: tuple[int, int, int]) -> None:
    img[mask] = colour


def overlay(a_prob: np.ndarray, b_prob_in_a_frame: np.ndarray) -> np.ndarray:
    """A and the transformed B in one picture.

    Free in either map is white, unknown in both light gray; walls of A only
    are blue, of B only orange, of both dark gray -- so a good merge shows
    dark walls with little blue or orange beside them.
    """
    pa = np.asarray(a_prob)
    pb = np.asarray(b_prob_in_a_frame)
    if pa.shape != pb.shape:
        raise ValueError(f"overlay needs equal shapes, got {pa.shape} and {pb.shape}")
    img = np.full((*pa.shape, 3), 200, dtype=np.uint8)
    _paint(img, (pa < FREE_THRESH) | (pb < FREE_THRESH), (255, 255, 255))
    wa, wb = pa > OCCUPIED_THRESH, pb > OCCUPIED_THRESH
    _paint(img, wa & ~wb, A_WALL)
    _paint(img, wb & ~wa, B_WALL)
    _paint(img, wa & wb, BOTH_WALL)
    return img


def pgvd_image(prob: np.ndarray, sp: np.ndarray, edges: np.ndarray | None = None) -> np.ndarray:
    """The PGVD (24) in a colour ramp over a faded map; ``edges`` (bool) in green.

    Parameters
    ----------
    prob : (H, W) occupancy probabilities.
    sp : (H, W) PGVD probabilities in [0, 1].
    edges : optional (H, W) bool mask of matched edges, drawn one cell wider.
    """
    base = grid_image(prob).astype(np.float64)
    img = 255.0 - 0.45 * (255.0 - base)  # fade the map so the PGVD stands out
    s = np.clip(np.nan_to_num(np.asarray(sp, dtype=np.float64)), 0.0, 1.0)
    if s.shape != img.shape[:2]:
        raise ValueError(f"pgvd shape {s.shape} differs from the map's {img.shape[:2]}")
    show = s > _SP_VISIBLE
    pos = s[show] * (len(_RAMP) - 1)
    i = np.minimum(pos.astype(int), len(_RAMP) - 2)
    f = (pos - i)[:, None]
    img[show] = _RAMP[i] * (1 - f) + _RAMP[i + 1] * f
    out = np.rint(img).astype(np.uint8)
    if edges is not None:
        _paint(out, ndimage.binary_dilation(np.asarray(edges, dtype=bool)), EDGE)
    return out


def _caption(width: int, text: str) -> np.ndarray:
    """A white strip with one line of black text (Pillow's built-in bitmap font)."""
    from PIL import Image, ImageDraw

    strip = Image.new("RGB", (width, 16), (255, 255, 255))
    ImageDraw.Draw(strip).text((4, 2), text, fill=(0, 0, 0))
    return np.asarray(strip)


def _side_by_side(panels: list[np.ndarray]) -> np.ndarray:
    h = max(p.shape[0] for p in panels)
    cols: list[np.ndarray] = []
    for i, p in enumerate(panels):
        if i:
            cols.append(np.full((h, 1, 3), SEPARATOR, np.uint8))
        pad = np.full((h, p.shape[1], 3), 255, np.uint8)
        pad[: p.shape[0]] = p
        cols.append(pad)
    return np.hstack(cols)


def _wall_box(*probs: np.ndarray, margin: int = 20) -> tuple[slice, slice]:
    """Rows and columns around the walls of the maps, ignoring the 0.1 % outermost wall
    cells on each side (stray hits of long rays), plus a margin."""
    walls = np.logical_or.reduce([p > OCCUPIED_THRESH for p in probs])
    rows, cols = np.nonzero(walls)
    if rows.size == 0:
        return slice(None), slice(None)
    h, w = walls.shape
    (r0, r1), (c0, c1) = (np.quantile(v, [0.001, 0.999]).astype(int) for v in (rows, cols))
    return (
        slice(max(r0 - margin, 0), min(r1 + margin + 1, h)),
        slice(max(c0 - margin, 0), min(c1 + margin + 1, w)),
    )


def merge_figure(a: Grid, b: Grid, result: _Result, crop: bool = True) -> np.ndarray:
    """Overlay | PGVD of A | PGVD of B warped, on one canvas holding both maps, captioned.

    ``result`` is a :class:`pgvd.result.MergeResult` (matrix B px -> A px,
    diagnostics with ``pgvd_a``/``edges_a`` in A's frame and
    ``pgvd_b``/``edges_b`` in B's).  A rejected result is drawn with its
    best candidate transform when it has one, so a person sees why it failed.
    With ``crop`` the canvas is cut to the walls of both maps (plus a margin).

    Parameters
    ----------
    a, b : Grid
        The two maps.
    result : MergeResult
        What :func:`pgvd.merge.merge` returned for them.
    crop : bool, optional
        Cut the canvas to the walls.

    Returns
    -------
    numpy.ndarray
        (H, W, 3) uint8 RGB picture with a caption line.

    References
    ----------
    .. [1] Saeedi, S., Paull, L., Trentini, M., Seto, M., and Li, H., "Map merging
       using probabilistic generalized Voronoi diagrams", IROS 2012, Figs. 2 and 4.
    """
    pa, pb = a.probability(), b.probability()
    m = np.asarray(result.matrix, dtype=np.float64)
    diag = result.diagnostics
    if result.accepted:
        psi, (tx, ty) = result.rotation_deg, result.translation_px
        text = f"accepted: rotation {psi:.2f} deg, translation ({tx:.1f}, {ty:.1f}) px"
        text += f", score {result.score:.3f} | A blue, B orange, both dark, matched edges green"
    else:
        text = f"REJECTED: {result.reason}"
    # pgvd.merge reports a rejection without any candidate as the identity with score 0
    no_candidate = not result.accepted and result.score == 0.0 and np.array_equal(m, np.eye(3))
    shape, offset = (None, None)
    if np.isfinite(m).all() and not no_candidate:
        shape, offset = union_canvas(a.shape, b.shape, m)
    if shape is None or shape[0] * shape[1] > _MAX_CANVAS:
        # no usable transform: the two maps and their PGVDs side by side, untransformed
        panels = [grid_image(pa), grid_image(pb)]
        if diag is not None:
            panels += [
                pgvd_image(pa, diag.pgvd_a, diag.edges_a),
                pgvd_image(pb, diag.pgvd_b, diag.edges_b),
            ]
        body = _side_by_side(panels)
        return np.vstack([_caption(body.shape[1], text), body])
    to_canvas_b = offset @ m
    a_on = warp(pa, offset, shape, order=0, cval=0.5)
    b_on = warp(pb, to_canvas_b, shape, order=0, cval=0.5)
    box = _wall_box(a_on, b_on) if crop else (slice(None), slice(None))
    panels = [overlay(a_on[box], b_on[box])]
    if diag is not None:
        sp_a = warp(diag.pgvd_a, offset, shape, order=0)[box]
        sp_b = warp(diag.pgvd_b, to_canvas_b, shape, order=0)[box]
        e_a = warp(diag.edges_a.astype(np.float32), offset, shape, order=0)[box] > 0.5
        e_b = warp(diag.edges_b.astype(np.float32), to_canvas_b, shape, order=0)[box] > 0.5
        panels += [pgvd_image(a_on[box], sp_a, e_a), pgvd_image(b_on[box], sp_b, e_b)]
    else:
        panels += [grid_image(a_on[box]), grid_image(b_on[box])]
    body = _side_by_side(panels)
    return np.vstack([_caption(body.shape[1], text), body])
