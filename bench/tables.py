"""Tables and charts of a merge bench run, from its per-pair records alone.

Every number here is computed from the records that ``merge.json`` stores,
so a table can be rebuilt, or a new one made, without rerunning a merge.

Success on an overlapping pair: accepted, heading within 2 degrees and mean
error of B's occupied cells within 3 cells.  A *wrong accept*: accepted on an
overlapping pair outside those bounds.  A *false accept*: any accept on a
negative pair.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Callable
from pathlib import Path

import numpy as np

#: The overlapping sets, in report order, and the negative set.
OVERLAP_SETS = ("standard", "low", "drifted")
NEGATIVE = "negative"
NEGATIVE_KINDS = ("disjoint", "lookalike", "mirror", "cross")
#: The paper's reported time per merge, seconds (10 to 13 s).
PAPER_SECONDS = (10.0, 13.0)
#: Success thresholds: heading error (degrees) and mean cell error of B's walls
#: (a drifted pair adds its own distortion: ``cell_tolerance`` of each record).
MAX_HEADING_DEG = 2.0
MAX_CELL_ERROR = 3.0
#: The project root: the commands a report states name paths from it.
ROOT = Path(__file__).resolve().parents[1]


def pose_right(record: dict) -> bool:
    """Whether a record's returned pose, accepted or not, is within the success bounds."""
    return (
        record["heading_deg"] <= MAX_HEADING_DEG and record["cell_err"] <= record["cell_tolerance"]
    )


def mark(success: bool, accepted: bool) -> str:
    """A pair's outcome in a progress line: ``ok``, ``ACC`` (accepted, wrong) or ``rej``."""
    return "ok" if success else ("ACC" if accepted else "rej")


def frac(hits: int, n: int, digits: int = 0) -> str:
    """``hits/n (P %)`` with ``digits`` decimals, or ``-`` for no pairs."""
    return "-" if n == 0 else f"{hits}/{n} ({100 * hits / n:.{digits}f} %)"


def _count(records: list[dict], key: str) -> tuple[int, int]:
    return sum(bool(r[key]) for r in records), len(records)


def _seconds(records: list[dict]) -> tuple[float, float]:
    if not records:
        return float("nan"), float("nan")
    s = np.array([r["seconds"] for r in records])
    return float(np.median(s)), float(np.percentile(s, 95))


def cell_stats(records: list[dict]) -> dict:
    """Counts of one group of records (one method): per set, wrong and false accepts, times."""
    out: dict = {}
    for name in OVERLAP_SETS:
        mine = [r for r in records if r["set"] == name]
        out[name] = _count(mine, "success")
        out[f"{name}_wrong"] = sum(r["accepted"] and not r["success"] for r in mine)
    overlapping = [r for r in records if r["set"] in OVERLAP_SETS]
    negatives = [r for r in records if r["set"] == NEGATIVE]
    out["overall"] = _count(overlapping, "success")
    out["wrong"] = (sum(r["accepted"] and not r["success"] for r in overlapping), len(overlapping))
    out["false"] = _count(negatives, "accepted")
    for kind in NEGATIVE_KINDS:
        out[f"false_{kind}"] = _count([r for r in negatives if r["kind"] == kind], "accepted")
    good = [r for r in overlapping if r["success"]]
    out["heading_deg"] = float(np.median([r["heading_deg"] for r in good])) if good else None
    out["cell_err"] = float(np.median([r["cell_err"] for r in good])) if good else None
    out["median_s"], out["p95_s"] = _seconds(records)
    return out


def summarise(records: list[dict], methods: list[str]) -> dict:
    """Per method: overall numbers, and per source (a row per building and source)."""
    doc: dict = {}
    for m in methods:
        mine = [r for r in records if r["method"] == m]
        sources = sorted({r["source"] for r in mine if r["source"] != "cross-building"})
        doc[m] = {
            "all": cell_stats(mine),
            "by_source": {s: cell_stats([r for r in mine if r["source"] == s]) for s in sources},
        }
    return doc


def _fmt(v: float | None, digits: int = 2) -> str:
    return "-" if v is None or not np.isfinite(v) else f"{v:.{digits}f}"


def method_table(summary: dict, scaling: list[dict]) -> list[str]:
    """One row per method over every source."""
    cells = sorted({r["cells"] for r in scaling})
    head = ["method", "standard", "low overlap", "drifted", "wrong accepts", "false accepts"]
    head += ["median heading err (deg)", "median cell err", "median s", "p95 s"]
    head += [f"s @ {c}^2" for c in cells]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for m, doc in summary.items():
        a = doc["all"]
        row = [m, *(frac(*a[s]) for s in OVERLAP_SETS), frac(*a["wrong"]), frac(*a["false"])]
        row += [_fmt(a["heading_deg"]), _fmt(a["cell_err"]), _fmt(a["median_s"]), _fmt(a["p95_s"])]
        for c in cells:
            t = [r["seconds"] for r in scaling if r["method"] == m and r["cells"] == c]
            row.append(_fmt(t[0]) if t else "-")
        lines.append("| " + " | ".join(row) + " |")
    return lines


