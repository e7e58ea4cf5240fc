"""A wrong link is caught: a keyed fleet member publishes a plausible but false accepted link.

Five agents replay overlapping halves of the Intel log (the building is a loop, so every
pair overlaps and every link lies on several cycles), each in a random frame, keyed.  Once
they agree, ``tests/liar.py`` -- holding the fleet key -- publishes for one pair of the current
epochs an accepted link 3 m and 20 degrees off the truth, with the honest link's covariance
and a better score, under the id ``r0`` that every agent prefers for that key
(:meth:`agent.links.LinkCache.get`).  Every agent must then use it as its link of the pair,
reject it by cycle consistency (the robust pose graph, :mod:`pgvd.posegraph`) and keep every
robot where the truth puts it (:mod:`agent.evaluate`).
"""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from agent.evaluate import link_error, true_matrix
from agent.launcher import ROOT, LocalFleet, agreement, sources_done, wait_for
from agent.links import LinkRecord
from agent.state import StateDir
from pgvd.grid import rigid_matrix

pytestmark = [pytest.mark.fleet, pytest.mark.slow]

INTEL = ROOT / "agent" / "data" / "intel-corrected.log.gz"
SEGMENTS = {
    "r1": "0.0-0.5",
    "r2": "0.12-0.62",
    "r3": "0.25-0.75",
    "r4": "0.38-0.88",
    "r5": "0.5-1.0",
}
FRAMES = {"r1": "3,-4,20", "r2": "-7,2,135", "r3": "5,9,250", "r4": "-3,6,60", "r5": "-2,-9,310"}
KEY = b"wrong-link-test-key"
#: The lie: B's map turned by this about its centre and moved this far (metres) in A.
LIE_DEG, LIE_M = 20.0, 3.0


def _agreed(fleet: LocalFleet) -> bool:
    dead = [r for r, a in fleet.agents.items() if not a.alive()]
    assert not dead, f"agents died: {dead}"
    st = fleet.statuses()
    return sources_done(st) and agreement(st, {r: s["own_version"] for r, s in st.items() if s})


def _cycles_through(used: list[list[str]], a: str, b: str) -> int:
    """Triangles the link (a, b) closes with the other used links."""
    nb: dict[str, set[str]] = {}
    for x, y in used:
        nb.setdefault(x, set()).add(y)
        nb.setdefault(y, set()).add(x)
    return len((nb.get(a, set()) & nb.get(b, set())) - {a, b})


def _placement_errors(status: dict, w2p: dict, shapes: dict) -> dict[str, tuple[float, float]]:
    """Per robot of the largest component: (deg, cells) of its placement against the truth."""
    comp = max(status["components"], key=lambda c: len(c["members"]))
    anchor = comp["anchor"]
    return {
        r: link_error(np.array(m), true_matrix(w2p[anchor], w2p[r]), shapes[r])
        for r, m in comp["transforms"].items()
    }


def _lie(honest: dict, shape_b: tuple[int, int], resolution: float) -> LinkRecord:
    """The honest link of a pair, turned and shifted about B's centre in A, from ``r0``, as a
    re-decision of it (one revision later), so that it supersedes a link the fleet confirmed."""
    m = np.array(honest["matrix"])
    h, w = shape_b
    centre = (m @ np.array([(w - 1) / 2.0, (h - 1) / 2.0, 1.0]))[:2]
    off = rigid_matrix(np.radians(LIE_DEG), 0.0, 0.0)
    off[:2, 2] = centre - off[:2, :2] @ centre + np.array([LIE_M / resolution, 0.0])
    return LinkRecord(
        honest["a"], honest["version_a"], honest["b"], honest["version_b"], True,
        off @ m, np.array(honest["covariance"]), 0.99, "r0", revision=honest["revision"] + 1,
    )  # fmt: skip


