"""The picture ``pgvd demo`` writes: every robot's local map over every agent's global map.

Each panel says whose map it is and what it shows.  On an agent's global map the robots it
placed are dots at the centres of their maps' known cells, joined by the links between them
that the agent holds: solid green where a link was accepted and used, red where the pose
graph rejected an accepted link as inconsistent around a cycle, dashed orange where a link
is only a candidate (tried, not accepted).  The title carries the demo's verdict and why.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw, ImageFont

from pgvd.grid import Grid, relative_matrix
from pgvd.render import grid_image

#: Height of a map panel, pixels: maps are scaled to it, whatever their size.
PANEL = 360
GAP = 8
LABEL = 22
USED = (0, 150, 0)
REJECTED = (210, 0, 0)
CANDIDATE = (230, 130, 0)
LEGEND = (
    "green: accepted link, red: accepted but rejected around a cycle, "
    "dashed orange: candidate; dots: the centres of the robots' maps"
)


@dataclass(frozen=True)
class AgentView:
    """What one agent shows: its robot's local map, its global map and what placed it.

    Attributes
    ----------
    robot : the agent's robot id.
    local : its own local map (None before its first).
    local_label : what the local map is, e.g. the segment of the run it replays.
    global_map : the agent's global map as it wrote it (None before its first).
    status : the agent's last status (``components``, ``global`` and ``links`` are read).
    """

    robot: str
    local: Grid | None
    local_label: str
    global_map: Grid | None
    status: dict | None


def write_side_by_side(
    path: Path, views: Sequence[AgentView], locals_: Mapping[str, Grid], title: Sequence[str]
) -> None:
    """Write the picture: local maps on the top row, each agent's global map below.

    Parameters
    ----------
    path : the PNG to write.
    views : one per agent, in the order of the columns.
    locals_ : every robot's local map, to find where a global map placed its centre.
    title : lines above the panels, the verdict first.
    """
    font = ImageFont.load_default(size=15)
    top = [
        _panel(v.local, f"{v.robot}: local map, {v.local_label}"
               + ("" if v.local is not None else ": none yet"), font)[0]
        for v in views
    ]  # fmt: skip
    bottom = [_global_panel(v, locals_, font) for v in views]
    rows = [_hstack(top), _hstack(bottom)]
    # the verdict in a larger type than what explains it
    lines = [(title[0], ImageFont.load_default(size=24), 2 * LABEL)]
    lines += [(t, font, LABEL) for t in [*title[1:], LEGEND]]
    width = max([r.width for r in rows] + [round(f.getlength(t)) + 2 * GAP for t, f, _ in lines])
    head = sum(h for _, _, h in lines) + GAP
    canvas = Image.new("RGB", (width, head + sum(r.height for r in rows) + GAP), "white")
    draw = ImageDraw.Draw(canvas)
    y = GAP // 2
    for line, f, h in lines:
        draw.text((GAP, y), line, fill="black", font=f)
        y += h
    y = head
    for row in rows:
        canvas.paste(row, (0, y))
        y += row.height + GAP
    canvas.save(path)


def _panel(
    grid: Grid | None, label: str, font: ImageFont.FreeTypeFont
) -> tuple[Image.Image, np.ndarray]:
    """A map cropped to its known cells, scaled to :data:`PANEL` pixels high, its label above;
    gray if there is none.  Also the 3x3 matrix from the map's pixels to the panel's."""
    to_panel = np.eye(3)
    if grid is None:
        img = Image.new("RGB", (PANEL, PANEL), (205, 205, 205))
    else:
        (r0, r1), (c0, c1) = _known_box(grid)
        gray = np.asarray(grid_image(grid.probability()))[r0:r1, c0:c1]
        img = Image.fromarray(gray).convert("RGB")
        scale = PANEL / img.height
        img = img.resize((max(1, round(img.width * scale)), PANEL), Image.NEAREST)
        to_panel = np.array([[scale, 0, -c0 * scale], [0, scale, LABEL - r0 * scale], [0, 0, 1]])
    width = max(img.width, round(font.getlength(label)) + 4)
    out = Image.new("RGB", (width, PANEL + LABEL), "white")
    out.paste(img, (0, LABEL))
    ImageDraw.Draw(out).text((2, 2), label, fill="black", font=font)
    return out, to_panel


def _known_box(grid: Grid, margin: int = 10) -> tuple[tuple[int, int], tuple[int, int]]:
    """Rows and columns ``(start, stop)`` around the known cells (the whole map if none)."""
    known = grid.logodds != 0
    if not known.any():
        return (0, grid.shape[0]), (0, grid.shape[1])
    rows, cols = np.flatnonzero(known.any(axis=1)), np.flatnonzero(known.any(axis=0))
    return (
        (max(0, rows[0] - margin), min(grid.shape[0], rows[-1] + 1 + margin)),
        (max(0, cols[0] - margin), min(grid.shape[1], cols[-1] + 1 + margin)),
    )


def _global_panel(
    view: AgentView, locals_: Mapping[str, Grid], font: ImageFont.FreeTypeFont
) -> Image.Image:
    """An agent's global map with its robots' centres and links drawn on it."""
    glob = (view.status or {}).get("global") or {}
    members = glob.get("members") or []
    label = (
        f"{view.robot}'s global map: {len(members)} robots, anchor {glob.get('anchor')}"
        if view.global_map is not None
        else f"{view.robot}'s global map: none yet"
    )
    panel, to_panel = _panel(view.global_map, label, font)
    if view.global_map is None or view.status is None:
        return panel
    at = {
        r: tuple((to_panel @ [x, y, 1.0])[:2])
        for r, (x, y) in _centres(view.global_map, view.status, locals_).items()
    }
    draw = ImageDraw.Draw(panel)
    for a, b, style in _link_styles(view.status):
        if a in at and b in at:
            _line(draw, at[a], at[b], style)
    for r, (x, y) in at.items():
        draw.ellipse((x - 5, y - 5, x + 5, y + 5), fill=(0, 70, 200))
        draw.text((x + 7, y - 8), r, fill=(0, 70, 200), font=font)
    return panel


def _centres(
    glob: Grid, status: dict, locals_: Mapping[str, Grid]
) -> dict[str, tuple[float, float]]:
    """Where the agent's own component put the centre of each member's known cells, in
    global-map pixels."""
    own = (status.get("global") or {}).get("anchor")
    comp = next((c for c in status.get("components", []) if c["anchor"] == own), None)
    if comp is None or own not in locals_:
        return {}
    # the global map's canvas is the anchor's, grown: anchor pixels -> global pixels
    to_global = relative_matrix(glob, locals_[own])
    out = {}
    for robot, matrix in comp["transforms"].items():
        if robot in locals_ and (known := np.argwhere(locals_[robot].logodds != 0)).size:
            row, col = known.mean(axis=0)
            x, y, _ = to_global @ np.asarray(matrix) @ np.array([col, row, 1.0])
            out[robot] = (float(x), float(y))
    return out


def _link_styles(status: dict) -> list[tuple[str, str, str]]:
    """``(a, b, style)`` per pair of the agent's current links; an accepted link wins."""
    rejected = {tuple(p) for c in status.get("components", []) for p in c.get("rejected", [])}
    styles: dict[tuple[str, str], str] = {}
    for ln in status.get("links", []):
        if not ln.get("current"):
            continue
        pair = (ln["a"], ln["b"])
        if ln["accepted"]:
            styles[pair] = "rejected" if pair in rejected else "used"
        else:
            styles.setdefault(pair, "candidate")
    return [(a, b, s) for (a, b), s in sorted(styles.items())]


def _line(draw: ImageDraw.ImageDraw, p: tuple[float, float], q: tuple[float, float], style: str):
    if style != "candidate":
        draw.line([p, q], fill=USED if style == "used" else REJECTED, width=3)
        return
    n = max(1, int(np.hypot(q[0] - p[0], q[1] - p[1]) // 8))
    for i in range(0, n, 2):
        a, b = i / n, min(1.0, (i + 1) / n)
        draw.line(
            [(p[0] + a * (q[0] - p[0]), p[1] + a * (q[1] - p[1])),
             (p[0] + b * (q[0] - p[0]), p[1] + b * (q[1] - p[1]))],
            fill=CANDIDATE, width=2,
        )  # fmt: skip


def _hstack(panels: Sequence[Image.Image]) -> Image.Image:
    width = sum(p.width for p in panels) + GAP * (len(panels) - 1)
    out = Image.new("RGB", (width, max(p.height for p in panels)), "white")
    x = 0
    for p in panels:
        out.paste(p, (x, 0))
        x += p.width + GAP
    return out
