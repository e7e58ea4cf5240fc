"""How long ``pgvd merge`` takes to start: process start to its first work, and the import.

    python3 -m bench startup [--runs 9]

The target: ``pgvd merge`` starts (import to first work) in under 0.4 s. Timed as whole
processes, in turn and run after run so that a drift of the machine's speed falls on all:

- ``python -c pass``: the interpreter alone, the floor;
- ``python -c "import numpy"``: the baseline every numpy program pays;
- ``pgvd merge A MISSING``: the CLI up to its first work, reading map A; B is missing, so it
  stops there with exit 2 (reading B is the same work again, and the merge is not start-up);
- ``python -c "import pgvd.merge"``: the whole method, scipy and scikit-image included, which
  the CLI loads only once both maps are known good.

Medians of wall seconds, and their ratio to the numpy import measured in the same run. Writes
``bench/results/startup.md`` and ``startup.json``.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "bench" / "results"
EXAMPLE = ROOT / "examples" / "intel_a.yaml"
MISSING = ROOT / "examples" / "missing.yaml"
PGVD = [sys.executable, "-m", "agent.cli"]


def commands() -> dict[str, list[str]]:
    """The timed command lines, by name."""
    return {
        "python -c pass": [sys.executable, "-c", "pass"],
        "import numpy": [sys.executable, "-c", "import numpy"],
        "pgvd merge to first work": [*PGVD, "merge", str(EXAMPLE), str(MISSING)],
        "import pgvd.merge": [sys.executable, "-c", "import pgvd.merge"],
    }


def wall_seconds(argv: list[str]) -> float:
    """Wall time of one run of ``argv``, output discarded."""
    start = time.perf_counter()
    subprocess.run(argv, cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    return time.perf_counter() - start


def measure(runs: int) -> dict[str, float]:
    """Median wall seconds per command over ``runs`` rounds, after one warm-up round."""
    table = commands()
    times: dict[str, list[float]] = {name: [] for name in table}
    for round_ in range(runs + 1):
        for name, argv in table.items():
            t = wall_seconds(argv)
            if round_:
                times[name].append(t)
    return {name: float(np.median(ts)) for name, ts in times.items()}


def markdown(medians: dict[str, float], runs: int) -> str:
    """The result table, with each median's ratio to ``import numpy``."""
    base = medians["import numpy"]
    lines = [
        "# `pgvd merge` start-up",
        "",
        f"`python3 -m bench startup --runs {runs}`: whole processes, median wall seconds of "
        f"{runs} rounds, in turn.",
        "",
        "| command | wall s | / import numpy |",
        "|---|---|---|",
    ]
    lines += [f"| {name} | {t:.3f} | {t / base:.2f} |" for name, t in medians.items()]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=9)
    args = parser.parse_args(argv)
    medians = measure(args.runs)
    text = markdown(medians, args.runs)
    print(text, end="")
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / "startup.md").write_text(text)
    (RESULTS / "startup.json").write_text(json.dumps(medians, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
