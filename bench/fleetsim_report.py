"""What a simulated fleet measured (:func:`summarise`), and its tables and plots
(:func:`write_results`), beside :mod:`bench.fleet`'s counts of real processes."""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from bench.fleetsim_fleet import SimFleet
from bench.fleetsim_net import Traffic

#: The issue's targets: per-agent CPU per epoch at the largest N over that at 16, and full
#: searches per epoch per robot, at most.
CPU_RATIO_TARGET = 3.0
SEARCHES_TARGET = 1.0
#: Counts compared with bench.fleet's at the same N, and how far apart they may be.
VALIDATED = (
    "searches",
    "checks",
    "searches_per_epoch",
    "checks_per_epoch",
    "epochs_per_robot",
    "messages_received_per_robot",
    "bytes_received_per_robot",
    "bytes_sent_per_robot",
)
TOLERANCE = 0.10


def _mean(values) -> float:
    return float(np.mean(values)) if len(values) else 0.0


def summarise(fleet: SimFleet, wall_s: float) -> dict:
    """The measures of one simulated fleet (the module docstring of :mod:`bench.fleetsim`)."""
    robots = list(fleet.robots.values())
    n = len(robots)
    counts = [r.node.counters.snapshot()["counts"] for r in robots]
    kinds = ("searches", "searches_gated", "checks", "epochs")
    total = {k: sum(c.get(k, 0) for c in counts) for k in kinds}
    epochs = max(total["epochs"] / n, 1.0)
    traffic = [fleet.net.traffic.get(r.name, Traffic()) for r in robots]
    worker = [r.worker_cpu for r in robots]
    host = [r.host_cpu for r in robots]
    cpu = [w + h for w, h in zip(worker, host, strict=True)]
    rebuilds = fleet.rebuilds.charged
    grid_bytes = [fleet.own_component_bytes(r) for r in robots]
    recv_bytes = _mean([t.received_bytes for t in traffic])
    recv_msgs = _mean([t.received_messages for t in traffic])
    return {
        "robots": n,
        "speed": fleet.sc.speed,
        "agreed": fleet.agreed_at is not None,
        "agreement_s": None
        if fleet.agreed_at is None
        else round(fleet.agreed_at - (fleet.last_update or 0.0), 2),
        "sim_s": round(fleet.loop.now, 1),
        "wall_s": round(wall_s, 1),
        "epochs_per_robot": round(epochs, 2),
        "searches": total["searches"],
        "checks": total["checks"],
        "searches_per_epoch": round(total["searches"] / epochs, 2),
        "checks_per_epoch": round(total["checks"] / epochs, 2),
        "searches_per_epoch_per_robot": round(total["searches"] / epochs / n, 3),
        "checks_per_epoch_per_robot": round(total["checks"] / epochs / n, 3),
        "searches_gated": total["searches_gated"],
        "searches_gated_per_epoch_per_robot": round(total["searches_gated"] / epochs / n, 3),
        "gate_verdicts_computed": fleet.gates.computed,
        "messages_received_per_robot": round(recv_msgs, 1),
        "bytes_received_per_robot": int(recv_bytes),
        "bytes_sent_per_robot": int(_mean([t.sent_bytes for t in traffic])),
        "messages_received_per_robot_per_epoch": round(recv_msgs / epochs, 1),
        "bytes_received_per_robot_per_epoch": int(recv_bytes / epochs),
        "messages_lost": sum(t.lost for t in traffic),
        "rebuilds_per_agent": round(len(rebuilds) / n, 1),
        "rebuild_cpu_s_mean": round(_mean(rebuilds), 4),
        "rebuild_cpu_s_per_agent": round(sum(rebuilds) / n, 3),
        "rebuilds_run_with_fusion": len(fleet.rebuilds.samples),
        "fusion_cpu_s_per_map": round(fleet.rebuilds.per_map(), 5),
        "worker_cpu_s_per_agent": round(_mean(worker), 3),
        "host_cpu_s_per_agent": round(_mean(host), 3),
        "cpu_s_per_agent": round(_mean(cpu), 3),
        "cpu_s_per_agent_per_epoch": round(_mean(cpu) / epochs, 4),
        "grid_bytes_per_agent": int(_mean(grid_bytes)),
        "grid_bytes_max_agent": int(max(grid_bytes)),
        **cpu_terms(fleet, epochs),
    }


#: The terms of an agent's CPU: stand-ins' charges by kind (:class:`bench.fleetsim_core.Meter`),
#: the core's own work in its worker, and its host's (decoding, encoding, the source).
CPU_TERMS = ("search", "check", "gate", "rebuild", "core", "host")


