"""What any decision could reach on a bench run: the pairs whose true pose was found at all.

A pair's true pose is *found* when some method of the runs given returned it,
accepted or not (:func:`bench.tables.pose_right`), or when one of that method's
finalists reached it after refinement (``finalist_success``: pgvd and its
variants record them).  A decision can accept at most the pairs whose pose is
found, so the share found per set bounds the success of every decision on those
hypotheses.  (:func:`bench.studies.recall.pose_recall` counts pgvd's own finalists and
successes instead: it splits pgvd's losses between its search and its decision.)  With the
``exhaustive`` reference's run among the inputs (every heading at 1 degree,
the best whole-pose score), a pair found by no method is one whose best-scoring
pose is not the truth: a wider search does not find it either.

The shares are set against targets per set (:data:`TARGETS`: standard 97 %, low 60 %,
drifted 90 %; the standard pairs of one building 90 %, :data:`BUILDING_TARGET`).

    python3 -m bench ceiling bench/results/merge.json RUN/merge.json [--png OUT.png]
"""

from __future__ import annotations

import argparse
import json
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from bench.tables import frac, pose_right

#: Success targets per set (share of the overlapping pairs).
TARGETS = {"standard": 0.97, "low": 0.60, "drifted": 0.90}
#: Success target for the standard pairs of every building.
BUILDING_TARGET = 0.90


#: The fields of a run's record that the bound reads.
FIELDS = ("pair", "method", "set", "source", "overlap", "heading_deg", "cell_err", "cell_tolerance")


def found(record: dict) -> bool:
    """Whether a record's method reached the true pose: returned it, accepted or not, or
    held it among its refined finalists."""
    return pose_right(record) or any(record.get("finalist_success") or ())


def read_run(path: Path, fields: tuple[str, ...] = FIELDS) -> dict:
    """The JSON document of the bench run at ``path``, its records checked.

    Raises
    ------
    ValueError
        One line naming the file: not a run's JSON, or a record without one of ``fields``.
    """
    try:
        doc = json.loads(path.read_text())
        mine = doc["records"]
        if not isinstance(mine, list) or not all(isinstance(r, dict) for r in mine):
            raise TypeError("records is not a list of objects")
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise ValueError(f"{path}: not a bench run's merge.json ({exc})") from None
    for r in mine:
        missing = [f for f in fields if f not in r]
        if missing:
            raise ValueError(f"{path}: a record without {', '.join(missing)}")
    return doc


def load(paths: list[Path]) -> list[dict]:
    """The records of the runs at ``paths`` (:func:`read_run`).

    Raises
    ------
    ValueError
        One line naming the file: as :func:`read_run`, or a method that two runs both hold
        for one pair.
    """
    records: list[dict] = []
    for path in paths:
        records += read_run(path)["records"]
    seen: set[tuple[str, str]] = set()
    for r in records:
        key = (r["pair"], r["method"])
        if key in seen:
            raise ValueError(f"{r['method']} is recorded twice for {r['pair']}: give each run once")
        seen.add(key)
    return records


def by_pair(records: list[dict]) -> dict[str, list[dict]]:
    """The overlapping pairs' records, every method's, keyed by pair."""
    out: dict[str, list[dict]] = {}
    for r in records:
        if r["overlap"] > 0:
            out.setdefault(r["pair"], []).append(r)
    return out


@dataclass(frozen=True)
class Bound:
    """One group's counts: its pairs, and how many ``ours`` accepted right, ``ours`` found
    and any method found (:func:`found`), against the target share."""

    group: str
    pairs: int
    ours: int
    success: int
    by_ours: int
    by_any: int
    target: float

    @property
    def reaches(self) -> bool:
        """Whether what any method found reaches the target."""
        return self.by_any >= self.target * self.pairs


def groups(records: Iterable[dict]) -> list[tuple[str, float, Callable[[dict], bool]]]:
    """The report's groups of records (each with ``set`` and ``source``): every set of
    :data:`TARGETS`, then the standard set of each source in ``records``; each as its name,
    its target share and whether a record belongs to it."""
    out: list[tuple[str, float, Callable[[dict], bool]]] = [
        (s, TARGETS[s], lambda r, s=s: r["set"] == s) for s in TARGETS
    ]
    out += [
        (
            f"standard, {src}",
            BUILDING_TARGET,
            lambda r, src=src: (r["set"], r["source"]) == ("standard", src),
        )
        for src in sorted({r["source"] for r in records if r["set"] == "standard"})
    ]
    return out


