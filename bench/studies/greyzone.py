"""The grey zone of the merge's margin, derived from a merge bench run (development only).

A fleet does not reject a pair outright when its best pose's margin (:mod:`pgvd.decision`)
falls short of ``DecisionParams.min_margin``: within the *grey zone* it becomes a candidate that
later versions of the maps confirm or contradict (:mod:`agent.trust`).  This prints, from the
pgvd records of ``bench/results/merge.json`` (development buildings only; the held-out runs
live under ``bench/results/held-out`` and are not read):

- the margins of right poses the first try rejects, per set, and how many lie below the
  floor (lost for good);
- the largest margin of a bad winner (negatives' winners and wrong poses);
- the bad winners the grey zone holds (they become candidates the re-checks must drop);
- the first-try bar's false accepts over bad winners, with the 95 % upper confidence bound
  (Clopper-Pearson one-sided; for zero accepts that is the rule of three, ~3/n).

Run from the project root::

    python3 -m bench greyzone
    python3 -m bench greyzone --merge /tmp/run/merge.json --floor 0.1
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from bench.studies.acceptance import margins
from bench.studies.ceiling import read_run
from bench.tables import OVERLAP_SETS


def upper_bound(k: int, n: int, level: float = 0.95) -> float:
    """One-sided Clopper-Pearson upper bound of a rate seen ``k`` times in ``n`` trials."""
    from scipy.stats import beta

    return 1.0 if k >= n else float(beta.ppf(level, k + 1, n - k))


def report(records: list[dict], floor: float, bar: float) -> list[str]:
    """The lines this study prints."""
    classes = margins(records)
    bad = [m for _, m in classes["wrong"]] + [m for _, m in classes["negative"]]
    lines = [f"first-try bar (min_margin) {bar}, grey floor {floor}"]
    for name in OVERLAP_SETS:
        lost = sorted(m for r, m in classes["right"] if r["set"] == name and m < bar)
        below = sum(m < floor for m in lost)
        span = f"{lost[0]:.2f} .. {lost[-1]:.2f}" if lost else "none"
        lines.append(
            f"right poses rejected ({name}): {len(lost)}, margins {span}; below the floor {below}"
        )
    grey = sum(floor <= m < bar for m in bad)
    accepts = sum(m >= bar for m in bad)
    lines += [
        f"bad winners (wrong {len(classes['wrong'])} + negative {len(classes['negative'])}): "
        f"max margin {max(bad):.2f}",
        f"bad winners in the grey zone [{floor}, {bar}): {grey} of {len(bad)}",
        f"first-try false accepts: {accepts} of {len(bad)}, 95 % upper bound "
        f"{upper_bound(accepts, len(bad)):.3f} (rule of three {3 / len(bad):.3f})",
    ]
    return lines


def main(argv: list[str] | None = None) -> int:
    from pgvd.params import DecisionParams

    results = Path(__file__).resolve().parents[1] / "results"
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--merge", type=Path, default=results / "merge.json")
    parser.add_argument("--floor", type=float, default=0.0, help="lowest margin of the grey zone")
    args = parser.parse_args(argv)
    try:
        records = read_run(args.merge, fields=())["records"]
    except ValueError as exc:
        print(f"greyzone: cannot read records: {exc}", file=sys.stderr)
        return 2
    print("\n".join(report(records, args.floor, DecisionParams.min_margin)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
