"""What the candidate rule of :mod:`agent.trust` does with grey-zone pairs as their maps grow
(development logs only).

Every pgvd record of a merge bench run (``bench/results/merge.json``) whose first try lands in
the grey zone and that a development log can grow is replayed: its pair is rendered as the
bench rendered it, each map on a canvas fixed at its first version, then robot B's segment
(and, for a mirror pair, both) grows version by version while the agent's own check
(:func:`agent.worker.verify_check`) re-checks the candidate at its pose and
:func:`agent.trust.recheck_verdict` decides.  It prints each pair's margins and states, and
how many right poses and bad ones (look-alikes, mirrors, wrong poses) ended kept (a
candidate) or dropped: a re-check on a newer version never confirms (a newer epoch's accept
at the same pose does), so what it must do is drop bad poses and keep right ones.

Drifted pairs are left out (their drift model would have to grow too), and so are pairs from
map images (nothing to grow).  Run from the project root::

    python3 -m bench holds
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from agent import trust
from agent.worker import Registration, verify_check
from bench.data.negatives import mirror_scans
from bench.data.pairs import random_frame
from bench.studies.ceiling import read_run
from bench.tables import NEGATIVE, pose_right
from pgvd.carmen import read_carmen
from pgvd.grid import Grid
from pgvd.integrate import frame_for, integrate, select_segment

LOGS = {"intel-log": "intel-corrected.log.gz", "fr079-log": "freiburg-079-corrected.log.gz"}
#: How far B's segment grows at each version: fractions of the log, or scans of a slice.
GROW_FRACTION = (0.02, 0.04, 0.06, 0.08)
GROW_SCANS = (6, 12, 18, 24)


def _segment(spec: list, grow: int) -> tuple[float, float] | slice:
    """A segment of a record's ``info``, its end grown by step ``grow`` (0: as recorded)."""
    kind, start, stop = spec
    if kind == "scans":
        return slice(start, stop + (GROW_SCANS[grow - 1] if grow else 0))
    return (start, min(stop + (GROW_FRACTION[grow - 1] if grow else 0.0), 1.0))


def versions(record: dict, scans: list) -> list[tuple[Grid, Grid]]:
    """The pair's maps at its first version and each grown one, canvases fixed at the first."""
    info = record["info"]
    rng = np.random.default_rng(info["seed"])
    frame_a, frame_b = random_frame(rng), random_frame(rng)
    if info.get("kind") == "mirror":
        parts = [select_segment(scans, _segment(info["seg"], g)) for g in range(5)]
        a_parts, b_parts = parts, [mirror_scans(p) for p in parts]
    else:
        a_parts = [select_segment(scans, _segment(info["seg_a"], 0))] * 5
        b_parts = [select_segment(scans, _segment(info["seg_b"], g)) for g in range(5)]
    canvas_a = frame_for(a_parts[0], info["resolution"], frame_a)
    canvas_b = frame_for(b_parts[0], info["resolution"], frame_b)
    return [
        (integrate(pa, canvas_a), integrate(pb, canvas_b))
        for pa, pb in zip(a_parts, b_parts, strict=True)
    ]


def replay(record: dict, scans: list, bar: float) -> tuple[list[float | None], list[str]]:
    """Margins and states of one grey-zone pair through its versions (module docstring)."""
    from pgvd.merge import merge
    from pgvd.params import MergeParams

    maps = versions(record, scans)
    first = merge(*maps[0], MergeParams(diagnostics=False))
    margins: list[float | None] = [first.margin]
    if first.accepted or not trust.in_grey_zone(first.margin, bar):
        return margins, ["not reproduced"]
    check = verify_check()
    states, pose, held, held_margin = [trust.CANDIDATE], first.matrix, 0, first.margin
    for a, b in maps[1:]:
        res = check(a, b, pose) or Registration(False, pose, np.zeros((3, 3)), 0.0, "left")
        verdict = trust.recheck_verdict(
            held, held_margin, first.margin, res.accepted, res.margin,
            trust.holds(pose, res.matrix, b),
            res.reason,
        )  # fmt: skip
        margins.append(res.margin)
        states.append(verdict.state)
        if verdict.state != trust.CANDIDATE:
            break
        pose, held, held_margin = res.matrix, verdict.holds, res.margin
    return margins, states


def main(argv: list[str] | None = None) -> int:
    from pgvd.params import DecisionParams

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    here = Path(__file__).resolve()
    parser.add_argument("--merge", type=Path, default=here.parents[1] / "results" / "merge.json")
    parser.add_argument("--logs", type=Path, default=here.parents[3] / "shared" / "logs")
    args = parser.parse_args(argv)
    try:
        records = read_run(args.merge, fields=())["records"]
    except ValueError as exc:
        print(f"holds: cannot read records: {exc}", file=sys.stderr)
        return 2
    bar = DecisionParams.min_margin
    chosen = [
        r for r in records
        if r["method"] == "pgvd" and r["source"] in LOGS and r["set"] != "drifted"
        and trust.in_grey_zone(r["result"].get("margin"), bar)
    ]  # fmt: skip
    logs = {s: read_carmen(args.logs / LOGS[s]) for s in sorted({r["source"] for r in chosen})}
    tally: dict[tuple[str, str], int] = {}
    for r in chosen:
        cls = "bad" if r["set"] == NEGATIVE or not pose_right(r) else "right"
        margins, states = replay(r, logs[r["source"]], bar)
        shown = " ".join("none" if m is None or not np.isfinite(m) else f"{m:.2f}" for m in margins)
        print(f"{r['pair']:28s} {cls:5s} margins {shown:32s} -> {' '.join(states)}")
        tally[(cls, states[-1])] = tally.get((cls, states[-1]), 0) + 1
    for (cls, state), n in sorted(tally.items()):
        print(f"{cls} ending {state}: {n}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
