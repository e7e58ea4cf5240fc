"""The acceptance statistic on the wide merge bench: margins of true and false hypotheses.

The merge accepts its winning pose when the margin of :mod:`pgvd.decision`
(its overlay evidence beyond the best rival pose's, per overlapping wall cell)
reaches ``MergeParams.min_margin``.  This reads the pgvd records of a merge
bench run (``merge.json``, :mod:`bench.merge`) and sorts every winning
hypothesis into one of three classes:

``right``     an overlapping pair whose winning pose is right (heading within
              2 deg, mean cell error within the pair's tolerance), accepted or not;
``wrong``     an overlapping pair whose winning pose is wrong;
``negative``  a pair with no overlap (disjoint parts, look-alike corridors,
              mirror images, different buildings): every pose is false.

It writes the margin histogram of the three classes (``acceptance.png``) and
a table of what each threshold would accept (``acceptance.md``): the false
accept rate of a threshold is measured on the development negatives.

The threshold is set just above the largest margin of a false hypothesis, so
that table cannot say how it fares on a building it was not set on.  The
report's last table leaves one building out at a time: the threshold set that
way on the other buildings' winners, and the wrong and false accepts it makes
on the building left out (a cross-building negative belongs to both of its
buildings).

Run from the project root after ``python3 -m bench merge``::

    python3 -m bench acceptance                       # reads bench/results/merge.json
    python3 -m bench acceptance --merge /tmp/d10/merge.json --out /tmp/d10

``bench.merge`` writes both files itself at the end of a run.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from bench.tables import NEGATIVE, OVERLAP_SETS, frac, pose_right, records_main, rerun

CLASSES = ("right", "wrong", "negative")
#: Thresholds of the table, beside the merge's own.
THRESHOLDS = (0.0, 0.2, 0.4, 0.5, 0.6, 0.65, 0.7, 0.8, 0.9)
#: Margins are drawn clipped to this range (far below 0 for a contradicted winner, above 1
#: when its rivals are contradicted).
CLIP = (-1.5, 2.0)


def hypothesis_class(record: dict) -> str | None:
    """``right``, ``wrong`` or ``negative`` for a pgvd record; None without a winning pose."""
    if record["result"].get("margin") is None:
        return None
    if record["set"] == NEGATIVE:
        return "negative"
    return "right" if pose_right(record) else "wrong"


def margins(records: list[dict]) -> dict[str, list[tuple[dict, float]]]:
    """The pgvd records with a winning pose, per class, with their margins."""
    out: dict[str, list[tuple[dict, float]]] = {c: [] for c in CLASSES}
    for r in records:
        cls = hypothesis_class(r) if r["method"] == "pgvd" else None
        if cls is not None:
            out[cls].append((r, float(r["result"]["margin"])))
    return out


def threshold_rows(
    classes: dict[str, list[tuple[dict, float]]], thresholds: list[float]
) -> list[str]:
    """Markdown rows: per threshold, right poses accepted per set, wrong and false accepts."""
    rows = []
    for t in thresholds:
        cells = []
        for name in OVERLAP_SETS:
            mine = [m for r, m in classes["right"] if r["set"] == name]
            cells.append(frac(sum(m >= t for m in mine), len(mine)))
        wrong = [m for _, m in classes["wrong"]]
        neg = [m for _, m in classes["negative"]]
        cells += [
            frac(sum(m >= t for m in wrong), len(wrong)),
            frac(sum(m >= t for m in neg), len(neg)),
        ]
        rows.append(f"| {t:.2f} | " + " | ".join(cells) + " |")
    return rows


def buildings(record: dict) -> set[str]:
    """The buildings a record belongs to: its own, or both of a cross-building negative."""
    info = record.get("info") or {}
    both = {info.get("building_a"), info.get("building_b")} - {None}
    return both or {record["building"]}


def held_out_rows(classes: dict[str, list[tuple[dict, float]]], step: float = 0.01) -> list[str]:
    """Markdown rows: per building, the threshold set without it and what that accepts on it.

    The threshold is the largest margin of a wrong or negative winner of the
    other buildings, rounded up to the next ``step`` above it.
    """
    every = [(r, m, c) for c in CLASSES for r, m in classes[c]]
    names = sorted(set().union(*(buildings(r) for r, _, _ in every))) if every else []
    rows = []
    for name in names:
        inside = [(r, m, c) for r, m, c in every if name in buildings(r)]
        false = [m for r, m, c in every if c != "right" and name not in buildings(r)]
        if not false:
            continue
        # (the small term: 0.29 / 0.01 is 28.999... in floating point)
        t = (np.floor(max(false) / step + 1e-9) + 1) * step
        bad = [r["pair"] for r, m, c in inside if c != "right" and m >= t]
        right = [m for _, m, c in inside if c == "right"]
        n_bad = sum(c != "right" for _, _, c in inside)
        rows.append(
            f"| {name} | {t:.2f} | {frac(sum(m >= t for m in right), len(right))} "
            f"| {frac(len(bad), n_bad)} | {', '.join(bad) or '-'} |"
        )
    return rows


def markdown(
    classes: dict[str, list[tuple[dict, float]]], threshold: float, source: str, command: str
) -> str:
    """The report: the margin of each class and what each threshold accepts."""
    lines = [
        "# Acceptance margin on the merge bench",
        "",
        f"`{command}`",
        "",
        f"From the pgvd records of `{source}`; the merge's threshold is {threshold}.",
        "",
        "| class | winning poses | min | median | max |",
        "|---|---|---|---|---|",
    ]
    for c in CLASSES:
        m = [v for _, v in classes[c]]
        if m:
            lines.append(f"| {c} | {len(m)} | {min(m):.2f} | {np.median(m):.2f} | {max(m):.2f} |")
        else:
            lines.append(f"| {c} | 0 | - | - | - |")
    false = [r for r, _ in classes["negative"] + classes["wrong"]]
    top = sorted(
        zip(false, [m for _, m in classes["negative"] + classes["wrong"]], strict=True),
        key=lambda x: -x[1],
    )[:3]
    lines += [
        "",
        "Largest margins of false hypotheses: "
        + ", ".join(f"{r['pair']} ({r['kind']}) {m:.2f}" for r, m in top)
        + ".",
        "",
        "What a threshold accepts (right poses per set; wrong poses of overlapping pairs; "
        "winners on the negatives, i.e. the false accept rate):",
        "",
        "| threshold | right, standard | right, low | right, drifted | wrong | negatives |",
        "|---|---|---|---|---|---|",
        *threshold_rows(classes, sorted({*THRESHOLDS, threshold})),
        "",
        "Winning pose: the merge's best hypothesis after refinement, accepted or not; pairs "
        "rejected before the decision (no supported translation) have none.",
        "",
        "Leave one building out: the threshold just above the largest margin of a wrong or "
        "negative winner of the other buildings, and what it accepts on the building left out:",
        "",
        "| building left out | threshold | right poses accepted | wrong or false accepts | which |",
        "|---|---|---|---|---|",
        *held_out_rows(classes),
        "",
    ]
    return "\n".join(lines)


def chart(classes: dict[str, list[tuple[dict, float]]], threshold: float, path: Path) -> None:
    """Histogram of the margins of the three classes, with the threshold."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8, 4.2))
    bins = np.linspace(*CLIP, 71)
    labels = {
        "right": "right-pose winners",
        "wrong": "wrong-pose winners",
        "negative": "winners on negatives (no overlap)",
    }
    for c, colour in zip(CLASSES, ("tab:green", "tab:orange", "tab:red"), strict=True):
        m = np.clip([v for _, v in classes[c]], *CLIP)
        ax.hist(m, bins, alpha=0.55, color=colour, label=f"{labels[c]} ({len(m)})")
    ax.axvline(threshold, color="k", ls="--", label=f"threshold {threshold}")
    ax.set_xlabel(f"margin (pgvd.decision), clipped to [{CLIP[0]}, {CLIP[1]}]")
    ax.set_ylabel("pairs")
    ax.set_title("acceptance margin of the winning pose, wide merge bench (development data)")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def write(records: list[dict], out: Path, source: str) -> str:
    """Write ``acceptance.md`` and ``acceptance.png`` to ``out``; returns the markdown."""
    from pgvd.params import MergeParams

    threshold = MergeParams().min_margin
    classes = margins(records)
    text = markdown(classes, threshold, Path(source).name, rerun("acceptance", Path(source)))
    out.mkdir(parents=True, exist_ok=True)
    (out / "acceptance.md").write_text(text)
    chart(classes, threshold, out / "acceptance.png")
    return text


def main(argv: list[str] | None = None) -> int:
    return records_main(argv, __doc__.splitlines()[0], write)


if __name__ == "__main__":
    raise SystemExit(main())
