"""The picture ``pgvd demo`` writes: every robot's local map over every agent's global map.

Each panel says whose map it is and what it shows.  On an agent's global map the robots it
placed are dots at the centres of their maps' known cells, joined by the links of the current
epochs between them that the agent holds, drawn by their lifecycle state (:mod:`agent.trust`)
in the colours of the RViz markers (:mod:`agent.linkmarks`): solid green where a link was
accepted, the same with a purple diamond where a candidate was confirmed, red where the pose
graph dropped an accepted or confirmed link as inconsistent around a cycle, dashed orange
for a candidate (kept out of the map), dotted grey for a withdrawn link; a rejected link is
not drawn.  A status of before the lifecycle (no ``state``) is drawn by ``accepted``: true as
accepted, false as a candidate.  The title carries the demo's verdict and why.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw, ImageFont

from agent import trust
from agent.linkmarks import COLOURS, known_centre
from pgvd.grid import Grid, relative_matrix
from pgvd.render import grid_image

#: Height of a map panel, pixels: maps are scaled to it, whatever their size.
PANEL = 360
GAP = 8
LABEL = 22
#: A link of the map that the pose graph dropped around a cycle.
CYCLE_DROPPED = (210, 0, 0)
#: The lines under the title that say what the drawing means.
LEGEND = (
    "links: green accepted, green with a purple diamond confirmed, red dropped around a cycle,",
    "dashed orange candidate, dotted grey withdrawn (rejected: not drawn); "
    "dots: the robots' map centres",
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
    lines += [(t, font, LABEL) for t in [*title[1:], *LEGEND]]
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
        centre = known_centre(locals_[robot]) if robot in locals_ else None
        if centre is not None:
            x, y, _ = to_global @ np.asarray(matrix) @ np.append(centre, 1.0)
            out[robot] = (float(x), float(y))
    return out


def link_state(link: dict) -> str:
    """A status link's lifecycle state; by ``accepted`` for an agent of before the lifecycle."""
    return link.get("state") or (trust.ACCEPTED if link["accepted"] else trust.CANDIDATE)


def _link_styles(status: dict) -> list[tuple[str, str, str]]:
    """``(a, b, style)`` per pair of the agent's current links, ``style`` a drawn state or
    ``cycle`` (in the map's links, dropped around a cycle); a link in the map wins."""
    dropped = {tuple(p) for c in status.get("components", []) for p in c.get("rejected", [])}
    styles: dict[tuple[str, str], str] = {}
    for ln in status.get("links", []):
        state = link_state(ln)
        if not ln.get("current") or state not in COLOURS:
            continue
        pair = (ln["a"], ln["b"])
        if state in trust.IN_MAP:
            styles[pair] = "cycle" if pair in dropped else state
        else:
            styles.setdefault(pair, state)
    return [(a, b, s) for (a, b), s in sorted(styles.items())]


def _line(draw: ImageDraw.ImageDraw, p: tuple[float, float], q: tuple[float, float], style: str):
    if style == trust.CANDIDATE:
        _broken(draw, p, q, COLOURS[style], dash=8.0, gap=8.0)
    elif style == trust.WITHDRAWN:
        _broken(draw, p, q, COLOURS[style], dash=3.0, gap=5.0, width=3)
    else:
        solid = CYCLE_DROPPED if style == "cycle" else COLOURS[trust.ACCEPTED]
        draw.line([p, q], fill=solid, width=3)
    if style == trust.CONFIRMED:
        x, y = (p[0] + q[0]) / 2, (p[1] + q[1]) / 2
        draw.polygon([(x, y - 7), (x + 7, y), (x, y + 7), (x - 7, y)], fill=COLOURS[style])


def _broken(
    draw: ImageDraw.ImageDraw,
    p: tuple[float, float],
    q: tuple[float, float],
    fill: tuple[int, int, int],
    dash: float,
    gap: float,
    width: int = 2,
) -> None:
    """A line from ``p`` to ``q`` drawn as dashes of ``dash`` pixels ``gap`` apart."""
    length = float(np.hypot(q[0] - p[0], q[1] - p[1]))
    for start in np.arange(0.0, length, dash + gap):
        a, b = start / length, min(length, start + dash) / length
        draw.line(
            [(p[0] + a * (q[0] - p[0]), p[1] + a * (q[1] - p[1])),
             (p[0] + b * (q[0] - p[0]), p[1] + b * (q[1] - p[1]))],
            fill=fill, width=width,
        )  # fmt: skip


def _hstack(panels: Sequence[Image.Image]) -> Image.Image:
    width = sum(p.width for p in panels) + GAP * (len(panels) - 1)
    out = Image.new("RGB", (width, max(p.height for p in panels)), "white")
    x = 0
    for p in panels:
        out.paste(p, (x, 0))
        x += p.width + GAP
    return out
