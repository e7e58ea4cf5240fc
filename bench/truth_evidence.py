"""The decision's evidence at the true pose: which pairs any threshold on it could accept.

The merge accepts its winner when the margin over the best rival
(:mod:`pgvd.decision`) reaches ``MergeParams.min_margin``.  Here every
overlapping pair of the development bench is scored at its *true* pose, as
the merge scores a winner: on the decision's maps
(:func:`bench.redecide.decision_maps`), each few-metre square of the overlap
re-aligned for drift first (:func:`pgvd.merge.score_hypothesis`), against no
rival at all (evidence 0, :func:`pgvd.decision.margin_against`).  Not only the
truth itself: every pose of a grid around it (:func:`around`) and the merge's
last refinement from it (:func:`pgvd.merge.final_refinement`) that the bench
still counts right (:func:`bench.merge.evaluate`), and the best of them is
taken.  That is the most this statistic gives the pair at a right pose,
whoever proposes it, up to the grid's steps: a rival only lowers it.

A pair whose true pose scores below the threshold is rejected by every
decision that keeps the statistic and the threshold.  The threshold stands
above the margins of the wrong and negative winners of a bench run (a
mirror image of a building scores like an overlap): lowering it to the
largest of them accepts that winner.  So the shares of pairs at or above
the threshold, and above that largest bad margin, bound the success of the
merge's decision, whatever its search finds (:mod:`bench.ceiling` bounds it
by what the searches find).

    python3 -m bench.truth_evidence bench/results/merge.json [--png OUT.png] [--out OUT.md]

``--held-out`` measures the pairs the bench cuts from the logs kept to evaluate the
merge (``python3 -m bench.merge --held-out``; give that run's ``merge.json``); the
report goes to ``bench/results/held-out/truth-evidence.md``.  Nothing is set from it.
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from bench.ceiling import groups
from bench.merge import CACHE, HELD_OUT, RESULTS, evaluate
from bench.pairs import MapPair
from bench.redecide import decision_maps
from bench.report import frac, pose_right
from bench.sets import FULL, Entry, build
from bench.sources import SOURCES, held_out_logs
from pgvd.decision import margin_against
from pgvd.merge import MergeParams, final_refinement, score_hypothesis
from pgvd.pooling import decision_pool, from_pooled, to_pooled

#: Heading offsets (degrees) and shifts (cells of the decision's maps) of :func:`around`:
#: 5 x 5 x 5 poses, within the bench's success bounds (2 degrees, 3 cells and more) near
#: B's walls.
HEADING_STEPS = (-1.0, -0.5, 0.0, 0.5, 1.0)
SHIFT_STEPS = (-2.0, -1.0, 0.0, 1.0, 2.0)


def around(matrix: np.ndarray, centre: np.ndarray) -> list[np.ndarray]:
    """The pose ``matrix`` (B->A pixels) turned about ``centre`` (a point of B, ``(x, y)``)
    by each of :data:`HEADING_STEPS` and shifted by each pair of :data:`SHIFT_STEPS`."""
    x, y = (matrix @ np.array([centre[0], centre[1], 1.0]))[:2]
    out = []
    for deg in HEADING_STEPS:
        c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
        # turned about B's centre as it lands in A, so the turn moves B's walls least
        turn = np.array([[c, -s, x - c * x + s * y], [s, c, y - s * x - c * y], [0, 0, 1.0]])
        for dx in SHIFT_STEPS:
            for dy in SHIFT_STEPS:
                m = turn @ matrix
                m[:2, 2] += (dx, dy)
                out.append(m)
    return out


def truth_margin(pair: MapPair, params: MergeParams) -> float:
    """The best margin with no rival of a right pose of ``pair`` near its truth.

    The poses tried are the truth's neighbourhood (:func:`around`, about B's wall
    centroid) and the merge's last refinement from the truth; those the bench counts
    right are scored (:func:`pgvd.merge.score_hypothesis`).

    Parameters
    ----------
    pair : MapPair
        An overlapping pair (its ``truth`` set).
    params : MergeParams
        The decision's parameters.

    Returns
    -------
    float
        ``(E - 0) / n - margin_noise / sqrt(n)`` of :func:`pgvd.decision.margin_against`,
        the largest over the right poses tried (the truth itself is one of them).
    """
    fine_a, fine_b = decision_maps(pair.a, pair.b, params)
    pool = decision_pool(pair.a.resolution)
    res = pair.a.resolution * pool
    truth = to_pooled(np.asarray(pair.truth, dtype=float), pool)
    poses = around(truth, fine_b.walls.mean(axis=0))
    poses.append(final_refinement(truth, fine_a, fine_b, params))
    right = [m for m in poses if evaluate(pair, True, from_pooled(m, pool))["success"]]
    return max(
        margin_against(
            score_hypothesis(m, fine_a, fine_b, params, res),
            -np.inf,
            params.disagreement_weight,
            params.margin_noise,
        )
        for m in right
    )


def measure(entries: list[Entry], params: MergeParams) -> list[dict]:
    """:func:`truth_margin` of every overlapping pair, one row each (``pair``, ``set``,
    ``source``, ``overlap``, ``margin``), with a progress line per pair on stderr."""
    out = []
    overlapping = [e for e in entries if e.pair.truth is not None and e.pair.overlap > 0]
    for i, e in enumerate(overlapping, 1):
        m = truth_margin(e.pair, params)
        out.append(
            {
                "pair": e.pair.name,
                "set": e.set,
                "source": e.source,
                "overlap": e.pair.overlap,
                "margin": m,
            }
        )
        print(f"[{i}/{len(overlapping)}] {e.pair.name}: {m:.2f}", file=sys.stderr, flush=True)
    return out


def bad_margins(records: list[dict], method: str) -> list[tuple[str, float]]:
    """``(pair, margin)`` of every winner of ``method`` in a run that is wrong or on a
    negative pair, accepted or not (records without a margin had no winner)."""
    out = []
    for r in records:
        margin = (r.get("result") or {}).get("margin")
        if r["method"] != method or margin is None:
            continue
        has_pose = r["heading_deg"] is not None and r["cell_err"] is not None
        if r["set"] == "negative" or not (has_pose and pose_right(r)):
            out.append((r["pair"], float(margin)))
    return out


@dataclass(frozen=True)
class Reach:
    """One group's pairs, the run's successes, and how many true poses reach the threshold
    and the largest bad margin, against the target share."""

    group: str
    pairs: int
    success: int
    at_threshold: int
    above_worst: int
    target: float

    @property
    def reaches(self) -> bool:
        """Whether the pairs above the largest bad margin reach the target."""
        return self.above_worst >= self.target * self.pairs


def reach(
    rows: list[dict], success: dict[str, bool], threshold: float, worst: float
) -> list[Reach]:
    """:class:`Reach` per group of :func:`bench.ceiling.groups`; ``success`` maps a pair
    to whether the run accepted it right."""
    out = []
    for name, target, member in groups(rows):
        mine = [r for r in rows if member(r)]
        if mine:
            out.append(
                Reach(
                    group=name,
                    pairs=len(mine),
                    success=sum(success.get(r["pair"], False) for r in mine),
                    at_threshold=sum(r["margin"] >= threshold for r in mine),
                    above_worst=sum(r["margin"] > worst for r in mine),
                    target=target,
                )
            )
    return out


def table(reaches: list[Reach], threshold: float, worst: float, method: str) -> list[str]:
    """Markdown rows of :func:`reach`."""
    lines = [
        f"| group | pairs | {method} success | true pose >= {threshold:.2f} "
        f"| true pose > {worst:.2f} | target | reaches target |",
        "|---|---|---|---|---|---|---|",
    ]
    for g in reaches:
        lines.append(
            f"| {g.group} | {g.pairs} | {frac(g.success, g.pairs)} "
            f"| {frac(g.at_threshold, g.pairs)} | {frac(g.above_worst, g.pairs)} "
            f"| {100 * g.target:.0f} % | {'yes' if g.reaches else 'no'} |"
        )
    return lines


def chart(
    rows: list[dict], bad: list[tuple[str, float]], threshold: float, path: Path, data: str
) -> None:
    """Histograms of the true poses' margins per set and of the run's bad winners', with
    the threshold; ``data`` names the pairs in the title."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    bins = np.linspace(-1.5, 1.0, 51)
    fig, axes = plt.subplots(4, 1, figsize=(8, 7), sharex=True)
    panels = [
        (s, [r["margin"] for r in rows if r["set"] == s], "tab:green")
        for s in ("standard", "low", "drifted")
    ]
    panels.append(("wrong or negative winners (run)", [m for _, m in bad], "tab:red"))
    for ax, (name, values, colour) in zip(axes, panels, strict=True):
        ax.hist(np.clip(values, bins[0], bins[-1]), bins, color=colour)
        ax.axvline(threshold, color="k", ls="--", lw=1)
        ax.set_ylabel("pairs")
        ax.set_title(f"{name}: {len(values)}", fontsize=9, loc="left")
    axes[0].annotate(
        f"threshold {threshold:.2f}", (threshold, axes[0].get_ylim()[1] * 0.8), fontsize=8
    )
    axes[-1].set_xlabel(
        "margin: a true pose's against no rival, a winner's against its best rival "
        "(beyond the axis: at its ends)",
        fontsize=9,
    )
    fig.suptitle(f"the true pose, scored as the merge scores its winner ({data})")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def report(
    reaches: list[Reach], bad: list[tuple[str, float]], threshold: float, method: str, cmd: str
) -> str:
    """The markdown report."""
    worst_pair, worst = max(bad, key=lambda b: b[1])
    lines = [
        "# The decision's evidence at the true pose\n",
        f"`{cmd}`\n",
        "Every overlapping pair scored at its true pose as the merge scores its winner "
        "(drift-tolerant overlay on the decision's maps), against no rival: the best of the "
        f"{len(HEADING_STEPS) * len(SHIFT_STEPS) ** 2} poses around the truth (turned by "
        f"up to {max(HEADING_STEPS):g} deg about B's walls, shifted by up to "
        f"{max(SHIFT_STEPS):g} cells) and the merge's last refinement from it, among those "
        "the bench counts right: the most the acceptance statistic gives the pair at a right "
        f"pose. The threshold is `MergeParams.min_margin` = {threshold:.2f}; the "
        f"largest margin of a wrong or negative winner of {method} in the run is "
        f"{worst:.2f} ({worst_pair}). No decision by this statistic accepts a pair whose "
        "right poses all score below the threshold; a threshold at the largest bad margin "
        "accepts that winner. Targets: issue 10.\n",
        *table(reaches, threshold, worst, method),
    ]
    return "\n".join(lines) + "\n"


