"""One entry point: ``python3 -m bench NAME ARGS...`` runs the bench module ``NAME``.

``python3 -m bench merge --quick`` is ``python3 -m bench.merge --quick``; a study or a data
generator is found by its name alone (``python3 -m bench recall`` runs
:mod:`bench.studies.recall`).  ``python3 -m bench --help`` lists every module that runs, one
line each, from the first line of its docstring.
"""

from __future__ import annotations

import ast
import importlib.util
import runpy
import sys
from pathlib import Path

#: The listing's sections: heading and package, in the order they are listed.
SECTIONS = (
    ("Benchmarks", "bench"),
    ("Studies: the analyses behind the merge's design", "bench.studies"),
    ("Data: the pairs the benches merge", "bench.data"),
)
USAGE = "usage: python3 -m bench NAME [ARGS...]    (python3 -m bench NAME --help: its options)"


def _runs(tree: ast.Module) -> bool:
    """Whether a module's source has an ``if __name__ == "__main__":`` block."""
    return any(
        isinstance(node, ast.If)
        and isinstance(node.test, ast.Compare)
        and isinstance(node.test.left, ast.Name)
        and node.test.left.id == "__name__"
        for node in tree.body
    )


def commands(package: str) -> dict[str, str]:
    """The runnable modules of one package: name -> the first line of its docstring.

    Read from the source, not imported, so that the listing stays quick and cannot fail on
    a module's heavy imports.
    """
    spec = importlib.util.find_spec(package)
    folder = Path(next(iter(spec.submodule_search_locations)))
    found = {}
    for path in sorted(folder.glob("*.py")):
        if path.stem.startswith("_"):
            continue
        tree = ast.parse(path.read_text(), str(path))
        if _runs(tree):
            found[path.stem] = next(iter((ast.get_docstring(tree) or "").splitlines()), "")
    return found


def listing() -> str:
    """Every runnable module, one line each, under its section's heading."""
    lines = [USAGE]
    for heading, package in SECTIONS:
        lines += ["", f"{heading}:"]
        lines += [f"  {name:<16} {doc}" for name, doc in commands(package).items()]
    return "\n".join(lines)


def module_of(name: str) -> str | None:
    """The full module name of the runnable module ``name``, or None when there is none."""
    for _, package in SECTIONS:
        if name in commands(package):
            return f"{package}.{name}"
    return None


def main(argv: list[str]) -> int:
    """List the bench modules, or run the one ``argv`` names with the rest of ``argv``."""
    if not argv or argv[0] in ("-h", "--help"):
        print(listing())
        return 0
    module = module_of(argv[0])
    if module is None:
        error = f"bench: no bench module {argv[0]!r} (python3 -m bench --help lists them)"
        print(error, file=sys.stderr)
        return 2
    sys.argv = [module, *argv[1:]]
    runpy.run_module(module, run_name="__main__", alter_sys=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
