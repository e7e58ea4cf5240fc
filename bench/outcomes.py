"""Compare two merge bench runs record by record: same outcomes, same accepted poses.

A change meant to make the merge faster must not change what it decides.  This reads two
``merge.json`` files (:mod:`bench.merge`), pairs their records of one method by pair name,
and lists every pair whose accepted/rejected outcome or success differs, and every pair
accepted by both whose poses differ by more than ``--cells`` (the largest displacement of
B's corners, in cells) or ``--degrees``::

    python3 -m bench outcomes bench/results/merge.json NEW/merge.json [--method pgvd] [--subset]

``--subset``: the new run covers only some of the reference's pairs (``--sources``); the
pairs it lacks are not differences.

Exit 0 when the runs agree, 1 when they do not (the differences on stdout), 2 for bad input.
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from pgvd.grid import heading


@dataclass
class Comparison:
    """What differs between a reference run and a new one, for one method."""

    compared: int = 0
    missing: list[str] = field(default_factory=list)  # pairs of the reference not in the new run
    outcome: list[str] = field(default_factory=list)  # accepted or success differs
    pose: list[str] = field(default_factory=list)  # both accepted, poses apart

    @property
    def same(self) -> bool:
        """True when no pair is missing and no outcome or pose differs."""
        return not (self.missing or self.outcome or self.pose)


def pose_gap(m1: np.ndarray, m2: np.ndarray, shape_b: tuple[int, int]) -> tuple[float, float]:
    """(cells, degrees) between two B->A pixel matrices: the largest displacement of B's four
    corners and the heading difference."""
    h, w = shape_b
    corners = np.array([[0, 0, 1], [w - 1, 0, 1], [0, h - 1, 1], [w - 1, h - 1, 1]], float).T
    cells = float(np.hypot(*((m1 - m2) @ corners)[:2]).max())
    degrees = abs(float(np.degrees(np.angle(np.exp(1j * (heading(m1) - heading(m2)))))))
    return cells, degrees


def compare_runs(
    reference: list[dict],
    new: list[dict],
    method: str,
    cells: float,
    degrees: float,
    subset: bool = False,
) -> Comparison:
    """The differences of ``method``'s records of ``new`` from those of ``reference``.

    Parameters
    ----------
    reference, new : list of dict
        The ``records`` of two ``merge.json`` files.
    method : str
        The method whose records are compared.
    cells, degrees : float
        Largest pose difference of a pair both runs accept (:func:`pose_gap`).
    subset : bool, optional
        Compare only the pairs ``new`` has; else a pair it lacks is listed as missing.

    Returns
    -------
    Comparison
        One line per differing pair, by kind.
    """
    ours = {r["pair"]: r for r in new if r["method"] == method}
    out = Comparison()
    for ref in (r for r in reference if r["method"] == method):
        name = ref["pair"]
        rec = ours.get(name)
        if rec is None:
            if not subset:
                out.missing.append(name)
            continue
        out.compared += 1
        if (ref["accepted"], ref["success"]) != (rec["accepted"], rec["success"]):
            out.outcome.append(
                f"{name} ({ref['set']}/{ref['kind']}): accepted {ref['accepted']} -> "
                f"{rec['accepted']}, success {ref['success']} -> {rec['success']}"
            )
        elif ref["accepted"]:
            gap = pose_gap(np.array(ref["matrix"]), np.array(rec["matrix"]), ref["shape_b"])
            if gap[0] > cells or gap[1] > degrees:
                out.pose.append(f"{name}: pose moved {gap[0]:.2f} cells, {gap[1]:.3f} deg")
    return out


def _records(path: Path) -> list[dict]:
    """The records of a ``merge.json``; ValueError with the path when it has none."""
    try:
        doc = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as error:
        raise ValueError(f"{path}: not a readable merge.json ({error})") from error
    if not isinstance(doc, dict) or not isinstance(doc.get("records"), list):
        raise ValueError(f"{path}: no records (not a merge.json of python3 -m bench merge)")
    return doc["records"]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("reference", type=Path, help="merge.json of the reference run")
    parser.add_argument("new", type=Path, help="merge.json of the run to check")
    parser.add_argument("--method", default="pgvd")
    parser.add_argument("--cells", type=float, default=1.0, help="largest pose gap, cells")
    parser.add_argument("--degrees", type=float, default=0.1, help="largest heading gap")
    parser.add_argument(
        "--subset", action="store_true", help="compare only the pairs the new run has"
    )
    args = parser.parse_args(argv)
    try:
        reference, new = _records(args.reference), _records(args.new)
    except ValueError as error:
        print(f"bench outcomes: {error}", file=sys.stderr)
        return 2
    result = compare_runs(reference, new, args.method, args.cells, args.degrees, args.subset)
    for kind in ("missing", "outcome", "pose"):
        for line in getattr(result, kind):
            print(f"{kind}: {line}")
    verdict = "same outcomes and poses" if result.same else "runs differ"
    print(f"{args.method}: {result.compared} pairs compared, {verdict}")
    return 0 if result.same else 1


if __name__ == "__main__":
    raise SystemExit(main())
