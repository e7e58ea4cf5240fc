"""What a running fleet showed, judged against the truth: placements, wrong spells, delays.

Pure functions on a recorded history, for :mod:`bench.fleet_accuracy`.  A history holds

- *maps*: every distinct global map an agent held, as ``{"t", "agent", "components"}``, each
  component ``{"anchor", "members", "transforms", "used"}`` as the agent's status shows it
  (:func:`agent.status.component_json`: each member's pixels -> the anchor's pixels);
- *progress*: ``{"t", "robot", "cursor", "epochs"}`` whenever a robot's replay cursor or its
  count of registration epochs changed;
- *overlaps*: ``{"t", "pair", "overlap"}``, the true overlap of two robots' maps as their
  segments grow (:func:`agent.evaluate.true_overlap`);
- *links*: ``{"t", "agent", "pair", "state", "margin", "how"}``, every link decision the
  agents logged (:func:`link_events`), to tell the time a decision took from the time its
  global map took to show it.

A robot is *placed* on an agent when it shares a component of that agent's global map with
another robot; its placement is *wrong* when its transform to the anchor is off the truth
by more than the tolerance (:func:`agent.evaluate.link_error`: rotation in degrees, and the
largest displacement of its canvas corners in cells).
"""

from __future__ import annotations

import re
import time
from collections.abc import Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from agent.evaluate import link_error, true_matrix
from agent.trust import IN_MAP
from pgvd.posegraph import components

UNPLACED, RIGHT, WRONG = "unplaced", "right", "wrong"
#: A link decision as an agent logs it (:meth:`agent.links.LinkRecord.logfmt` and the worker's
#: ``how=``, ``seconds=`` and ``book=``), after the log's local time and robot.
LINK_LINE = re.compile(
    r"^(?P<when>\d{4}-\d\d-\d\d \d\d:\d\d:\d\d),(?P<ms>\d{3}) (?P<agent>\S+) INFO "
    r"link pair=(?P<a>[^/\s]+)/(?P<b>\S+) versions=\S+ outcome=(?P<state>\w+) "
    r"margin=(?P<margin>\S+) .* how=(?P<how>[\w ]+?) seconds=\S+(?: book=(?P<book>\w+))?"
)


@dataclass(frozen=True)
class Truth:
    """Each robot's true frame: the run's world metres (log or map image) -> its map's pixels,
    and its canvas shape."""

    world_to_pixel: Mapping[str, np.ndarray]
    shapes: Mapping[str, tuple[int, int]]


@dataclass(frozen=True)
class Tolerance:
    """The largest rotation (degrees) and translation (cells) error of a right placement."""

    deg: float = 2.0
    cells: float = 3.0

    def allows(self, error: tuple[float, float]) -> bool:
        return error[0] <= self.deg and error[1] <= self.cells


def relative_error(
    transforms: Mapping[str, Sequence], a: str, b: str, truth: Truth
) -> tuple[float, float]:
    """``(deg, cells)`` error of where a component puts robot ``b`` relative to robot ``a``.

    Parameters
    ----------
    transforms : each member's pixels -> the anchor's pixels, 3x3.
    a, b : two members of the component.
    truth : the robots' true frames.

    Returns
    -------
    The error of ``inv(T_a) @ T_b`` (b pixel -> a pixel) against the true matrix, measured on
    ``b``'s canvas; with ``a`` the anchor, ``T_a`` is the identity and this is ``b``'s
    placement error.
    """
    estimate = np.linalg.inv(np.asarray(transforms[a], float)) @ np.asarray(transforms[b], float)
    true = true_matrix(truth.world_to_pixel[a], truth.world_to_pixel[b])
    return link_error(estimate, true, truth.shapes[b])


def placements(components: Iterable[Mapping], truth: Truth, tol: Tolerance) -> dict[str, str]:
    """Each robot of a global map: ``"right"``, ``"wrong"`` or ``"unplaced"``.

    A robot alone in its component is unplaced; so is an anchor none of whose members is
    placed right against it (the members carry the wrong placements).
    """
    out: dict[str, str] = {}
    for comp in components:
        members = list(comp["members"])
        for robot in members:
            if len(members) < 2:
                out[robot] = UNPLACED
            elif robot == comp["anchor"]:
                # the anchor is right when any robot placed against it is; a wrong partner
                # is that partner's error, not a second one of the anchor's
                others = [r for r in members if r != robot]
                ok = any(
                    tol.allows(relative_error(comp["transforms"], robot, r, truth)) for r in others
                )
                out[robot] = RIGHT if ok else UNPLACED
            else:
                err = relative_error(comp["transforms"], comp["anchor"], robot, truth)
                out[robot] = RIGHT if tol.allows(err) else WRONG
    return out


def views(maps: Iterable[Mapping]) -> Iterator[tuple[float, dict[str, list]]]:
    """``(t, {agent: components})`` after each recorded map, in time order: what every agent
    showed at that moment (agents not heard from yet are absent)."""
    held: dict[str, list] = {}
    for m in sorted(maps, key=lambda m: m["t"]):
        held[m["agent"]] = m["components"]
        yield m["t"], dict(held)


def wrong_spells(maps: Sequence[Mapping], truth: Truth, tol: Tolerance, end: float) -> list[dict]:
    """Every spell during which an agent showed a robot wrongly placed.

    Returns
    -------
    list of dict
        ``{"agent", "robot", "start", "end", "seconds", "at_end"}``: ``end`` is the time of
        the agent's first later map that no longer places it wrongly, or ``end`` (the run's
        end) with ``at_end`` True if none did.
    """
    open_since: dict[tuple[str, str], float] = {}
    spells = []
    for m in sorted(maps, key=lambda m: m["t"]):
        shown = placements(m["components"], truth, tol)
        for robot, state in shown.items():
            key = (m["agent"], robot)
            if state == WRONG:
                open_since.setdefault(key, m["t"])
        for key in [k for k in open_since if k[0] == m["agent"] and shown.get(k[1]) != WRONG]:
            spells.append(_spell(key, open_since.pop(key), m["t"], False))
    spells += [_spell(key, start, end, True) for key, start in open_since.items()]
    return sorted(spells, key=lambda s: (s["start"], s["agent"], s["robot"]))


