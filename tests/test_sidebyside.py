"""The demo picture draws each link by its lifecycle state, on real maps placed by their true
transform, and still draws a status of an agent of before the lifecycle (no ``state``)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from agent import trust
from agent.linkmarks import COLOURS
from agent.sidebyside import CYCLE_DROPPED, LEGEND, AgentView, write_side_by_side
from pgvd.io import read_map

ROOT = Path(__file__).resolve().parents[1]


def _link(a: str, b: str, state: str | None, current: bool = True) -> dict:
    link = {"a": a, "b": b, "accepted": state in trust.IN_MAP, "current": current}
    if state is not None:
        link["state"] = state
    return link


def _status(links: list[dict], dropped: tuple[tuple[str, str], ...] = ()) -> dict:
    """Robots a (intel A), b (intel B at its true pose) and c (A shifted), anchored at a."""
    truth = json.loads((ROOT / "examples" / "truth.json").read_text())["matrix"]
    shift = [[1.0, 0.0, 120.0], [0.0, 1.0, 90.0], [0.0, 0.0, 1.0]]
    return {
        "global": {"anchor": "a", "members": ["a", "b", "c"]},
        "components": [
            {
                "anchor": "a",
                "members": ["a", "b", "c"],
                "transforms": {"a": np.eye(3).tolist(), "b": truth, "c": shift},
                "rejected": [list(p) for p in dropped],
            }
        ],
        "links": links,
    }


def _colours(tmp_path: Path, status: dict) -> set[tuple[int, int, int]]:
    """The colours the links add to the picture: it drawn with ``status``'s links and
    without them, compared pixel by pixel."""
    a, b = (read_map(ROOT / "examples" / f"intel_{m}.yaml") for m in "ab")
    locals_ = {"a": a, "b": b, "c": a}
    pictures = []
    for links in (status["links"], []):
        view = AgentView("a", a, "whole run", a, {**status, "links": links})
        path = tmp_path / f"{len(pictures)}.png"
        write_side_by_side(path, [view], locals_, ["PASSED", "test"])
        pictures.append(np.asarray(Image.open(path).convert("RGB")))
    drawn, bare = pictures
    changed = (drawn != bare).any(axis=2)
    return {tuple(int(v) for v in px) for px in drawn[changed]}


def test_each_state_is_drawn_in_its_colour_and_rejected_links_are_not(tmp_path: Path) -> None:
    status = _status(
        [
            _link("a", "b", trust.CONFIRMED),
            _link("a", "c", trust.CANDIDATE),
            _link("b", "c", trust.WITHDRAWN),
        ]
    )
    colours = _colours(tmp_path, status)
    for state in (trust.ACCEPTED, trust.CONFIRMED, trust.CANDIDATE, trust.WITHDRAWN):
        # confirmed: the accepted green line, marked with a diamond of its own colour
        assert COLOURS[state] in colours, state
    assert CYCLE_DROPPED not in colours
    rejected = _status([_link("a", "b", trust.REJECTED), _link("a", "c", trust.ACCEPTED, False)])
    assert _colours(tmp_path, rejected) == set()  # rejected, or of an older epoch: not drawn


def test_a_link_the_pose_graph_dropped_is_red(tmp_path: Path) -> None:
    status = _status([_link("a", "b", trust.ACCEPTED)], dropped=(("a", "b"),))
    colours = _colours(tmp_path, status)
    assert CYCLE_DROPPED in colours and COLOURS[trust.ACCEPTED] not in colours


def test_a_status_without_states_is_drawn_by_accepted(tmp_path: Path) -> None:
    """An agent of before the lifecycle: accepted true is an accepted link, false a candidate."""
    status = _status([_link("a", "b", None), _link("a", "c", None)])
    status["links"][0]["accepted"] = True
    colours = _colours(tmp_path, status)
    assert COLOURS[trust.ACCEPTED] in colours and COLOURS[trust.CANDIDATE] in colours
    assert COLOURS[trust.CONFIRMED] not in colours and COLOURS[trust.WITHDRAWN] not in colours


@pytest.mark.parametrize("word", ["accepted", "confirmed", "candidate", "withdrawn", "rejected"])
def test_the_legend_names_every_state(word: str) -> None:
    assert word in " ".join(LEGEND)
