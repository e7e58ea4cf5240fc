"""How much the thin-evidence inflation widened the merge covariance, and nothing else.

    python3 -m bench covariance_inflation --before BASE/merge.json --after NEW/merge.json \
        [--out DIR]

Reads the pgvd records of two merge bench runs (:mod:`bench.merge`) on the same pairs,
one without :mod:`pgvd.inflation` (``--before``) and one with it (``--after``), and
reports:

* the outcomes: pairs whose accepted flag or matrix differ between the runs (the
  inflation changes the covariance alone, so there should be none);
* per group of :func:`bench.studies.covariance_wide.groups` (accepted right poses), the
  inflation factor of each pose -- the largest variance factor over all directions,
  the largest eigenvalue of ``Sigma_before^-1 Sigma_after`` -- as median, 90th
  percentile and maximum, and its smallest eigenvalue at its lowest (1: never shrinks).

Writes ``covariance-inflation.md`` to ``--out`` (default: the directory of ``--after``).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from bench.studies.covariance_wide import accepted_right, groups


def pgvd_records(path: Path) -> dict[str, dict]:
    """The pgvd records of a run, by pair name."""
    return {r["pair"]: r for r in json.loads(path.read_text())["records"] if r["method"] == "pgvd"}


def changed_outcomes(before: dict[str, dict], after: dict[str, dict]) -> list[str]:
    """Pairs of either run missing from the other, or accepted or placed differently."""
    changed = sorted(set(before) ^ set(after))
    for name in sorted(set(before) & set(after)):
        b, a = before[name], after[name]
        if b["accepted"] != a["accepted"] or b["matrix"] != a["matrix"]:
            changed.append(name)
    return changed


def factors(before: np.ndarray, after: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Largest and smallest eigenvalue of ``before^-1 after`` for (n, 3, 3) covariances: the
    most and least a pose's variance grew in any direction."""
    if len(before) == 0:
        return np.zeros(0), np.zeros(0)
    eig = np.linalg.eigvals(np.linalg.solve(before, after)).real
    return eig.max(axis=1), eig.min(axis=1)


def markdown(before: dict[str, dict], after: dict[str, dict], sources: tuple[str, str]) -> str:
    """The report of the module docstring."""
    changed = changed_outcomes(before, after)
    right, _ = accepted_right([r for n, r in after.items() if n not in changed])
    lines = [
        "# The thin-evidence inflation of the merge covariance (pgvd.inflation)",
        "",
        f"`python3 -m bench covariance_inflation --before {sources[0]} --after {sources[1]}`: "
        f"{len(after)} pgvd pairs; {len(changed)} with a different outcome (accepted or "
        "matrix)" + (f": {', '.join(changed)}" if changed else "") + ".",
        "",
        "Factor of a pose: the largest eigenvalue of Sigma_before^-1 Sigma_after (the most its "
        "variance grew in any direction); smallest: the least (1 = no direction shrank).",
        "",
        "| poses | n | median factor | p90 | max | smallest eigenvalue |",
        "|---|---|---|---|---|---|",
    ]
    for name, members in groups(right).items():
        cov = [
            np.array([r["result"]["covariance"] for r in members_of], dtype=float)
            for members_of in ([before[r["pair"]] for r in members], members)
        ]
        most, least = factors(*cov)
        lines.append(
            f"| {name} | {len(members)} | {np.median(most):.2f} | "
            f"{np.percentile(most, 90):.2f} | {most.max():.2f} | {least.min():.4f} |"
        )
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--before", type=Path, required=True, help="merge.json without the inflation")
    ap.add_argument("--after", type=Path, required=True, help="merge.json with it")
    ap.add_argument("--out", type=Path, help="default: the directory of --after")
    args = ap.parse_args(argv)
    try:
        before, after = pgvd_records(args.before), pgvd_records(args.after)
    except (OSError, ValueError, KeyError) as e:
        print(f"cannot read the merge records: {e}", file=sys.stderr)
        return 2
    text = markdown(before, after, (str(args.before), str(args.after)))
    out = args.out or args.after.parent
    out.mkdir(parents=True, exist_ok=True)
    (out / "covariance-inflation.md").write_text(text)
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
