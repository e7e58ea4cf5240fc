"""Calibration of the merge covariance on real development pairs.

    python3 -m bench covariance collect [--pairs 120] [--seed 10]   # merges, slow
    python3 -m bench covariance fit [--splits 20]                   # fit + report

``collect`` cuts overlapping pairs from the intel and freiburg-079 logs
(:func:`bench.data.pairs.make_pairs`, each map in its own random frame, distinct
segments and frames per pair), merges them, and stores per accepted pair the
pose error ``(tx, ty, psi)`` of the result against the truth and the terms of
:func:`pgvd.alignment.alignment_fit` at the result: ``bench/results/covariance_pairs.json``.

``fit`` splits the pairs in two halves (alternating in the order of their
names, so both halves hold both logs), fits the constants of
:func:`pgvd.covariance.calibrated_covariance` by maximum likelihood on the
first half only, and reports on the second half only: the mean NEES
against the 95 % band of the mean of n chi2(3) (mean 3, variance 6/n), the
share of errors inside the 95 % ellipsoid, and the same for the heading
alone (chi2(1)).  The plain Laplace covariance of the fit, uncalibrated, is
evaluated on the same half for comparison.  ``--splits n`` refits the
models chosen before and with the heading scale on ``n`` random halvings
and says how often each target is met on the held-out half (minutes).
Writes ``covariance.md`` and ``covariance.json`` in ``bench/results/``.

Gross failures (heading error above 2 degrees or B's walls more than 3 cells
off: the bench's definition of a wrong merge) are no Gaussian error; they are
counted and left out of the NEES, and the report says how many.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

import numpy as np
from scipy.stats import chi2

from bench.tables import MAX_CELL_ERROR, MAX_HEADING_DEG
from pgvd.alignment import AlignmentFit
from pgvd.covariance import CALIBRATED, CovarianceModel, calibrated_covariance
from pgvd.grid import matrix_to_pose
from pgvd.inflation import inflate

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared"
RESULTS = ROOT / "bench" / "results"
LOGS = {"intel": "intel-corrected.log.gz", "fr079": "freiburg-079-corrected.log.gz"}
PAIRS_FILE = RESULTS / "covariance_pairs.json"


def pose_error(truth: np.ndarray, estimate: np.ndarray) -> np.ndarray:
    """``(tx, ty, psi)`` of ``estimate`` minus those of ``truth`` (eq. (1)), psi wrapped."""
    pe, pt = matrix_to_pose(estimate), matrix_to_pose(truth)
    dpsi = (pe[0] - pt[0] + np.pi) % (2 * np.pi) - np.pi
    return np.array([pe[1] - pt[1], pe[2] - pt[2], dpsi])


def _wall_error(b_walls: np.ndarray, truth: np.ndarray, estimate: np.ndarray) -> float:
    """Mean distance (cells) between B's walls placed by ``estimate`` and by ``truth``."""
    pts = np.column_stack([b_walls, np.ones(len(b_walls))])
    return float(np.mean(np.linalg.norm(((estimate - truth) @ pts.T)[:2], axis=0)))


