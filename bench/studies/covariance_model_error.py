"""The weight of the model-error term of the merge covariance, left out one building at a time.

    python3 -m bench covariance_model_error --before BASE/merge.json --after NEW/merge.json \
        --after-scale 1 [--out DIR]

Reads the pgvd records of two development merge bench runs (:mod:`bench.merge`) on the same
pairs: ``--before`` reports the covariance without the model-error term of
:mod:`pgvd.model_error`, ``--after`` with it at weight ``--after-scale``.  The decision does not
read the covariance, so both runs must accept the same pairs at the same matrices; the
report lists any that differ.  Since the term is added, ``Sigma(c) = Sigma_before + c M`` with
``M = (Sigma_after - Sigma_before) / after_scale`` for every accepted right pose (the pooled
frame's Jacobian of :func:`pgvd.pooling.covariance_from_pooled` is linear in the covariance),
and any weight ``c`` is evaluated without another run.

The weight is fitted by maximum likelihood (Gaussian pose errors, ``c >= 0``), on every
accepted right pose and on the drifted ones alone (those with a bent map, the error the term
is for).  Each development building is left out in turn: ``c`` is fitted on the others' poses
and the building's own poses are scored with it (mean NEES against the chi2(3) band, share
inside the 95 % ellipsoid), and with the weight the merge uses
(:data:`pgvd.model_error.MODEL_ERROR_SCALE`).  Writes ``covariance-model-error.md`` and
``.json`` to ``--out`` (default: the directory of ``--after``).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
from scipy.optimize import minimize_scalar

from bench.covariance import consistency, nees
from bench.studies.covariance_inflation import changed_outcomes, pgvd_records
from bench.studies.covariance_wide import accepted_right, errors_and_covariances, groups
from pgvd.model_error import MODEL_ERROR_SCALE

#: Largest weight searched: far beyond where the term would dwarf the rest.
MAX_SCALE = 1e3


def model_terms(
    before: dict[str, dict], after: dict[str, dict], after_scale: float
) -> tuple[list[dict], np.ndarray, np.ndarray, np.ndarray]:
    """Accepted right poses of both runs with equal outcomes: their records, errors, the
    covariance without the term and ``M``."""
    if not after_scale > 0:
        raise ValueError(f"the weight of the --after run must be > 0, got {after_scale}")
    changed = set(changed_outcomes(before, after))
    right, _ = accepted_right([r for n, r in sorted(after.items()) if n not in changed])
    errors, with_term = errors_and_covariances(right)
    _, base = errors_and_covariances([before[r["pair"]] for r in right])
    return right, errors, base, (with_term - base) / after_scale


def negative_log_likelihood(
    scale: float, errors: np.ndarray, base: np.ndarray, term: np.ndarray
) -> float:
    """Gaussian negative log-likelihood of ``errors`` under ``base + scale term`` (no constant)."""
    covs = base + scale * term
    return float(0.5 * np.sum(np.linalg.slogdet(covs)[1] + nees(errors, covs)))


def fit_scale(errors: np.ndarray, base: np.ndarray, term: np.ndarray) -> float:
    """The maximum-likelihood weight ``c`` in ``[0, MAX_SCALE]``, searched over ``log(1 + c)``."""

    def cost(x: float) -> float:
        return negative_log_likelihood(np.expm1(x), errors, base, term)

    best = minimize_scalar(cost, bounds=(0.0, np.log1p(MAX_SCALE)), method="bounded")
    at_zero = cost(0.0)
    return 0.0 if at_zero <= best.fun else float(np.expm1(best.x))


#: The pairs a weight is fitted on: every accepted right pose, or the drifted ones alone
#: (those with a map bent by drift, the model error the term is for).
FITS = {"all poses": None, "drifted poses": "drifted"}


def leave_one_building_out(
    records: list[dict], errors: np.ndarray, base: np.ndarray, term: np.ndarray, scale: float
) -> dict[str, dict]:
    """Per building: the weight fitted on the others' poses (each of :data:`FITS`), and its own
    poses' consistency without the term, with each fitted weight and with ``scale``."""
    buildings = np.array([r["building"] for r in records])
    sets = np.array([r["set"] for r in records])
    out = {}
    for building in sorted(set(buildings)):
        own = buildings == building
        row = {
            "without": consistency(errors[own], base[own]),
            "in_use": consistency(errors[own], base[own] + scale * term[own]),
        }
        for name, only in FITS.items():
            fit_on = ~own if only is None else ~own & (sets == only)
            fitted = fit_scale(errors[fit_on], base[fit_on], term[fit_on])
            row[name] = {
                "scale": fitted,
                "with": consistency(errors[own], base[own] + fitted * term[own]),
            }
        out[building] = row
    return out


