"""The decision's evidence at right poses: which pairs any threshold on it could accept.

The merge accepts its winner when the margin over the best rival
(:mod:`pgvd.decision`) reaches ``MergeParams.min_margin``.  Here every
overlapping pair of the development bench is scored as the merge scores a
winner: on the decision's maps (:func:`bench.studies.redecide.decision_maps`), each
few-metre square of the overlap re-aligned for drift first
(:func:`pgvd.scoring.score_hypothesis`), against no rival at all (evidence 0,
:func:`pgvd.decision.margin_against`: a rival only lowers the margin).  The
poses scored are right ones (the bench's own test, :func:`bench.merge.evaluate`):
a grid around the truth (:func:`around`), the merge's last refinement from the
truth (:func:`pgvd.refinement.final_refinement`), the run's own returned pose and
refined finalists where they are right, and a pattern search of the statistic
from the best of them (:func:`climb`).  The best margin found is a *sampled*
maximum over the right poses, not a proof: a right pose elsewhere could score
more, but the run's own right poses are among those tried, so it is never
below what the merge achieved.

A pair whose best right pose scores below a threshold is rejected there by
every decision on this statistic that finds no better right pose.  The
threshold must stay above the margins of the run's wrong and negative
winners (a mirror image of a building scores like an overlap) against the
rivals the run's search found.  The report gives, per set and building, the
pairs whose best right pose reaches ``min_margin`` and exceeds the run's
largest bad margin, and the threshold each target would need.  Not modelled:
the retry with lone wall cells read as unknown (``MergeParams.speckle_retry``),
which decides a rejected pair of raw map images a second time.

    python3 -m bench truth_evidence bench/results/merge.json [--png OUT.png] [--out OUT.md]

Per-pair margins go beside the report (``OUT.json``).  ``--held-out`` measures the
pairs the bench cuts from the logs kept to evaluate the merge (``python3 -m
bench.merge --held-out``; give that run's ``merge.json``); the report goes to
``bench/results/held-out/truth-evidence.md``.  Nothing is set from it.
``--param FIELD=VALUE`` scores with other ``MergeParams`` (the run's bad winners
keep the margins the run gave them under its own).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from bench.data.pairs import MapPair
from bench.data.sets import FULL, Entry, build
from bench.data.sources import SOURCES, held_out_logs
from bench.merge import CACHE, HELD_OUT, RESULTS, evaluate
from bench.studies.acceptance import margins
from bench.studies.ceiling import groups, read_run
from bench.studies.redecide import decision_maps, params_from
from bench.tables import frac
from pgvd.decision import margin_against
from pgvd.params import MergeParams
from pgvd.pooling import decision_pool, from_pooled, to_pooled
from pgvd.refinement import final_refinement
from pgvd.scoring import score_hypothesis
from pgvd.walls import WallMap

#: Heading offsets (degrees) and shifts (cells of the decision's maps) of :func:`around`.
HEADING_STEPS = (-1.0, -0.5, 0.0, 0.5, 1.0)
SHIFT_STEPS = (-2.0, -1.0, 0.0, 1.0, 2.0)
#: First steps of :func:`climb` (degrees, cells), and how many step sizes it tries: each
#: half the one before (the last 0.0625 degree and 0.25 cell).
CLIMB_START = (0.5, 2.0)
CLIMB_LEVELS = 4
#: The runs a pair's maps must have been read as given in: painted or speckled maps are
#: other maps (``bench.merge --unknown free``, ``--speckle``).
ALTERED = ("--unknown", "--speckle")
#: The fields of a run's pgvd record this reads beyond :data:`bench.studies.ceiling.FIELDS`.
PGVD_FIELDS = ("result", "success")


def moved(matrix: np.ndarray, centre: np.ndarray, deg: float, dx: float, dy: float) -> np.ndarray:
    """The pose ``matrix`` (B->A pixels) turned by ``deg`` about ``centre`` (a point of B,
    ``(x, y)``, where it lands in A) and shifted by ``(dx, dy)`` pixels of A.

    Turning about B's own centre moves B's walls least for a given turn.
    """
    x, y = (matrix @ np.array([centre[0], centre[1], 1.0]))[:2]
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    turn = np.array([[c, -s, x - c * x + s * y + dx], [s, c, y - s * x - c * y + dy], [0, 0, 1.0]])
    return turn @ matrix


def around(matrix: np.ndarray, centre: np.ndarray) -> list[np.ndarray]:
    """:func:`moved` by every heading of :data:`HEADING_STEPS` and every pair of shifts of
    :data:`SHIFT_STEPS` (125 poses, ``matrix`` itself among them)."""
    return [
        moved(matrix, centre, deg, dx, dy)
        for deg in HEADING_STEPS
        for dx in SHIFT_STEPS
        for dy in SHIFT_STEPS
    ]


@dataclass
class _Scorer:
    """The margin with no rival of poses of one pair (pooled frame), right ones only."""

    pair: MapPair
    fine_a: WallMap
    fine_b: WallMap
    params: MergeParams
    pool: int

    def right(self, m: np.ndarray) -> bool:
        """Whether the bench counts the pose right (:func:`bench.merge.evaluate`)."""
        return bool(evaluate(self.pair, True, from_pooled(m, self.pool))["success"])

    def margin(self, m: np.ndarray) -> float:
        """``margin_against`` of the pose scored by :func:`pgvd.scoring.score_hypothesis`."""
        res = self.pair.a.resolution * self.pool
        scored = score_hypothesis(m, self.fine_a, self.fine_b, self.params, res)
        return margin_against(
            scored, -np.inf, self.params.disagreement_weight, self.params.margin_noise
        )


def climb(scorer: _Scorer, start: np.ndarray, score: float, centre: np.ndarray) -> float:
    """The margin of the best right pose a pattern search reaches from ``start`` (right,
    of margin ``score``).

    Each step tries the current pose turned by +-``deg`` and shifted by +-``cells`` along
    each axis (:func:`moved`), moves to the best right one that scores more, and halves
    both steps when none does: :data:`CLIMB_LEVELS` sizes from :data:`CLIMB_START`.
    """
    best = start
    deg, cells = CLIMB_START
    levels = CLIMB_LEVELS
    while levels:
        tries = [
            moved(best, centre, *step)
            for step in (
                (deg, 0, 0),
                (-deg, 0, 0),
                (0, cells, 0),
                (0, -cells, 0),
                (0, 0, cells),
                (0, 0, -cells),
            )
        ]
        scored = [(scorer.margin(m), m) for m in tries if scorer.right(m)]
        top = max(scored, key=lambda s: s[0], default=None)
        if top is not None and top[0] > score:
            score, best = top
        else:
            deg, cells, levels = deg / 2, cells / 2, levels - 1
    return score


def truth_margin(pair: MapPair, params: MergeParams, tried: tuple[np.ndarray, ...] = ()) -> float:
    """The best margin with no rival of a right pose of ``pair`` found near its truth.

    Parameters
    ----------
    pair : MapPair
        An overlapping pair (its ``truth`` set).
    params : MergeParams
        The decision's parameters.
    tried : tuple of numpy.ndarray, optional
        More poses to try (3x3 B->A pixels of the pair's maps), e.g. a run's returned
        pose and refined finalists; those that are not right are left out.

    Returns
    -------
    float
        ``(E - 0) / n - margin_noise / sqrt(n)`` of :func:`pgvd.decision.margin_against`,
        the largest over the right poses of :func:`around` the truth, the merge's last
        refinement from it and ``tried``, then improved by :func:`climb` from the best.
    """
    fine_a, fine_b = decision_maps(pair.a, pair.b, params)
    pool = decision_pool(pair.a.resolution)
    scorer = _Scorer(pair, fine_a, fine_b, params, pool)
    truth = to_pooled(np.asarray(pair.truth, dtype=float), pool)
    centre = fine_b.walls.mean(axis=0)
    poses = around(truth, centre)
    poses.append(final_refinement(truth, fine_a, fine_b, params))
    poses += [to_pooled(np.asarray(m, dtype=float), pool) for m in tried]
    # the truth itself is right: never an empty choice
    score, start = max(
        ((scorer.margin(m), m) for m in poses if scorer.right(m)), key=lambda s: s[0]
    )
    return climb(scorer, start, score, centre)


def run_poses(record: dict | None) -> tuple[np.ndarray, ...]:
    """A run record's returned pose and refined finalists (B->A pixels), those it has."""
    if record is None:
        return ()
    mats = [record.get("matrix"), *(record.get("finalists") or ())]
    return tuple(np.asarray(m, dtype=float) for m in mats if m is not None)


def measure(entries: list[Entry], params: MergeParams, run: dict[str, dict]) -> list[dict]:
    """:func:`truth_margin` of every overlapping pair, with the run's poses of it tried.

    Parameters
    ----------
    entries : list of Entry
        The bench's pairs; those without overlap are skipped.
    params : MergeParams
        The decision's parameters.
    run : dict
        The run's pgvd record of each pair, by pair name.

    Returns
    -------
    list of dict
        One row a pair: ``pair``, ``set``, ``source``, ``overlap``, ``margin`` (the bound),
        ``run_margin`` (the run's, None without a winner) and ``run_success``; a progress
        line a pair goes to stderr.
    """
    out = []
    overlapping = [e for e in entries if e.pair.truth is not None and e.pair.overlap > 0]
    for i, e in enumerate(overlapping, 1):
        rec = run.get(e.pair.name)
        m = truth_margin(e.pair, params, run_poses(rec))
        out.append(
            {
                "pair": e.pair.name,
                "set": e.set,
                "source": e.source,
                "overlap": e.pair.overlap,
                "margin": m,
                "run_margin": None if rec is None else rec["result"].get("margin"),
                "run_success": bool(rec and rec["success"]),
            }
        )
        print(f"[{i}/{len(overlapping)}] {e.pair.name}: {m:.2f}", file=sys.stderr, flush=True)
    return out


def bad_margins(records: list[dict]) -> list[tuple[str, float]]:
    """``(pair, margin)`` of every pgvd winner of a run that is wrong or on a negative pair,
    accepted or not (:func:`bench.studies.acceptance.margins`)."""
    classes = margins(records)
    return [(r["pair"], m) for cls in ("wrong", "negative") for r, m in classes[cls]]


@dataclass(frozen=True)
class Reach:
    """One group: its pairs, the run's successes, how many best right poses reach the
    threshold and exceed the largest bad margin, the threshold its target would need (the
    margin of its ``ceil(target * pairs)``-th best pair) and the target share."""

    group: str
    pairs: int
    success: int
    at_threshold: int
    above_worst: int
    needs: float
    target: float

    @property
    def reaches(self) -> bool:
        """Whether the pairs above the largest bad margin reach the target."""
        return self.above_worst >= self.target * self.pairs


def reach(rows: list[dict], threshold: float, worst: float) -> list[Reach]:
    """:class:`Reach` per group of :func:`bench.studies.ceiling.groups` of ``rows``
    (:func:`measure`)."""
    out = []
    for name, target, member in groups(rows):
        mine = sorted((r for r in rows if member(r)), key=lambda r: -r["margin"])
        if mine:
            k = min(len(mine), math.ceil(target * len(mine) - 1e-9))
            out.append(
                Reach(
                    group=name,
                    pairs=len(mine),
                    success=sum(r["run_success"] for r in mine),
                    at_threshold=sum(r["margin"] >= threshold for r in mine),
                    above_worst=sum(r["margin"] > worst for r in mine),
                    needs=mine[k - 1]["margin"],
                    target=target,
                )
            )
    return out


def table(reaches: list[Reach], threshold: float, worst: float) -> list[str]:
    """Markdown rows of :func:`reach`."""
    lines = [
        f"| group | pairs | pgvd success | best right pose >= {threshold:.2f} "
        f"| best right pose > {worst:.2f} | threshold the target needs | target "
        f"| reaches target above {worst:.2f} |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for g in reaches:
        lines.append(
            f"| {g.group} | {g.pairs} | {frac(g.success, g.pairs)} "
            f"| {frac(g.at_threshold, g.pairs)} | {frac(g.above_worst, g.pairs)} "
            f"| {g.needs:.2f} | {100 * g.target:.0f} % | {'yes' if g.reaches else 'no'} |"
        )
    return lines


def chart(
    rows: list[dict], bad: list[tuple[str, float]], threshold: float, path: Path, data: str
) -> None:
    """Histograms of the best right poses' margins per set and of the run's bad winners',
    with the threshold; ``data`` names the pairs in the title."""
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
        "margin: a best right pose's against no rival, a winner's against its best rival "
        "(beyond the axis: at its ends)",
        fontsize=9,
    )
    fig.suptitle(f"the best right pose found near the truth, scored as the merge scores ({data})")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def report(
    reaches: list[Reach],
    worst: tuple[str, float],
    threshold: float,
    cmd: str,
    below: int,
    overridden: bool = False,
) -> str:
    """The markdown report; ``worst`` is the run's largest bad margin and its pair, ``below``
    counts pairs the run accepted right at a margin above their bound (0 unless the bound
    is broken), ``overridden`` says the pairs were scored with other parameters than the
    run's."""
    worst_pair, worst_margin = worst
    n_poses = len(HEADING_STEPS) * len(SHIFT_STEPS) ** 2
    lines = [
        "# The decision's evidence at right poses\n",
        f"`{cmd}`\n",
        "Every overlapping pair scored as the merge scores its winner (drift-tolerant "
        "overlay on the decision's maps), against no rival, at right poses (as the bench "
        f"counts them): {n_poses} around the truth (turned by up to {max(HEADING_STEPS):g} "
        f"deg about B's walls, shifted by up to {max(SHIFT_STEPS):g} cells), the merge's last "
        "refinement from it and the run's own returned pose and finalists, then a pattern "
        "search of the statistic from the best. The best margin found is a sampled maximum, "
        "not a proof, but never below the run's own. "
        f"The threshold is `MergeParams.min_margin` = {threshold:.2f}; the largest margin of "
        f"a wrong or negative winner of pgvd in the run is {worst_margin:.2f} ({worst_pair}), "
        "against "
        "the rivals its search found: a threshold with no bad accept in this run is above it. "
        "'threshold the target needs': the margin of the group's ceil(target x pairs)-th best "
        f"pair. Pairs the run accepted right above their bound: {below}.\n",
        *(
            [
                "Scored with `--param`: the run's bad winners keep the margins it gave them with "
                "its own parameters, so the column above their largest compares two statistics; "
                "replay them with the same `--param` (`python3 -m bench redecide -v`) to compare "
                "like with like.\n"
            ]
            if overridden
            else []
        ),
        *table(reaches, threshold, worst_margin),
    ]
    return "\n".join(lines) + "\n"


def pgvd_records(doc: dict, path: Path) -> list[dict]:
    """The pgvd records of a run read by :func:`bench.studies.ceiling.read_run`.

    Raises
    ------
    ValueError
        One line: a pgvd record without a field of :data:`PGVD_FIELDS`.
    """
    mine = [r for r in doc["records"] if r["method"] == "pgvd"]
    for r in mine:
        missing = [f for f in PGVD_FIELDS if f not in r]
        if missing:
            raise ValueError(f"{path}: a pgvd record without {', '.join(missing)}")
    return mine


def check_run(
    command: str, records: list[dict], path: Path, entries: list[Entry]
) -> dict[str, dict]:
    """The run's pgvd record of each pair, once the run is checked to be of ``entries``.

    Parameters
    ----------
    command : str
        The run's command line (``merge.json``'s ``command``).
    records : list of dict
        Its pgvd records (:func:`pgvd_records`).
    path : Path
        The run's file, named in errors.
    entries : list of Entry
        The bench's pairs.

    Returns
    -------
    dict
        Record by pair name.

    Raises
    ------
    ValueError
        One line: a run of maps read otherwise (painted, speckled), without a pgvd record
        of an overlapping pair, or whose truth of a pair is not the pair's (another seed).
    """
    altered = [flag for flag in ALTERED if flag in command.split()]
    if altered:
        raise ValueError(f"{path}: a run of altered maps ({altered[0]}): give a plain run")
    run = {r["pair"]: r for r in records}
    for e in entries:
        if e.pair.truth is None or e.pair.overlap <= 0:
            continue
        rec = run.get(e.pair.name)
        if rec is None:
            raise ValueError(
                f"{path}: no pgvd record of {e.pair.name}: give the run of the same pairs "
                "(with --held-out, a --held-out run)"
            )
        if rec.get("truth") is None or not np.allclose(rec["truth"], e.pair.truth, atol=1e-6):
            raise ValueError(f"{path}: its truth of {e.pair.name} is not this pair's (--seed?)")
    return run


def _writable(path: Path, suffix: str | None = None) -> None:
    """Raise ValueError (one line) for an output path that cannot be written."""
    if not path.parent.is_dir():
        raise ValueError(f"{path}: no directory {path.parent}")
    if suffix is not None and path.suffix.lower() != suffix:
        raise ValueError(f"{path}: the picture must be a {suffix} file")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run", type=Path, help="merge.json of a bench run (its bad winners)")
    parser.add_argument("--out", type=Path, help="default: truth-evidence.md in bench/results")
    parser.add_argument(
        "--held-out", action="store_true", help="the pairs of the logs kept for evaluation"
    )
    parser.add_argument("--png", type=Path, metavar="OUT.png", help="also draw the margins")
    parser.add_argument("--param", nargs="*", default=[], help="MergeParams FIELD=VALUE")
    parser.add_argument("--seed", type=int, default=1, help="seed of the run's pairs")
    parser.add_argument("--cache", type=Path, default=CACHE)
    args = parser.parse_args(argv)
    out = args.out or (HELD_OUT if args.held_out else RESULTS) / "truth-evidence.md"
    try:
        params = params_from(args.param)
        _writable(out)
        if args.png is not None:
            _writable(args.png, ".png")
        doc = read_run(args.run)
        records = pgvd_records(doc, args.run)
        bad = bad_margins(records)
        if not bad:
            raise ValueError(f"{args.run}: no wrong or negative winner of pgvd to set beside")
        sources = held_out_logs() if args.held_out else SOURCES
        entries = build(FULL, args.seed, args.cache, sources, gmapping=not args.held_out)
        run = check_run(str(doc.get("command", "")), records, args.run, entries)
    except (ValueError, TypeError, AttributeError) as exc:
        parser.error(str(exc))
    rows = measure(entries, params, run)
    below = [r["pair"] for r in rows if r["run_success"] and r["run_margin"] > r["margin"] + 1e-9]
    if below:
        print(f"the run accepted right above the bound: {', '.join(below)}", file=sys.stderr)
    out.with_suffix(".json").write_text(json.dumps(rows, indent=1) + "\n")
    worst = max(bad, key=lambda b: b[1])
    cmd = f"python3 -m bench truth_evidence {args.run}"
    if args.held_out:
        cmd += " --held-out"
    if args.png is not None:
        cmd += f" --png {args.png}"
    if args.param:
        cmd += f" --param {' '.join(args.param)}"
    reaches = reach(rows, params.min_margin, worst[1])
    text = report(reaches, worst, params.min_margin, cmd, len(below), bool(args.param))
    out.write_text(text)
    print(f"wrote {out} and {out.with_suffix('.json')}")
    if args.png is not None:
        data = "logs kept for evaluation" if args.held_out else "development data"
        chart(rows, bad, params.min_margin, args.png, data)
        print(f"wrote {args.png}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