def cpu_terms(fleet: SimFleet, epochs: float) -> dict:
    """Each of :data:`CPU_TERMS`, in CPU seconds per agent per epoch."""
    robots = list(fleet.robots.values())
    spent = dict(fleet.meter.by_kind)
    spent["core"] = sum(r.core_cpu for r in robots)
    spent["host"] = sum(r.host_cpu for r in robots)
    per = len(robots) * epochs
    return {f"cpu_{t}_s_per_agent_per_epoch": round(spent.get(t, 0.0) / per, 4) for t in CPU_TERMS}


def add_relative(rows: list[dict]) -> None:
    """Per-agent CPU per epoch relative to 16 robots (or to the fewest run, if no 16)."""
    ref = next((r for r in rows if r["robots"] == 16), min(rows, key=lambda r: r["robots"]))
    base = ref["cpu_s_per_agent_per_epoch"] or 1e-9
    b0 = ref["bytes_received_per_robot_per_epoch"] or 1
    for r in rows:
        r["cpu_reference_robots"] = ref["robots"]
        r["cpu_per_epoch_vs_reference"] = round(r["cpu_s_per_agent_per_epoch"] / base, 2)
        # linear growth in N keeps this at most 1
        growth = r["bytes_received_per_robot_per_epoch"] / b0
        r["bytes_growth_over_linear"] = round(growth / (r["robots"] / ref["robots"]), 2)


def load_real_runs(paths: list[Path]) -> list[list[dict]]:
    """The rows of each :mod:`bench.fleet` result file; ValueError (one line) if one is bad."""
    runs = []
    for path in paths:
        try:
            rows = json.loads(path.read_text())
        except (OSError, ValueError) as exc:
            raise ValueError(f"cannot read bench.fleet results {path}: {exc}") from None
        if not isinstance(rows, list) or not all(
            isinstance(r, dict) and "robots" in r for r in rows
        ):
            raise ValueError(f"not a bench.fleet result file (a list of rows by robots): {path}")
        runs.append(rows)
    return runs


def validation(rows: list[dict], real_runs: list[list[dict]]) -> list[dict]:
    """Each count of ``rows`` beside bench.fleet's at the same N over every real run.

    The real runs differ from one another (registrations race on a shared machine), so the
    simulated count is set against their mean and their spread: ``spread`` is the range of
    the real values over their mean, ``difference`` the simulated count's distance from the
    mean over the mean, and ``within`` whether that distance is at most :data:`TOLERANCE`
    or the count lies inside the real runs' range.
    """
    out = []
    for row in rows:
        refs = [r for run in real_runs for r in run if r["robots"] == row["robots"]]
        for key in VALIDATED:
            real = [float(r[key]) for r in refs if key in r]
            if not real:
                continue
            mean = float(np.mean(real))
            diff = (row[key] - mean) / mean if mean else float("nan")
            spread = (max(real) - min(real)) / mean if mean else float("nan")
            within = abs(diff) <= TOLERANCE or min(real) <= row[key] <= max(real)
            out.append(
                {"robots": row["robots"], "measure": key, "fleet": real,
                 "fleet_mean": round(mean, 2), "spread": round(spread, 3),
                 "fleetsim": row[key], "difference": round(diff, 3), "within": within}
            )  # fmt: skip
    return out


COLUMNS = (
    ("robots", "N"),
    ("agreed", "agreed"),
    ("agreement_s", "agreement after last update (sim s)"),
    ("epochs_per_robot", "epochs / robot"),
    ("searches_per_epoch", "full searches / epoch (fleet)"),
    ("checks_per_epoch", "checks / epoch (fleet)"),
    ("searches_per_epoch_per_robot", "full searches / epoch / robot"),
    ("checks_per_epoch_per_robot", "checks / epoch / robot"),
    ("searches_gated_per_epoch_per_robot", "gated searches / epoch / robot"),
    ("messages_received_per_robot_per_epoch", "messages received / robot / epoch"),
    ("bytes_received_per_robot_per_epoch", "bytes received / robot / epoch"),
    ("bytes_growth_over_linear", "bytes growth / linear"),
    ("rebuild_cpu_s_mean", "rebuild CPU (s, mean)"),
    ("rebuild_cpu_s_per_agent", "rebuild CPU / agent (s)"),
    ("cpu_s_per_agent_per_epoch", "CPU / agent / epoch (s)"),
    ("cpu_per_epoch_vs_reference", "CPU / agent / epoch vs 16"),
    ("grid_bytes_per_agent", "grid bytes held / agent"),
    ("wall_s", "wall (s)"),
)


def table(rows: list[dict]) -> str:
    lines = ["| " + " | ".join(h for _, h in COLUMNS) + " |", "|" + "---|" * len(COLUMNS)]
    for r in rows:
        lines.append("| " + " | ".join(str(r[k]) for k, _ in COLUMNS) + " |")
    return "\n".join(lines)


