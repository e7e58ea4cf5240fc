"""python3 -m bench: one line per bench module that runs, and NAME runs that module."""

import subprocess
import sys
from pathlib import Path

from bench.__main__ import SECTIONS, commands

ROOT = Path(__file__).resolve().parents[1]


def bench(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "bench", *args], cwd=ROOT, capture_output=True, text=True
    )


def test_help_lists_every_module_that_runs_once_under_its_heading():
    done = bench("--help")
    assert done.returncode == 0, done.stderr
    lines = done.stdout.splitlines()
    headings = [line for line in lines if line.endswith(":") and not line.startswith(" ")]
    assert [h.split(":")[0] for h in headings] == [h.split(":")[0] for h, _ in SECTIONS]
    starts = [lines.index(f"{heading}:") for heading, _ in SECTIONS]
    stops = [*starts[1:], len(lines)]
    for (heading, package), start, stop in zip(SECTIONS, starts, stops, strict=True):
        names = [line.split()[0] for line in lines[start + 1 : stop] if line.strip()]
        assert names == list(commands(package)), heading
    studies = dict(commands("bench.studies"))
    assert "recall" in studies and "merge" not in studies
    assert "merge" in commands("bench") and "report" in commands("bench")
    # a library module, with no command line of its own, is not listed
    assert "pairs" not in commands("bench.data") and "tables" not in commands("bench")
    for docs in map(commands, [p for _, p in SECTIONS]):
        assert all(docs.values()), "every listed module has a docstring"


def test_a_name_runs_its_module_as_python_m_would():
    run = ["bench/results/merge.json", "--method", "pgvd"]
    via_entry = bench("recall", *run)
    direct = subprocess.run(
        [sys.executable, "-m", "bench.studies.recall", *run],
        cwd=ROOT,
        capture_output=True,
        text=True,
    )
    assert via_entry.returncode == direct.returncode == 0, via_entry.stderr
    assert via_entry.stdout == direct.stdout
    assert "| standard |" in via_entry.stdout


def test_an_unknown_name_is_one_line_and_exit_2():
    done = bench("no-such-bench", "--quick")
    assert done.returncode == 2
    assert done.stdout == ""
    assert done.stderr.strip().splitlines() == [
        "bench: no bench module 'no-such-bench' (python3 -m bench --help lists them)"
    ]