def summary(
    before: dict[str, dict], after: dict[str, dict], after_scale: float, scale: float
) -> dict:
    """Everything the report shows, from the two runs' records, with ``scale`` the weight in
    use."""
    records, errors, base, term = model_terms(before, after, after_scale)
    sets = np.array([r["set"] for r in records])
    index = {r["pair"]: i for i, r in enumerate(records)}
    rows = {}
    for name, members in groups(records).items():
        i = [index[r["pair"]] for r in members]
        grown = np.linalg.eigvals(np.linalg.solve(base[i], base[i] + scale * term[i])).real
        rows[name] = {
            "without": consistency(errors[i], base[i]),
            "with": consistency(errors[i], base[i] + scale * term[i]),
            "median_factor": float(np.median(grown.max(axis=1))),
            "max_factor": float(grown.max()),
        }
    fitted = {}
    for name, only in FITS.items():
        on = np.ones(len(sets), bool) if only is None else sets == only
        fitted[name] = fit_scale(errors[on], base[on], term[on])
    return {
        "changed": changed_outcomes(before, after),
        "pairs": len(after),
        "scale": scale,
        "fitted": fitted,
        "leave_one_out": leave_one_building_out(records, errors, base, term, scale),
        "rows": rows,
    }


def _stats(s: dict) -> str:
    lo, hi = max(0.0, s["band"][0]), s["band"][1]
    return f"{s['mean_nees']:.2f} | {lo:.2f}-{hi:.2f} | {s['inside_95']:.0%}"


def _nees(s: dict) -> str:
    return f"{s['mean_nees']:.2f} | {s['inside_95']:.0%}"


def markdown(doc: dict, command: str) -> str:
    """The report of the module docstring."""
    changed = doc["changed"]
    fits = ", ".join(f"{name}: c = {c:.3g}" for name, c in doc["fitted"].items())
    lines = [
        "# The model-error term of the merge covariance (pgvd.model_error)",
        "",
        f"`{command}`: {doc['pairs']} pgvd pairs of the development bench; {len(changed)} "
        "with a different outcome (accepted or matrix)"
        + (f": {', '.join(changed)}" if changed else "")
        + ".",
        "",
        "Reported covariance: the calibrated one widened where the evidence is thin, plus c M, "
        "M the cluster-robust (sandwich) covariance of the fit with the overlap's four "
        "quadrants as clusters (what the parts of a bent map disagree by). Weight in use: "
        f"**c = {doc['scale']:.3g}**. Maximum likelihood on the accepted right poses of every "
        f"development building: {fits}.",
        "",
        "## Each development building left out",
        "",
        "c fitted on the other buildings' poses (all of them, or their drifted ones); the "
        "building's own poses scored without the term, with each fitted c and with the c in "
        "use: mean NEES (against the chi2(3) band of the mean) and the share inside the 95 % "
        "ellipsoid.",
        "",
        "| building left out | n | chi2(3) band | NEES without | inside | c fitted on all poses "
        "| NEES | inside | c fitted on drifted poses | NEES | inside | NEES, c in use | inside |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for building, row in doc["leave_one_out"].items():
        every, drifted = row["all poses"], row["drifted poses"]
        band = row["without"]["band"]
        lines.append(
            f"| {building} | {row['without']['n']} | {max(0.0, band[0]):.2f}-{band[1]:.2f} "
            f"| {_nees(row['without'])} | {every['scale']:.3g} | {_nees(every['with'])} "
            f"| {drifted['scale']:.3g} | {_nees(drifted['with'])} | {_nees(row['in_use'])} |"
        )
    lines += [
        "",
        f"## Every development pose at the c in use ({doc['scale']:.3g})",
        "",
        "Factor: the largest eigenvalue of Sigma_without^-1 Sigma_with (the most a pose's "
        "variance grew in any direction).",
        "",
        "| poses | n | mean NEES without | band | inside 95 % without | mean NEES with | band "
        "| inside 95 % with | median factor | max factor |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for name, row in doc["rows"].items():
        lines.append(
            f"| {name} | {row['with']['n']} | {_stats(row['without'])} | {_stats(row['with'])} "
            f"| {row['median_factor']:.2f} | {row['max_factor']:.2f} |"
        )
    lines += [
        "",
        "NEES = e^T Sigma^-1 e, e the (tx px, ty px, psi rad) error of the accepted pose about "
        "B's pixel origin; a mean below its band is a covariance wider than the errors, above "
        "it one narrower. Held-out buildings are not read here.",
    ]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--before", type=Path, required=True, help="merge.json without the term")
    ap.add_argument("--after", type=Path, required=True, help="merge.json with it")
    ap.add_argument(
        "--after-scale", type=float, required=True, help="the term's weight in the --after run"
    )
    ap.add_argument("--out", type=Path, help="default: the directory of --after")
    args = ap.parse_args(argv)
    try:
        before, after = pgvd_records(args.before), pgvd_records(args.after)
        doc = summary(before, after, args.after_scale, MODEL_ERROR_SCALE)
    except (OSError, ValueError, KeyError) as e:
        print(f"covariance_model_error: {e}", file=sys.stderr)
        return 2
    command = (
        f"python3 -m bench covariance_model_error --before {args.before} --after {args.after} "
        f"--after-scale {args.after_scale:g}"
    )
    text = markdown(doc, command)
    out = args.out or args.after.parent
    out.mkdir(parents=True, exist_ok=True)
    (out / "covariance-model-error.md").write_text(text)
    (out / "covariance-model-error.json").write_text(json.dumps(doc, indent=2) + "\n")
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