def collect(n_pairs: int, seed: int, out: Path) -> int:
    """Merge ``n_pairs`` overlapping pairs per log; store errors and alignment terms."""
    from bench.data.pairs import make_pairs
    from pgvd.alignment import alignment_fit
    from pgvd.carmen import read_carmen
    from pgvd.merge import merge
    from pgvd.params import MergeParams
    from pgvd.walls import WallMap

    params = MergeParams(diagnostics=False)
    records = []
    for log, file in LOGS.items():
        t0 = time.perf_counter()
        scans = read_carmen(SHARED / "logs" / file)
        pairs = make_pairs(scans, n_pairs, 0, seed, log)
        print(f"{log}: {len(pairs)} pairs in {time.perf_counter() - t0:.0f} s", flush=True)
        for p in pairs:
            result = merge(p.a, p.b, params)
            rec = {"name": p.name, "overlap": p.overlap, "accepted": bool(result.accepted)}
            if result.accepted:
                wa = WallMap(p.a.probability(), params.occupied, params.free)
                wb = WallMap(p.b.probability(), params.occupied, params.free)
                fit = alignment_fit(wa.tree, wb.walls, result.matrix)
                heading = abs(np.degrees(pose_error(p.truth, result.matrix)[2]))
                rec.update(
                    error=pose_error(p.truth, result.matrix).tolist(),
                    gross=bool(
                        heading > MAX_HEADING_DEG
                        or _wall_error(wb.walls, p.truth, result.matrix) > MAX_CELL_ERROR
                    ),
                    matrix=np.asarray(result.matrix).tolist(),
                    truth=np.asarray(p.truth).tolist(),
                    reported=np.asarray(result.covariance).tolist(),
                    info=fit.info.tolist(),
                    sigma2=fit.sigma2,
                    centroid=fit.centroid.tolist(),
                    psi=fit.psi,
                    walls_b=len(wb.walls),
                    resolution=p.a.resolution,
                )
            records.append(rec)
            print(f"  {p.name}: overlap {p.overlap:.2f} {rec.get('error')}", flush=True)
    out.write_text(json.dumps({"seed": seed, "pairs_per_log": n_pairs, "records": records}))
    return 0


def alignment(rec: dict) -> AlignmentFit:
    """The :class:`pgvd.alignment.AlignmentFit` stored in a record."""
    return AlignmentFit(
        info=np.array(rec["info"]),
        sigma2=rec["sigma2"],
        centroid=np.array(rec["centroid"]),
        psi=rec["psi"],
    )


