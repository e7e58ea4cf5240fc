"""The public ``pgvd`` API: what ``import pgvd`` offers, what it costs, and its examples."""

from __future__ import annotations

import doctest
import importlib
import inspect
import pkgutil
import subprocess
import sys
from pathlib import Path

import pytest

import pgvd

ROOT = Path(__file__).resolve().parents[1]


def _run(code: str) -> str:
    """Run ``code`` in a fresh interpreter (imports are process-wide) and return its stdout."""
    done = subprocess.run(
        [sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=120
    )
    assert done.returncode == 0, done.stderr
    return done.stdout.strip()


def test_every_public_name_resolves_to_its_definition():
    for name in pgvd.__all__:
        value = getattr(pgvd, name)
        home = importlib.import_module(value.__module__)
        assert getattr(home, name) is value, name
    assert set(pgvd.__all__) <= set(dir(pgvd))


def test_unknown_name_is_an_attribute_error():
    with pytest.raises(AttributeError, match="no_such_thing"):
        pgvd.no_such_thing  # noqa: B018


def test_import_loads_no_scientific_library():
    loaded = _run(
        "import sys, pgvd; "
        "print(sorted({m.split('.')[0] for m in sys.modules} & {'scipy', 'skimage', 'matplotlib'}))"
    )
    assert loaded == "[]"


@pytest.mark.parametrize(
    ("name", "first"),
    [
        ("merge", "import pgvd.merge"),
        ("merge", "from pgvd.merge import MergeParams"),
        ("merge", "from pgvd import merge"),
        # the README and docs name pgvd.verify; it once raised AttributeError after import pgvd
        ("verify", "import pgvd"),
        ("verify", "import pgvd.verify"),
        ("verify", "from pgvd.verify import pooled_maps"),
    ],
)
def test_a_function_is_itself_whatever_was_imported_first(name, first):
    out = _run(f"{first}\nimport pgvd, inspect\nprint(inspect.isfunction(pgvd.{name}))")
    assert out == "True"


@pytest.mark.parametrize("name", ["merge", "verify"])
def test_the_submodule_of_a_function_stays_reachable(name):
    module = importlib.import_module(f"pgvd.{name}")
    assert inspect.ismodule(module)
    assert getattr(module, name) is getattr(pgvd, name)


def _docstring_examples() -> list[doctest.DocTest]:
    finder = doctest.DocTestFinder()
    tests = []
    for info in pkgutil.iter_modules(pgvd.__path__, "pgvd."):
        tests += [t for t in finder.find(importlib.import_module(info.name)) if t.examples]
    return tests


EXAMPLES = _docstring_examples()


def test_merge_has_an_example():
    assert "pgvd.merge.merge" in {t.name for t in EXAMPLES}


@pytest.mark.parametrize("example", EXAMPLES, ids=lambda t: t.name)
def test_docstring_example(example, monkeypatch):
    # Examples name the bundled maps relative to the project root, as a user there would.
    monkeypatch.chdir(ROOT)
    runner = doctest.DocTestRunner(optionflags=doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE)
    report: list[str] = []
    runner.run(example, out=report.append)
    assert runner.failures == 0, "".join(report)
