"""Shared fixtures: the real data set lives in ``../shared`` beside the project root."""

from __future__ import annotations

import functools
from pathlib import Path
from typing import TYPE_CHECKING

import pytest
from hypothesis import settings

if TYPE_CHECKING:
    import numpy as np

    from bench.data.pairs import MapPair
    from pgvd.grid import Grid

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared"

# No per-example deadline: the property tests check what a decoder does, not how fast.
# On a loaded 2-core CI runner a first example can take 50x its usual time, and
# hypothesis then reports the test as flaky although every example behaved.
settings.register_profile("pgvd", deadline=None)
settings.load_profile("pgvd")


@pytest.fixture(scope="session")
def shared() -> Path:
    """Path of the shared real data (maps/, logs/); skips when it is absent."""
    if not (SHARED / "maps").is_dir():
        pytest.skip(f"shared data not found at {SHARED}")
    return SHARED


@pytest.fixture(scope="module")
def intel_split(shared: Path) -> MapPair:
    """The Intel lab map split in two, each part in its own frame, with its true transform."""
    # imported here, not at the top: test modules that need neither bench nor the maps
    # collect without loading scipy and OpenCV
    from bench.data.pairs import MapPair
    from pgvd.grid import relative_matrix
    from pgvd.io import read_map

    a = read_map(shared / "maps" / "intel_split_gt" / "intel_partA.yaml")
    b = read_map(shared / "maps" / "intel_split_gt" / "intel_partB.yaml")
    return MapPair(a, b, relative_matrix(a, b), 0.5, "intel-split")


@pytest.fixture(scope="module")
def halves(shared: Path) -> tuple[Grid, Grid, np.ndarray]:
    """The two halves of intel_split_gt at 0.1 m, and their true B px -> A px matrix."""
    from pgvd.grid import relative_matrix
    from pgvd.io import read_map
    from pgvd.transform import resample

    d = shared / "maps" / "intel_split_gt"
    a = resample(read_map(d / "intel_partA.yaml"), 0.1)
    b = resample(read_map(d / "intel_partB.yaml"), 0.1)
    return a, b, relative_matrix(a, b)


#: Marks of the tests that start agent processes or build network namespaces.
PROCESS_MARKS = ("mark.fleet", "mark.netns")


@pytest.hookimpl(optionalhook=True)  # a hook of pytest-xdist, absent without it
def pytest_xdist_make_scheduler(config: pytest.Config, log: object) -> object | None:
    """Under ``pytest -n N`` (the README's test command), hand out whole modules.

    Each module goes to one worker, so its module-scoped fixtures (a fleet, a merge) are
    built once. The modules that start agent processes or network namespaces form one unit
    instead: they run one after another, as each one's timeouts were set for, while the
    other workers take the rest. The controller does not collect, so a module counts as
    such when its source names one of :data:`PROCESS_MARKS`. An explicit ``--dist`` other
    than the default ``load`` is left to xdist.
    """
    if config.getoption("dist") != "load":
        return None
    from xdist.scheduler import LoadScopeScheduling

    class ModuleScheduling(LoadScopeScheduling):
        def _split_scope(self, nodeid: str) -> str:
            module = nodeid.split("::", 1)[0]
            return "processes" if _starts_processes(config.rootpath / module) else module

    return ModuleScheduling(config, log)


@functools.cache
def _starts_processes(module: Path) -> bool:
    return any(mark in module.read_text() for mark in PROCESS_MARKS)