def terms_table(rows: list[dict]) -> str:
    """Per-agent CPU per epoch by term (:data:`CPU_TERMS`), each with its ratio to the
    reference N's (the growth a term adds over N is its ratio over N's)."""
    ref = next(r for r in rows if r["robots"] == rows[0]["cpu_reference_robots"])
    head = " | ".join(f"{t} (s) | {t} vs {ref['robots']}" for t in CPU_TERMS)
    lines = [f"| N | {head} |", "|---|" + "---|---|" * len(CPU_TERMS)]
    for r in rows:
        cells = []
        for t in CPU_TERMS:
            key = f"cpu_{t}_s_per_agent_per_epoch"
            cells += [str(r[key]), f"{r[key] / ref[key]:.2f}" if ref[key] else "-"]
        lines.append(f"| {r['robots']} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def validation_table(checks: list[dict]) -> str:
    if not checks:
        return "No bench.fleet result at these N to compare with."
    lines = [
        "| N | measure | bench.fleet runs | mean | spread (range / mean) | fleetsim "
        f"| fleetsim vs mean | within {100 * TOLERANCE:.0f} % or the range |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for c in checks:
        runs = " / ".join(f"{v:g}" for v in c["fleet"])
        lines.append(
            f"| {c['robots']} | {c['measure']} | {runs} | {c['fleet_mean']:g} "
            f"| {100 * c['spread']:.0f} % | {c['fleetsim']} | {100 * c['difference']:+.0f} % "
            f"| {'yes' if c['within'] else 'no'} |"
        )
    return "\n".join(lines)


def targets(rows: list[dict]) -> list[str]:
    """The issue's three targets, met or not, one line each."""
    big = max(rows, key=lambda r: r["robots"])
    worst = max(r["searches_per_epoch_per_robot"] for r in rows)
    growth = max(r["bytes_growth_over_linear"] for r in rows)
    ref = big["cpu_reference_robots"]
    return [
        f"- per-agent CPU per epoch at {big['robots']} over {ref}: "
        f"{big['cpu_per_epoch_vs_reference']} (target <= {CPU_RATIO_TARGET:g})",
        f"- full searches per epoch per robot, worst N: {worst} (target <= {SEARCHES_TARGET:g})",
        f"- bytes received per robot per epoch, growth over linear in N, worst: {growth} "
        "(target <= 1)",
    ]


def plot(rows: list[dict], path: Path) -> None:
    """Each measure against N, log-x."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    shown = [c for c in COLUMNS[2:-1] if c[0] != "bytes_growth_over_linear"]
    fig, axes = plt.subplots(4, 4, figsize=(16, 13))
    ns = [r["robots"] for r in rows]
    for ax, (key, label) in zip(axes.flat, shown, strict=False):
        ax.plot(ns, [r[key] if r[key] is not None else np.nan for r in rows], "o-")
        ax.set_xscale("log", base=2)
        ax.set_xticks(ns, [str(n) for n in ns])
        ax.set_title(label, fontsize=9)
        ax.set_xlabel("robots")
    for ax in list(axes.flat)[len(shown) :]:
        ax.axis("off")
    fig.suptitle("fleetsim: measures against the number of robots")
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)


def write_results(
    rows: list[dict], args: argparse.Namespace, out: Path, real_runs: list[list[dict]]
) -> None:
    """``fleetsim.json``, ``fleetsim.md`` and ``fleetsim.png`` under ``out`` (``fleetsim-TAG``
    with ``--tag``), the counts beside ``real_runs`` (:func:`validation`)."""
    stem = "fleetsim" if not args.tag else f"fleetsim-{args.tag}"
    add_relative(rows)
    checks = validation(rows, real_runs)
    out.mkdir(parents=True, exist_ok=True)
    (out / f"{stem}.json").write_text(json.dumps({"rows": rows, "validation": checks}, indent=1))
    plot(rows, out / f"{stem}.png")
    stamp = time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())
    flags = " --quick" if args.quick else ""
    flags += "" if args.cores is None else f" --cores {args.cores:g}"
    flags += "" if not args.tag else f" --tag {args.tag}"
    flags += " --exact-poses" if args.exact_poses else ""
    flags += " --real " + " ".join(str(p) for p in args.real)
    md = (
        f"# Fleet simulator{'' if not args.tag else f' ({args.tag})'}\n\n"
        f"`python3 -m bench fleetsim --robots {' '.join(str(r['robots']) for r in rows)}{flags}`, "
        f"{stamp}.  Real fleet cores in simulated time; registrations drawn from real "
        "outcomes, charged at their measured CPU (see the module docstrings of "
        "bench/fleetsim*.py).\n\n"
        + table(rows)
        + "\n\nCPU per agent per epoch by term (stand-ins' charges by kind, the core's own "
        "work in its worker, its host's):\n\n"
        + terms_table(rows)
        + "\n\nTargets:\n\n"
        + "\n".join(targets(rows))
        + "\n\nBeside bench.fleet (real processes on this machine) at the same N, run by run:\n\n"
        + validation_table(checks)
        + f"\n\n![measures against N]({stem}.png)\n"
    )
    (out / f"{stem}.md").write_text(md)