@pytest.fixture(scope="module")
def attacked(tmp_path_factory: pytest.TempPathFactory) -> dict:
    work = tmp_path_factory.mktemp("wronglink")
    key_file = work / "fleet.key"
    key_file.write_bytes(KEY + b"\n")
    out: dict = {}
    common = ["--speed", "400", "--link-timeout", "3", "--key-file", str(key_file)]
    with LocalFleet("wl", work, common) as fleet:
        for robot, seg in SEGMENTS.items():
            fleet.add(robot, f"carmen:{INTEL}@{seg}", [f"--frame={FRAMES[robot]}"])
        assert wait_for(lambda: _agreed(fleet), 240), "the fleet did not agree before the attack"
        before = fleet.statuses()
        grids = {r: StateDir(a.state_dir).load_maps()[0][r].grid for r, a in fleet.agents.items()}
        w2p = {r: np.array(s["source"]["world_to_pixel"]) for r, s in before.items()}
        shapes = {r: g.shape for r, g in grids.items()}
        comp = max(before["r1"]["components"], key=lambda c: len(c["members"]))
        pair = max(
            (tuple(p) for p in comp["used"]), key=lambda p: (_cycles_through(comp["used"], *p), p)
        )
        honest = next(
            ln for ln in before["r1"]["links"] if (ln["a"], ln["b"]) == pair and ln["current"]
        )
        record = next(
            r
            for r in StateDir(fleet.agents["r1"].state_dir).load_links()[0]
            if r.pair == pair and r.decided_by == honest["decided_by"]
            and (r.version_a, r.version_b) == (honest["version_a"], honest["version_b"])
        )  # fmt: skip
        honest["covariance"], honest["revision"] = record.covariance.tolist(), record.revision
        lie = _lie(honest, shapes[pair[1]], grids[pair[1]].resolution)
        liar = [sys.executable, "tests/liar.py", "--fleet", "wl", "--key-file", str(key_file)]
        for a in fleet.agents.values():
            liar += ["--connect", a.endpoint]
        res = subprocess.run(
            liar, input=json.dumps(lie.to_json()), cwd=ROOT, capture_output=True, text=True,
            timeout=60,
        )  # fmt: skip
        assert res.returncode == 0 and "done" in res.stdout, res.stderr[-2000:]

        def lie_used_and_agreed() -> bool:
            st = fleet.statuses()
            return _agreed(fleet) and all(
                any((ln["a"], ln["b"]) == pair and ln["decided_by"] == "r0" for ln in s["links"])
                for s in st.values()
            )

        out["caught_up"] = wait_for(lie_used_and_agreed, 60)
        out["after"] = fleet.statuses()
    out["resolution"] = grids[pair[1]].resolution
    out.update(before=before, w2p=w2p, shapes=shapes, pair=pair, lie=lie, used=comp["used"])
    out["lie_error"] = link_error(
        lie.matrix, true_matrix(w2p[pair[0]], w2p[pair[1]]), shapes[pair[1]]
    )
    out["honest_error"] = link_error(
        np.array(honest["matrix"]), true_matrix(w2p[pair[0]], w2p[pair[1]]), shapes[pair[1]]
    )
    return out


def test_the_lie_is_plausible_and_on_several_cycles(attacked: dict) -> None:
    a, b = attacked["pair"]
    assert _cycles_through(attacked["used"], a, b) >= 2, (attacked["pair"], attacked["used"])
    deg, _ = attacked["lie_error"]
    assert 10.0 <= deg <= 30.0
    h, w = attacked["shapes"][b]
    lie, truth = attacked["lie"].matrix, true_matrix(attacked["w2p"][a], attacked["w2p"][b])
    centre = np.array([(w - 1) / 2.0, (h - 1) / 2.0, 1.0])
    metres = np.hypot(*((lie - truth) @ centre)[:2]) * attacked["resolution"]
    assert 2.0 <= metres <= 5.0, metres
    hdeg, hcells = attacked["honest_error"]
    print(f"\nlie on {attacked['pair']}: {deg:.1f} deg, {metres:.2f} m off at B's centre")
    print(f"honest link of the pair: {hdeg:.2f} deg, {hcells:.1f} cells off")


def test_every_agent_uses_the_lie_and_rejects_it_by_cycles(attacked: dict) -> None:
    assert attacked["caught_up"], "the agents did not all take up the false link and agree"
    pair = list(attacked["pair"])
    for robot, s in attacked["after"].items():
        comp = max(s["components"], key=lambda c: len(c["members"]))
        assert pair in comp["rejected"] and pair not in comp["used"], (robot, comp)
        assert len(comp["members"]) == len(attacked["before"][robot]["global"]["members"])


def test_every_robot_stays_where_the_truth_puts_it(attacked: dict) -> None:
    w2p, shapes = attacked["w2p"], attacked["shapes"]
    for robot, s in attacked["after"].items():
        before = _placement_errors(attacked["before"][robot], w2p, shapes)
        after = _placement_errors(s, w2p, shapes)
        for r, (deg, cells) in after.items():
            assert deg <= 1.0 and cells <= before[r][1] + 3.0, (robot, r, before[r], (deg, cells))
    worst = max(
        c for s in attacked["after"].values() for _, c in _placement_errors(s, w2p, shapes).values()
    )
    print(f"\nworst placement after the lie: {worst:.1f} cells (canvas corners)")
    digests = {s["global"]["digest"] for s in attacked["after"].values()}
    assert len(digests) == 1