def plain_laplace(rec: dict, coarse: int = 4, max_points: int = 4000) -> np.ndarray:
    """The plain Laplace covariance of the fit, before any calibration, from a record.

    ``coarse sigma^2 (J^T J)^-1`` with ``J^T J`` summed over an even subsample of
    at most ``max_points`` of B's walls (the stored ``info`` is over all of them).
    """
    stride = -(-rec["walls_b"] // max_points)
    return coarse * rec["sigma2"] * stride * np.linalg.inv(np.array(rec["info"]))


def nees(errors: np.ndarray, covs: np.ndarray) -> np.ndarray:
    """``e^T Sigma^-1 e`` per pair."""
    return np.einsum("ni,ni->n", errors, np.linalg.solve(covs, errors[..., None])[..., 0])


def _covs(recs: list[dict], model: CovarianceModel) -> np.ndarray:
    return np.array([calibrated_covariance(alignment(r), r["resolution"], model) for r in recs])


def reported(recs: list[dict]) -> np.ndarray:
    """The covariances the merge reports for ``recs``: :data:`pgvd.covariance.CALIBRATED`,
    widened where the evidence is thin (:func:`pgvd.inflation.inflate`), short of the
    model-error term (:mod:`pgvd.model_error`), which needs the walls a record does not keep."""
    calibrated = _covs(recs, CALIBRATED)
    return np.array(
        [inflate(c, alignment(r), r["resolution"]) for c, r in zip(calibrated, recs, strict=True)]
    )


#: Constants of a model that are not fitted (the Laplace covariance, no floor).
FIXED = {
    "correlation": 1.0,
    "misfit_power": 1.0,
    "floor_m": 0.0,
    "floor_rad": 0.0,
    "heading_scale": 1.0,
}
#: Where the search of each fitted constant starts.
START = {
    "correlation": 20.0,
    "misfit_power": 2.0,
    "floor_m": 0.01,
    "floor_rad": 1e-4,
    "heading_scale": 1.0,
}


def fit_model(recs: list[dict], free: tuple[str, ...]) -> CovarianceModel:
    """Maximum-likelihood constants (Gaussian errors) of the named ``free`` fields.

    The others keep their :data:`FIXED` values.  The search runs over the
    logarithms, so every fitted constant stays positive.
    """
    from scipy.optimize import minimize

    errors = np.array([r["error"] for r in recs])

    def model(x: np.ndarray) -> CovarianceModel:
        return CovarianceModel(**{**FIXED, **dict(zip(free, np.exp(x), strict=True))})

    def nll(x: np.ndarray) -> float:
        covs = _covs(recs, model(x))
        return float(0.5 * np.sum(np.linalg.slogdet(covs)[1] + nees(errors, covs)))

    start = np.log([START[n] for n in free])
    best = minimize(nll, start, method="Nelder-Mead", options={"maxiter": 4000, "xatol": 1e-4})
    return model(best.x)


def consistency(errors: np.ndarray, covs: np.ndarray) -> dict:
    """Mean NEES and 95 % coverage, in 3-D and for the heading alone, with their bands."""
    n = len(errors)
    full = nees(errors, covs)
    head = errors[:, 2] ** 2 / covs[:, 2, 2]
    return {
        "n": n,
        "mean_nees": float(full.mean()),
        "band": [3 - 1.96 * np.sqrt(6 / n), 3 + 1.96 * np.sqrt(6 / n)],
        "inside_95": float(np.mean(full < chi2.ppf(0.95, 3))),
        "heading_mean_nees": float(head.mean()),
        "heading_band": [1 - 1.96 * np.sqrt(2 / n), 1 + 1.96 * np.sqrt(2 / n)],
        "heading_inside_95": float(np.mean(head < chi2.ppf(0.95, 1))),
        "median_heading_sigma_deg": float(np.degrees(np.median(np.sqrt(covs[:, 2, 2])))),
        "median_heading_error_deg": float(np.degrees(np.median(np.abs(errors[:, 2])))),
    }


#: The model whose constants are ``pgvd.covariance.CALIBRATED``.
CHOSEN = "calibrated (misfit + floor + heading scale)"
#: Models compared in the report: the free constants of each (see :func:`fit_model`).
MODELS = {
    "laplace, correlation fitted": ("correlation",),
    "misfit": ("correlation", "misfit_power"),
    "misfit + floor": ("correlation", "misfit_power", "floor_m", "floor_rad"),
    "misfit + heading scale": ("correlation", "misfit_power", "heading_scale"),
    CHOSEN: ("correlation", "misfit_power", "floor_m", "floor_rad", "heading_scale"),
}


#: The row of the constants the merge reports with, whatever this run's fit gives.
IN_USE = "in use: pgvd.covariance.CALIBRATED"
#: The row of the covariance the merge reports: those constants, widened where the evidence
#: is thin (:func:`pgvd.inflation.inflate`, constants measured, not fitted).
REPORTED = "reported: CALIBRATED widened by pgvd.inflation"

#: Models refitted on random halvings (``fit --splits``): chosen before and with the heading scale.
RESPLIT = ("misfit + floor", CHOSEN)


def split(records: list[dict]) -> tuple[list[dict], list[dict]]:
    """Usable pairs (accepted, not gross) in two halves, alternating by name."""
    usable = sorted(
        (r for r in records if r["accepted"] and not r["gross"]), key=lambda r: r["name"]
    )
    return usable[0::2], usable[1::2]


def _targets_met(row: dict) -> dict[str, bool]:
    """The targets on one held-out half: NEES in band, 90-98 % inside (3-D, heading)."""
    return {
        "full_in_band": row["band"][0] <= row["mean_nees"] <= row["band"][1],
        "full_inside": 0.90 <= row["inside_95"] <= 0.98,
        "heading_in_band": row["heading_band"][0]
        <= row["heading_mean_nees"]
        <= row["heading_band"][1],
        "heading_inside": 0.90 <= row["heading_inside_95"] <= 0.98,
    }


def random_splits(records: list[dict], n: int, seed: int = 0) -> dict[str, dict]:
    """Held-out figures of the :data:`RESPLIT` models over ``n`` random halvings.

    The alternating split of :func:`split` is one halving of many; the spread
    of the held-out mean NEES from one halving to another, and how often each
    target is met, say how much one table can be read into.
    """
    usable = [r for half in split(records) for r in half]
    rng = np.random.default_rng(seed)
    rows: dict[str, list[dict]] = {name: [] for name in RESPLIT}
    for _ in range(n):
        order = rng.permutation(len(usable))
        fit_half = [usable[i] for i in order[: (len(usable) + 1) // 2]]
        test_half = [usable[i] for i in order[(len(usable) + 1) // 2 :]]
        errors = np.array([r["error"] for r in test_half])
        for name in RESPLIT:
            model = fit_model(fit_half, MODELS[name])
            rows[name].append(consistency(errors, _covs(test_half, model)))
    out = {}
    for name, held_out in rows.items():
        met = [_targets_met(r) for r in held_out]
        out[name] = {
            "splits": n,
            "mean_nees": [r["mean_nees"] for r in held_out],
            "heading_mean_nees": [r["heading_mean_nees"] for r in held_out],
            "met": {k: int(sum(m[k] for m in met)) for k in met[0]},
            "all_met": int(sum(all(m.values()) for m in met)),
        }
    return out


def report(pairs_file: Path, out: Path, splits: int = 0) -> int:
    """Fit on the first half, evaluate on the second; write covariance.md/json.

    With ``splits`` > 0 the :data:`RESPLIT` models are also refitted on that
    many random halvings (:func:`random_splits`).
    """
    doc = json.loads(pairs_file.read_text())
    records = doc["records"]
    fit_half, test_half = split(records)
    errors = np.array([r["error"] for r in test_half])
    rows = {
        "laplace, uncalibrated": consistency(
            errors, np.array([plain_laplace(r) for r in test_half])
        )
    }
    fitted = {}
    for name, free in MODELS.items():
        model = fit_model(fit_half, free)
        fitted[name] = dataclasses.asdict(model)
        rows[name] = consistency(errors, _covs(test_half, model))
        rows[name + " (fit half)"] = consistency(
            np.array([r["error"] for r in fit_half]), _covs(fit_half, model)
        )
    # The constants the merge reports with: when the decision changes, so do the accepted
    # pairs, and this row says whether the constants still hold before they are refitted.
    rows[IN_USE] = consistency(errors, _covs(test_half, CALIBRATED))
    rows[REPORTED] = consistency(errors, reported(test_half))
    summary = {
        "pairs": len(records),
        "accepted": sum(r["accepted"] for r in records),
        "gross": sum(bool(r.get("gross")) for r in records),
        "fit_half": len(fit_half),
        "test_half": len(test_half),
        "seed": doc["seed"],
        "chosen": CHOSEN,
        "models": fitted,
        "rows": rows,
        "random_splits": random_splits(records, splits) if splits else {},
    }
    (out / "covariance.json").write_text(json.dumps(summary, indent=2) + "\n")
    (out / "covariance.md").write_text(markdown(summary))
    print(markdown(summary))
    return 0


def markdown(summary: dict) -> str:
    """The report table."""
    lines = [
        "# Calibration of the merge covariance",
        "",
        "`python3 -m bench covariance collect && python3 -m bench covariance fit"
        + (
            f" --splits {next(iter(summary['random_splits'].values()))['splits']}`"
            if summary["random_splits"]
            else "`"
        ),
        "",
        f"{summary['pairs']} overlapping pairs of the intel and freiburg-079 logs (seed "
        f"{summary['seed']}), {summary['accepted']} accepted, {summary['gross']} of them gross "
        f"errors (left out). Constants fitted (maximum likelihood) on {summary['fit_half']} "
        f"pairs; every row without '(fit half)' is on the other {summary['test_half']} pairs, "
        f"which the fit never saw. '{IN_USE}' is the calibrated covariance the merge uses, on the "
        f"same held-out pairs: the same as the '{CHOSEN}' row when its constants are this "
        "run's fit, and otherwise whether they still hold for the pairs the merge accepts now. "
        f"'{REPORTED}' is what the merge reports: the same, widened where the overlap's "
        "evidence is thin (constants measured in `bench/results/covariance-evidence.md`).",
        "",
        "| covariance | n | mean NEES | chi2(3) 95 % band | inside 95 % ellipsoid "
        "| heading NEES | chi2(1) band | heading inside 95 % | median sigma_psi (deg) "
        "| median abs psi error (deg) |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for name, r in summary["rows"].items():
        lines.append(
            f"| {name} | {r['n']} | {r['mean_nees']:.2f} | {r['band'][0]:.2f}-{r['band'][1]:.2f} "
            f"| {100 * r['inside_95']:.0f} % | {r['heading_mean_nees']:.2f} "
            f"| {r['heading_band'][0]:.2f}-{r['heading_band'][1]:.2f} "
            f"| {100 * r['heading_inside_95']:.0f} % | {r['median_heading_sigma_deg']:.4f} "
            f"| {r['median_heading_error_deg']:.4f} |"
        )
    lines += [
        "",
        "Pairs are independent draws: distinct segments of the logs, each map in its own "
        "random frame. NEES = e^T Sigma^-1 e with e the (tx px, ty px, psi rad) error of the "
        "accepted B -> A matrix about B's pixel origin (eq. (1)); the 95 % ellipsoid is "
        "NEES < chi2(3).ppf(0.95) = 7.81, and 3.84 for the heading alone.",
        "",
        "Fitted constants (`pgvd.covariance.CovarianceModel`; constants not fitted are fixed "
        "at correlation 1, misfit_power 1, no floor, heading_scale 1):",
        "",
    ]
    for name, m in summary["models"].items():
        lines.append(f"- {name}: " + ", ".join(f"{k} = {v:.4g}" for k, v in m.items()))
    if summary["random_splits"]:
        lines += ["", *split_table(summary["random_splits"])]
    return "\n".join(lines) + "\n"


def split_table(resplit: dict[str, dict]) -> list[str]:
    """Markdown of :func:`random_splits`: spread of the held-out figures, targets met."""
    n = next(iter(resplit.values()))["splits"]
    lines = [
        f"Refitted on {n} random halvings of the same pairs (the split above is one halving): "
        "held-out mean NEES min / median / max, and in how many halvings each target is met "
        "(NEES inside its band; 90-98 % inside the 95 % ellipsoid or 3.84).",
        "",
        "| covariance | mean NEES | heading NEES | NEES in band | inside 90-98 % "
        "| heading NEES in band | heading inside 90-98 % | all four |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for name, s in resplit.items():
        spread = [
            "/".join(f"{v:.2f}" for v in (min(x), float(np.median(x)), max(x)))
            for x in (s["mean_nees"], s["heading_mean_nees"])
        ]
        met = s["met"]
        lines.append(
            f"| {name} | {spread[0]} | {spread[1]} | {met['full_in_band']}/{n} "
            f"| {met['full_inside']}/{n} | {met['heading_in_band']}/{n} "
            f"| {met['heading_inside']}/{n} | {s['all_met']}/{n} |"
        )
    return lines


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="command", required=True)
    c = sub.add_parser("collect")
    c.add_argument("--pairs", type=int, default=120, help="overlapping pairs per log")
    c.add_argument("--seed", type=int, default=10)
    c.add_argument("--out", type=Path, default=PAIRS_FILE)
    f = sub.add_parser("fit")
    f.add_argument("--pairs-file", type=Path, default=PAIRS_FILE)
    f.add_argument("--out", type=Path, default=RESULTS)
    f.add_argument(
        "--splits", type=int, default=0, help="also refit on this many random halvings (slow)"
    )
    args = ap.parse_args(argv)
    if args.command == "collect":
        return collect(args.pairs, args.seed, args.out)
    return report(args.pairs_file, args.out, args.splits)


if __name__ == "__main__":
    sys.exit(main())