def read_run(path: Path, method: str) -> tuple[list[tuple[str, float]], dict[str, bool]]:
    """A run's bad winners of ``method`` (:func:`bad_margins`) and whether it accepted each
    pair right.

    Raises
    ------
    ValueError
        One line naming the file: not a bench run's ``merge.json``, or no wrong or negative
        winner of ``method`` in it.
    """
    try:
        records = json.loads(path.read_text())["records"]
        bad = bad_margins(records, method)
        success = {r["pair"]: bool(r["success"]) for r in records if r["method"] == method}
    except (OSError, ValueError, KeyError, TypeError, AttributeError) as exc:
        raise ValueError(f"{path}: not a bench run's merge.json ({exc})") from None
    if not bad:
        raise ValueError(f"{path}: no wrong or negative winner of {method} to set beside")
    return bad, success


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run", type=Path, help="merge.json of a bench run (its bad winners)")
    parser.add_argument("--method", default="pgvd", help="the run's method")
    parser.add_argument("--out", type=Path, help="default: truth-evidence.md in bench/results")
    parser.add_argument(
        "--held-out", action="store_true", help="the pairs of the logs kept for evaluation"
    )
    parser.add_argument("--png", type=Path, metavar="OUT.png", help="also draw the margins")
    parser.add_argument("--seed", type=int, default=1, help="seed of the run's pairs")
    parser.add_argument("--cache", type=Path, default=CACHE)
    args = parser.parse_args(argv)
    try:
        bad, success = read_run(args.run, args.method)
    except ValueError as exc:
        parser.error(str(exc))
    sources = held_out_logs() if args.held_out else SOURCES
    entries = build(FULL, args.seed, args.cache, sources, gmapping=not args.held_out)
    missing = [e.pair.name for e in entries if e.pair.overlap > 0 and e.pair.name not in success]
    if missing:
        parser.error(
            f"{args.run}: {len(missing)} of these pairs are not in the run ({missing[0]}, ...): "
            "give the run of the same pairs (with --held-out, a --held-out run)"
        )
    params = MergeParams(diagnostics=False)
    rows = measure(entries, params)
    out = args.out or (HELD_OUT if args.held_out else RESULTS) / "truth-evidence.md"
    worst = max(m for _, m in bad)
    png = "" if args.png is None else f" --png {args.png}"
    held = " --held-out" if args.held_out else ""
    cmd = f"python3 -m bench.truth_evidence {args.run}{held}{png}"
    out.write_text(
        report(
            reach(rows, success, params.min_margin, worst), bad, params.min_margin, args.method, cmd
        )
    )
    print(f"wrote {out}")
    if args.png is not None:
        data = "logs kept for evaluation" if args.held_out else "development data"
        chart(rows, bad, params.min_margin, args.png, data)
        print(f"wrote {args.png}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