def _spell(key: tuple[str, str], start: float, end: float, at_end: bool) -> dict:
    return {
        "agent": key[0],
        "robot": key[1],
        "start": start,
        "end": end,
        "seconds": end - start,
        "at_end": at_end,
    }


def together(components: Iterable[Mapping], a: str, b: str, truth: Truth, tol: Tolerance) -> bool:
    """True when ``a`` and ``b`` share a component that places them rightly to each other."""
    for comp in components:
        if a in comp["members"] and b in comp["members"]:
            return tol.allows(relative_error(comp["transforms"], a, b, truth))
    return False


def placed_together_at(
    maps: Sequence[Mapping], a: str, b: str, truth: Truth, tol: Tolerance
) -> float | None:
    """First time both robots' own agents show ``a`` and ``b`` rightly placed together."""
    for t, held in views(maps):
        if a in held and b in held and all(together(held[g], a, b, truth, tol) for g in (a, b)):
            return t
    return None


def first_reaching(overlaps: Sequence[Mapping], pair: str, threshold: float) -> float | None:
    """First time the true overlap of ``pair`` ("a-b") reached ``threshold``."""
    times = [o["t"] for o in overlaps if o["pair"] == pair and o["overlap"] >= threshold]
    return min(times, default=None)


def value_at(progress: Sequence[Mapping], robot: str, t: float, key: str) -> int:
    """``robot``'s ``key`` ("cursor" or "epochs") last recorded at or before ``t``, else 0."""
    before = [p for p in progress if p["robot"] == robot and p["t"] <= t]
    return int(max(before, key=lambda p: p["t"])[key]) if before else 0


def pair_delays(
    maps: Sequence[Mapping],
    progress: Sequence[Mapping],
    overlaps: Sequence[Mapping],
    truth: Truth,
    tol: Tolerance,
    threshold: float,
    links: Sequence[Mapping] = (),
) -> list[dict]:
    """For each pair whose true overlap reached ``threshold``: how long until placed together.

    Returns
    -------
    list of dict
        ``{"pair", "overlap_at", "placed_at", "seconds", "epochs", "linked_at"}``:
        ``seconds`` is ``placed_at - overlap_at`` (negative when the fleet placed them
        together before the overlap reached the threshold; None if never), ``epochs`` the
        registration epochs both robots began in between (:mod:`agent.links`), negative
        likewise; ``linked_at`` when the ``links`` decided anywhere joined them
        (:func:`linked_at`), None if never or without ``links``.
    """
    out = []
    for pair in sorted({o["pair"] for o in overlaps}):
        start = first_reaching(overlaps, pair, threshold)
        if start is None:
            continue
        a, b = pair.split("-")
        placed = placed_together_at(maps, a, b, truth, tol)
        epochs = None
        if placed is not None:
            epochs = sum(
                value_at(progress, r, placed, "epochs") - value_at(progress, r, start, "epochs")
                for r in (a, b)
            )
        out.append(
            {
                "pair": pair,
                "overlap_at": start,
                "placed_at": placed,
                "seconds": None if placed is None else placed - start,
                "epochs": epochs,
                "linked_at": linked_at(links, a, b),
            }
        )
    return out


def placed_right_at_end(
    maps: Sequence[Mapping], robots: Iterable[str], truth: Truth, tol: Tolerance
) -> dict[str, bool]:
    """Per robot: does every agent's last global map place it right?"""
    last: dict[str, list] = {}
    for _, held in views(maps):
        last = held
    shown = [placements(comps, truth, tol) for comps in last.values()]
    return {r: bool(shown) and all(s.get(r) == RIGHT for s in shown) for r in robots}


def link_events(lines: Iterable[str], t0: float) -> list[dict]:
    """The link decisions of an agent's log lines (:data:`LINK_LINE`; other lines, and
    decisions the agent's book refused as superseded, are skipped: no agent held them), their
    times in seconds since ``t0`` (a POSIX time; the log is in local time)."""
    out = []
    for line in lines:
        m = LINK_LINE.match(line)
        if m is None or m["book"] == "superseded":
            continue
        when = time.mktime(time.strptime(m["when"], "%Y-%m-%d %H:%M:%S")) + int(m["ms"]) / 1e3
        out.append(
            {
                "t": round(when - t0, 3),
                "agent": m["agent"],
                "pair": f"{m['a']}-{m['b']}",
                "state": m["state"],
                "margin": None if m["margin"] == "none" else float(m["margin"]),
                "how": m["how"],
            }
        )
    return out


def linked_at(links: Sequence[Mapping], a: str, b: str) -> float | None:
    """First time the links in the global map, as decided anywhere in the fleet (each pair's
    latest decision standing), joined ``a`` and ``b``: when the fleet had decided them."""
    state: dict[tuple[str, str], bool] = {}
    for ln in sorted(links, key=lambda ln: ln["t"]):
        pair = tuple(ln["pair"].split("-"))
        state[pair] = ln["state"] in IN_MAP  # type: ignore[index]
        robots = {r for p in state for r in p} | {a, b}
        joined = components(robots, [p for p, inside in state.items() if inside])
        if any(a in g and b in g for g in joined):
            return ln["t"]
    return None