def bounds(pairs: dict[str, list[dict]], ours: str = "pgvd") -> list[Bound]:
    """The counts per group of :func:`groups`; groups without pairs are left out."""
    first = {p: recs[0] for p, recs in pairs.items()}
    out = []
    for name, target, member in groups(first.values()):
        mine = [p for p, r in first.items() if member(r)]
        if not mine:
            continue
        own = [r for p in mine for r in pairs[p] if r["method"] == ours]
        out.append(
            Bound(
                group=name,
                pairs=len(mine),
                ours=len(own),
                success=sum(r["success"] for r in own),
                by_ours=sum(found(r) for r in own),
                by_any=sum(any(found(r) for r in pairs[p]) for p in mine),
                target=target,
            )
        )
    return out


def rows(pairs: dict[str, list[dict]], ours: str = "pgvd") -> list[str]:
    """Markdown rows of :func:`bounds`: success of ``ours``, pose found by ``ours``, by any
    method, the target and whether the bound reaches it."""
    lines = [
        f"| group | pairs | {ours} success | found by {ours} | found by any method "
        "| target | bound reaches target |",
        "|---|---|---|---|---|---|---|",
    ]
    for b in bounds(pairs, ours):
        lines.append(
            f"| {b.group} | {b.pairs} | {frac(b.success, b.ours)} | {frac(b.by_ours, b.ours)} "
            f"| {frac(b.by_any, b.pairs)} | {100 * b.target:.0f} % "
            f"| {'yes' if b.reaches else 'no'} |"
        )
    return lines


def chart(found_bounds: list[Bound], ours: str, path: Path) -> None:
    """Bars per group: ``ours``'s success, what it found, what any method found; a tick at
    the target."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(10, 4.5))
    x = np.arange(len(found_bounds))
    bars = (
        (f"{ours} accepted right", "tab:green", lambda b: b.success / max(1, b.ours)),
        (f"found by {ours}", "tab:olive", lambda b: b.by_ours / max(1, b.ours)),
        ("found by any method", "tab:gray", lambda b: b.by_any / b.pairs),
    )
    for i, (label, colour, share) in enumerate(bars):
        ax.bar(
            x + (i - 1) * 0.27,
            [100 * share(b) for b in found_bounds],
            0.27,
            color=colour,
            label=label,
        )
    ax.scatter(
        x,
        [100 * b.target for b in found_bounds],
        marker="_",
        s=900,
        color="k",
        zorder=3,
        label="target",
    )
    ax.set_xticks(
        x,
        [b.group.replace("standard, ", "std: ") for b in found_bounds],
        rotation=30,
        ha="right",
        fontsize=8,
    )
    ax.set_ylabel("% of the overlapping pairs")
    ax.set_ylim(0, 120)
    ax.set_title("what pgvd accepts, what the searches find, and the targets (development data)")
    ax.legend(fontsize=8, loc="upper center", ncol=4)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", nargs="+", type=Path, help="merge.json files of bench runs")
    parser.add_argument("--method", default="pgvd", help="the method whose success is shown")
    parser.add_argument("--png", type=Path, metavar="OUT.png", help="also draw the bounds")
    args = parser.parse_args(argv)
    try:
        pairs = by_pair(load(args.runs))
    except ValueError as exc:
        parser.error(str(exc))
    if not pairs:
        parser.error("no overlapping pair in the runs given")
    methods = sorted({r["method"] for recs in pairs.values() for r in recs})
    if args.method not in methods:
        parser.error(f"--method {args.method}: not in the runs ({', '.join(methods)})")
    print("# What any decision could reach: pairs whose true pose was found\n")
    png = "" if args.png is None else f" --png {args.png}"
    print(f"`python3 -m bench ceiling {' '.join(map(str, args.runs))}{png}`\n")
    print(f"Methods: {', '.join(methods)}.\n")
    print(
        "A pair's true pose is found when a method returned it, accepted or not, or when one "
        "of that method's refined finalists reached it (pgvd and its variants record them). "
        f"'found by {args.method}' counts its own. No decision on these hypotheses "
        "accepts more pairs than are found. With the exhaustive search among the runs, a pair "
        "no method found is one whose best pose by a whole-map score over every heading is "
        "not the truth either.\n"
    )
    print("\n".join(rows(pairs, args.method)))
    if args.png is not None:
        chart(bounds(pairs, args.method), args.method, args.png)
        print(f"\nPicture: `{args.png}`.")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
