"""The merge's reported covariance on the wide merge bench: is it consistent there too?

The covariance (eq. (3), :func:`pgvd.covariance.calibrated_covariance`) is calibrated by
:mod:`bench.covariance` on pairs of the intel and freiburg-079 *logs* only, and widened
where an overlap's evidence is thin (:mod:`pgvd.inflation`, constants measured on those
logs' pairs, :mod:`bench.studies.covariance_evidence`), plus the disagreement of the
overlap's parts where a map is bent (:mod:`pgvd.model_error`, weight checked by
:mod:`bench.studies.covariance_model_error`).  This reads
the pgvd records of a merge bench run (``merge.json``, :mod:`bench.merge`) and measures
the covariance each accepted right pose reported against that pose's error: on the
simulated-lidar maps of every development building, on low-overlap and on drifted pairs,
which the calibration did not see (the bench's log pairs are other cuts of the
calibration's two logs; the report has a row for the buildings outside it).

Per group: the mean NEES ``e^T Sigma^-1 e`` (``e`` the ``(tx px, ty px, psi rad)`` error
about B's pixel origin, :func:`bench.covariance.pose_error`) against the 95 % band of a
mean of n chi2(3), the share inside the 95 % ellipsoid, and the heading alone.  A mean
below the band is a covariance too wide (safe for fusion, but it throws information
away); above, one too narrow.  Accepted wrong poses are no Gaussian error: they are
counted apart.  The fr079 gmapping pairs are left out: their truth is itself a fit
(``bench/results/gmapping_truth.md``).

Run from the project root after ``python3 -m bench merge`` (which writes both files at the
end of a run)::

    python3 -m bench covariance_wide     # reads bench/results/merge.json

Writes ``covariance-wide.md`` and ``covariance-wide.png`` (NEES of every pose against the
chi2(3) quantiles).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from bench.covariance import consistency, nees, pose_error
from bench.tables import OVERLAP_SETS, pose_right, records_main, rerun

#: Sources whose pairs :mod:`bench.covariance` draws its calibration pairs from (their logs).
CALIBRATION_BUILDINGS = ("intel", "fr079")


def accepted_right(records: list[dict]) -> tuple[list[dict], int]:
    """The pgvd records of overlapping pairs accepted at a right pose, and how many were
    accepted at a wrong one."""
    mine = [
        r for r in records if r["method"] == "pgvd" and r["kind"] == "overlap" and r["accepted"]
    ]
    right = [r for r in mine if pose_right(r)]
    return right, len(mine) - len(right)


def errors_and_covariances(records: list[dict]) -> tuple[np.ndarray, np.ndarray]:
    """``(n, 3)`` pose errors and ``(n, 3, 3)`` reported covariances of ``records``."""
    errors = np.array([pose_error(np.array(r["truth"]), np.array(r["matrix"])) for r in records])
    covs = np.array([r["result"]["covariance"] for r in records], dtype=float)
    return errors.reshape(-1, 3), covs.reshape(-1, 3, 3)


def groups(records: list[dict]) -> dict[str, list[dict]]:
    """The rows of the report: every pose, each set, the buildings outside the calibration,
    and each source."""
    out = {"all": records}
    for name in OVERLAP_SETS:
        out[name] = [r for r in records if r["set"] == name]
    out["buildings the calibration never saw"] = [
        r for r in records if r["building"] not in CALIBRATION_BUILDINGS
    ]
    for source in sorted({r["source"] for r in records}):
        out[source] = [r for r in records if r["source"] == source]
    return {k: v for k, v in out.items() if v}


def _row(name: str, stats: dict) -> str:
    # the bands are normal approximations of the mean of n chi2: clipped at 0 for small n
    lo, hi = max(0.0, stats["band"][0]), stats["band"][1]
    hlo, hhi = max(0.0, stats["heading_band"][0]), stats["heading_band"][1]
    return (
        f"| {name} | {stats['n']} | {stats['mean_nees']:.2f} | {lo:.2f}-{hi:.2f} | "
        f"{stats['inside_95']:.0%} | {stats['heading_mean_nees']:.2f} | {hlo:.2f}-{hhi:.2f} | "
        f"{stats['heading_inside_95']:.0%} |"
    )


def markdown(records: list[dict], source: str, command: str) -> str:
    """The report of the module docstring, from a run's records."""
    right, wrong = accepted_right(records)
    lines = [
        "# The reported covariance on the wide merge bench",
        "",
        f"`{command}`",
        "",
        f"From the pgvd records of `{source}`: every "
        f"overlapping pair accepted at a right pose ({len(right)}; {wrong} accepted at a wrong "
        "pose are left out, and so are the fr079 gmapping pairs, whose truth is itself a "
        "fit). The covariance was calibrated on other pairs of the intel "
        "and freiburg-079 logs only (`bench/results/covariance.md`), is widened where the "
        "evidence is thin with constants measured on them "
        "(`bench/results/covariance-evidence.md`), and adds the disagreement of the overlap's "
        "quadrants (pgvd.model_error), its weight checked leaving each development building "
        "out (`bench/results/covariance-model-error.md`).",
        "",
        "| poses | n | mean NEES | chi2(3) 95 % band of the mean | inside 95 % ellipsoid | "
        "heading NEES | chi2(1) band | heading inside 95 % |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for name, members in groups(right).items():
        lines.append(_row(name, consistency(*errors_and_covariances(members))))
    lines += [
        "",
        "A mean NEES below its band is a covariance wider than the errors (conservative), above "
        "it one narrower; a band is for n independent poses, so a group of a few pairs says "
        "little.",
    ]
    return "\n".join(lines) + "\n"


def chart(records: list[dict], path: Path) -> None:
    """Each accepted right pose's NEES against the chi2(3) quantile of its rank, per set."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from scipy.stats import chi2

    right, _ = accepted_right(records)
    fig, ax = plt.subplots(figsize=(6, 5))
    top = 0.0  # the diagonal spans the largest quantile and the largest NEES
    for name in OVERLAP_SETS:
        members = [r for r in right if r["set"] == name]
        if not members:
            continue
        values = np.sort(nees(*errors_and_covariances(members)))
        quantiles = chi2.ppf((np.arange(len(values)) + 0.5) / len(values), 3)
        ax.plot(quantiles, values, "o", ms=4, label=f"{name} ({len(values)})")
        top = max(top, quantiles.max(), values.max())
    ax.plot([0, top], [0, top], "k--", lw=1, label="consistent")
    ax.set_xlabel("chi2(3) quantile")
    ax.set_ylabel("NEES of the accepted pose")
    ax.set_title("Reported covariance on the wide bench (right accepted poses)")
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def write(records: list[dict], out: Path, source: str) -> str:
    """Write ``covariance-wide.md`` and ``covariance-wide.png`` to ``out``; returns the
    markdown."""
    text = markdown(records, Path(source).name, rerun("covariance_wide", Path(source)))
    out.mkdir(parents=True, exist_ok=True)
    (out / "covariance-wide.md").write_text(text)
    chart(records, out / "covariance-wide.png")
    return text


def main(argv: list[str] | None = None) -> int:
    return records_main(argv, __doc__.splitlines()[0], write)


if __name__ == "__main__":
    raise SystemExit(main())