def speed_table(scaling: list[dict], ours: str = "pgvd") -> list[str]:
    """Seconds per merge at each map size, and ``ours`` over every other method, same run.

    A ratio below 1 is ``ours`` faster.  The methods were timed in turn on the
    same pair at each size (:func:`bench.merge.run_scaling`), so a ratio holds
    when the machine's speed drifts; absolute seconds do not.  Ratios are given
    in wall-clock and in CPU time (``cpu_seconds``, when recorded): on a busy
    machine the wall clock also counts the time other processes took.
    """
    methods = list(dict.fromkeys(r["method"] for r in scaling))
    peers = [m for m in methods if m != ours]
    head = ["cells", *(f"{m} s" for m in methods), *(f"{ours} / {m}" for m in peers)]
    head += [f"{ours} / {m} (cpu)" for m in peers]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for c in sorted({r["cells"] for r in scaling}):
        at = {r["method"]: r for r in scaling if r["cells"] == c}
        row = [f"{c}^2", *(_fmt(at[m]["seconds"]) if m in at else "-" for m in methods)]
        for key in ("seconds", "cpu_seconds"):
            mine = at.get(ours, {}).get(key)
            for m in peers:
                theirs = at.get(m, {}).get(key)
                row.append(_fmt(mine / theirs) if mine and theirs else "-")
        lines.append("| " + " | ".join(row) + " |")
    return lines


def source_table(stats: dict) -> list[str]:
    """One row per source (building and where its maps come from) for one method."""
    head = ["source", "standard", "low overlap", "drifted", "wrong accepts"]
    head += ["false accepts (negatives of this source)", "median s", "p95 s"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for name, s in [*stats["by_source"].items(), ("**all**", stats["all"])]:
        row = [name, *(frac(*s[k]) for k in OVERLAP_SETS), frac(*s["wrong"])]
        row += [frac(*s["false"]), _fmt(s["median_s"]), _fmt(s["p95_s"])]
        lines.append("| " + " | ".join(row) + " |")
    return lines


def negative_table(summary: dict) -> list[str]:
    """False accepts per kind of negative, per method."""
    head = ["method", *NEGATIVE_KINDS, "all"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for m, doc in summary.items():
        a = doc["all"]
        row = [m, *(frac(*a[f"false_{k}"]) for k in NEGATIVE_KINDS), frac(*a["false"])]
        lines.append("| " + " | ".join(row) + " |")
    return lines


def markdown(summary: dict, scaling: list[dict], command: str, notes: list[str]) -> str:
    """The whole report."""
    lines = ["# Merge benchmark", "", f"`{command}`", "", "## Every method", ""]
    lines += method_table(summary, scaling)
    if scaling:
        lines += ["", "## Speed against map size (one pair, upsampled)", "", *speed_table(scaling)]
    lines += ["", "## False accepts per kind of negative", "", *negative_table(summary)]
    for m, doc in summary.items():
        lines += ["", f"## {m}: a row per building and source", "", *source_table(doc)]
    lines += ["", "## Notes", "", *(f"- {n}" for n in notes), ""]
    return "\n".join(lines)


def chart(summary: dict, records: list[dict], scaling: list[dict], path: Path) -> None:
    """Success per set, time per merge, and time against map size."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = list(summary)
    fig, axes = plt.subplots(1, 3, figsize=(15, 4.5))
    x = np.arange(len(names))
    groups = [*OVERLAP_SETS, "wrong", "false"]
    width = 0.8 / len(groups)
    for i, g in enumerate(groups):
        vals = []
        for n in names:
            hits, total = summary[n]["all"][g]
            vals.append(hits / total if total else np.nan)
        label = {"wrong": "wrong accepts", "false": "false accepts (negatives)"}.get(g, g)
        axes[0].bar(x + (i - (len(groups) - 1) / 2) * width, vals, width, label=label)
    axes[0].set_xticks(x, names, rotation=20)
    axes[0].set_ylim(0, 1.3)
    axes[0].legend(loc="upper right", fontsize=7, ncol=3)
    axes[0].set_title("success per set (fraction of pairs)")
    axes[1].boxplot(
        [[r["seconds"] for r in records if r["method"] == n] for n in names], tick_labels=names
    )
    axes[1].set_yscale("log")
    axes[1].axhspan(*PAPER_SECONDS, color="grey", alpha=0.3, label="paper: 10-13 s")
    axes[1].set_ylabel("seconds per merge")
    axes[1].legend(fontsize=8)
    axes[1].tick_params(axis="x", rotation=20)
    axes[1].set_title("time per merge")
    for n in names:
        pts = sorted((r["cells"], r["seconds"]) for r in scaling if r["method"] == n)
        if pts:
            axes[2].loglog(*zip(*pts, strict=True), "o-", label=n)
    axes[2].set_xlabel("cells per side")
    axes[2].set_ylabel("seconds per merge")
    if scaling:
        axes[2].legend(fontsize=8)
    axes[2].set_title("time vs map size")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def rerun(module: str, merge: Path) -> str:
    """The command that writes the report of ``module`` again from the run at ``merge``."""
    paths = []
    for path in (merge.resolve(), merge.resolve().parent):
        paths.append(path.relative_to(ROOT) if path.is_relative_to(ROOT) else path)
    return f"python3 -m bench {module} --merge {paths[0]} --out {paths[1]}"


def records_main(
    argv: list[str] | None, description: str, write: Callable[[list[dict], Path, str], str]
) -> int:
    """The command line of a report built from a run's records alone (``--merge``, ``--out``).

    Reads the records of ``--merge`` (default ``bench/results/merge.json``), hands them to
    ``write(records, out, source)``, ``source`` the path of ``--merge``, and prints what it
    returns; a file without records is one line on stderr and exit 2.
    """
    results = Path(__file__).resolve().parent / "results"
    parser = argparse.ArgumentParser(description=description)
    parser.add_argument("--merge", type=Path, default=results / "merge.json")
    parser.add_argument("--out", type=Path, default=results)
    args = parser.parse_args(argv)
    try:
        records = json.loads(args.merge.read_text())["records"]
    except (OSError, ValueError, KeyError) as e:
        print(f"cannot read the merge records of {args.merge}: {e}", file=sys.stderr)
        return 2
    print(write(records, args.out, str(args.merge)))
    return 0
