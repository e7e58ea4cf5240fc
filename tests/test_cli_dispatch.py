"""The ``pgvd`` entry point: no import cycle, and each command loads only what it uses."""

from __future__ import annotations

import ast
import os
import subprocess
import sys
from pathlib import Path

import pytest

from agent.cli.dispatch import COMMANDS
from agent.launcher import ROOT

PACKAGES = ("pgvd", "protocol", "agent", "bench")
HEAVY = ("zenoh", "scipy", "skimage", "matplotlib")


def modules() -> dict[str, Path]:
    """Every module of the project's packages, by dotted name."""
    found = {}
    for package in PACKAGES:
        for path in (ROOT / package).rglob("*.py"):
            parts = list(path.relative_to(ROOT).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts.pop()
            found[".".join(parts)] = path
    return found


def import_graph() -> dict[str, set[str]]:
    """Module -> the project modules it imports, at module level or inside functions.

    ``agent.cli.dispatch`` imports the command modules by name (:data:`COMMANDS`).
    """
    mods = modules()
    graph: dict[str, set[str]] = {}
    for name, path in mods.items():
        targets = set()
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                targets |= {alias.name for alias in node.names}
            elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                for alias in node.names:
                    sub = f"{node.module}.{alias.name}"
                    targets.add(sub if sub in mods else node.module)
        graph[name] = targets & mods.keys()
    graph["agent.cli.dispatch"] |= {module for module, _ in COMMANDS.values()}
    return graph


def find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One import cycle of ``graph`` as a path that ends where it starts, or None."""
    done: set[str] = set()
    path: list[str] = []

    def visit(node: str) -> list[str] | None:
        if node in path:
            return [*path[path.index(node) :], node]
        if node in done:
            return None
        path.append(node)
        for target in sorted(graph[node]):
            if cycle := visit(target):
                return cycle
        path.pop()
        done.add(node)
        return None

    for node in sorted(graph):
        if cycle := visit(node):
            return cycle
    return None


def pgvd(*args: str, **kwargs) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "agent.cli", *args],
        cwd=ROOT,
        env={**os.environ, "PYTHONPATH": str(ROOT)},
        timeout=60,
        **kwargs,
    )


_LOADED_BY = """
import os, sys
from agent.cli import main
out, sys.stdout = sys.stdout, open(os.devnull, "w")
try:
    main(sys.argv[1:])
except SystemExit:
    pass
out.write(" ".join(sys.modules))
"""


def loaded_by(*argv: str) -> set[str]:
    """The modules a fresh interpreter holds after running ``pgvd argv``."""
    res = subprocess.run(
        [sys.executable, "-c", _LOADED_BY, *argv],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert res.returncode == 0, res.stderr
    return set(res.stdout.split())


def test_the_project_has_no_import_cycle() -> None:
    graph = import_graph()
    assert {"agent.cli.dispatch", "agent.cli.common", "agent.scenario"} <= graph.keys()
    assert find_cycle(graph) is None, find_cycle(graph)


def test_find_cycle_finds_one() -> None:
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
    assert find_cycle({"a": {"b", "c"}, "b": {"c"}, "c": set()}) is None


def test_nothing_outside_the_cli_imports_it() -> None:
    """bench/ and the agent's modules use :mod:`agent.scenario`, not a command module."""
    users = {
        m
        for m, targets in import_graph().items()
        if any(t.startswith("agent.cli") for t in targets)
    }
    assert {m for m in users if not m.startswith("agent.cli")} == set()


@pytest.mark.parametrize("extra", [(), ("--prior=-1.5,2,0.3",)])
def test_merge_loads_no_heavy_library_before_reading_its_files(tmp_path: Path, extra) -> None:
    loaded = loaded_by("merge", str(tmp_path / "a.yaml"), str(tmp_path / "b.yaml"), *extra)
    assert "agent.cli.merge" in loaded and "pgvd.io" in loaded
    assert [m for m in loaded if m.split(".")[0] in HEAVY] == []
    # --prior is parsed without the agent's protocol stack
    assert "protocol" not in {m.split(".")[0] for m in loaded}


def test_help_loads_no_command() -> None:
    loaded = loaded_by("--help")
    assert "agent.cli.dispatch" in loaded
    assert {module for module, _ in COMMANDS.values()} & loaded == set()
    assert not {"numpy", *HEAVY} & {m.split(".")[0] for m in loaded}


def test_every_command_has_its_arguments_and_help() -> None:
    for name in COMMANDS:
        res = pgvd(name, "--help", capture_output=True, text=True)
        assert res.returncode == 0 and res.stdout.startswith(f"usage: pgvd {name} [-h]")
        assert res.stdout.count("--") >= 2, res.stdout  # its own options, not only --help
        # descriptions are module docstrings: their reStructuredText reads as plain text
        assert "``" not in res.stdout and ":mod:`" not in res.stdout, res.stdout
        assert max(map(len, res.stdout.splitlines())) <= 100, res.stdout  # wrapped


def test_help_shows_defaults_once() -> None:
    out = pgvd("demo", "--help", capture_output=True, text=True).stdout
    assert "(default: 100.0)" in out  # --speed
    assert "(default demo-out)" in out and "(default: demo-out)" not in out  # said in its help
    assert "\n- side_by_side.png" in out  # a docstring's list stays a list


def test_version_needs_no_command() -> None:
    res = pgvd("--version", capture_output=True, text=True)
    assert res.returncode == 0 and res.stdout.startswith("pgvd ")
    assert res.stdout.split()[1][0].isdigit(), res.stdout
