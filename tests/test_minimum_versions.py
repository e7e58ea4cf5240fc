"""The lower bounds of pyproject.toml are the versions CI tests: .ci/minimum-versions pins
every one of them, at the bound itself."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

# tomllib is 3.11's; the lowest-versions job runs on 3.10, where this check is the main job's.
tomllib = pytest.importorskip("tomllib")

ROOT = Path(__file__).resolve().parents[1]


def _declared() -> dict[str, str]:
    """Every dependency of the project and its extras -> its lower bound."""
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    requirements = list(project["dependencies"])
    for extra in project["optional-dependencies"].values():
        requirements += extra
    out = {}
    for req in requirements:
        name = re.match(r"[A-Za-z0-9_.-]+", req)[0].lower()
        bound = re.search(r">=\s*([0-9][0-9.]*)", req)
        assert bound, f"{req!r} has no lower bound"
        out[name] = bound[1]
    return out


def _pinned() -> dict[str, str]:
    out = {}
    for line in (ROOT / ".ci" / "minimum-versions").read_text().splitlines():
        line = line.split("#", 1)[0].strip()
        if line:
            name, _, version = line.partition("==")
            assert version, f"{line!r} is not a NAME==VERSION pin"
            out[name.strip().lower()] = version.strip()
    return out


def test_every_lower_bound_is_pinned_at_the_bound() -> None:
    declared, pinned = _declared(), _pinned()
    assert sorted(pinned) == sorted(declared)
    for name, bound in declared.items():
        # 4.8 -> 4.8.0.76: the pin is the first release of the bound, not a later one
        head = pinned[name].split(".")[: len(bound.split("."))]
        assert head == bound.split("."), f"{name}: bound {bound}, CI tests {pinned[name]}"
