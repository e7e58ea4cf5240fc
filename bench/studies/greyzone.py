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
  (Clopper-Pearson one-sided; for zero accepts that is the rule of three, ~3/n);
- the high bar of :mod:`agent.trust` (a search's accept below it is provisional): where an
  exponential tail fitted to the bad winners' margins above the floor puts 1 bad winner in
  1,000, and the fleet's ``HIGH_BAR`` with its false accepts, bound and the right poses it
  leaves provisional.

Run from the project root::

    python3 -m bench greyzone
    python3 -m bench greyzone --merge /tmp/run/merge.json --floor 0.1
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

from bench.studies.acceptance import margins
from bench.studies.ceiling import read_run
from bench.tables import OVERLAP_SETS


def upper_bound(k: int, n: int, level: float = 0.95) -> float:
    """One-sided Clopper-Pearson upper bound of a rate seen ``k`` times in ``n`` trials."""
    from scipy.stats import beta

    return 1.0 if k >= n else float(beta.ppf(level, k + 1, n - k))


#: The rate of bad winners at or above the high bar the tail fit aims at.
TAIL_RATE = 1e-3


def _tail(bad: list[float], floor: float) -> tuple[float, float]:
    """The exponential tail of the ``bad`` margins above ``floor`` (maximum likelihood: the
    scale is their mean excess): the share of them above it, and the scale."""
    excess = [m - floor for m in bad if m > floor]
    if not excess:
        raise ValueError(f"no bad winner above the floor {floor}: no tail to fit")
    return len(excess) / len(bad), sum(excess) / len(excess)


def tail_bar(bad: list[float], floor: float, rate: float = TAIL_RATE) -> float:
    """The margin above which the tail of the ``bad`` margins (:func:`_tail`) leaves a share
    ``rate`` of them."""
    share, scale = _tail(bad, floor)
    return floor + scale * math.log(share / rate)


def tail_share(bad: list[float], floor: float, margin: float) -> float:
    """The share of bad winners at or above ``margin`` by their tail (:func:`_tail`)."""
    share, scale = _tail(bad, floor)
    return share * math.exp(-(margin - floor) / scale)


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
        *high_bar_lines(classes, bad, floor, bar),
    ]
    return lines


def high_bar_lines(
    classes: dict[str, list[tuple[dict, float]]], bad: list[float], floor: float, bar: float
) -> list[str]:
    """What :func:`tail_bar` says of the high bar, and how ``agent.trust.HIGH_BAR`` fares."""
    from agent.trust import HIGH_BAR

    above = sum(m >= HIGH_BAR for m in bad)
    right = [m for _, m in classes["right"]]
    return [
        f"high bar by the tail above {floor} (1 bad winner in {1 / TAIL_RATE:.0f}): "
        f"{tail_bar(bad, floor):.2f}; the merge's bar {bar} leaves "
        f"1 in {1 / tail_share(bad, floor, bar):.0f}",
        f"agent.trust.HIGH_BAR {HIGH_BAR}: bad winners at or above it {above} of {len(bad)}, "
        f"95 % upper bound {upper_bound(above, len(bad)):.3f}; right winners at or above it "
        f"{sum(m >= HIGH_BAR for m in right)} of {len(right)}, provisional (in [{bar}, "
        f"{HIGH_BAR})) {sum(bar <= m < HIGH_BAR for m in right)}",
    ]


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
