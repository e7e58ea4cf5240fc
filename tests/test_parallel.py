"""pgvd.parallel.both: the two maps' computations at once, with the results and errors of one
after the other."""

from __future__ import annotations

import threading
from pathlib import Path

import numpy as np
import pytest

from pgvd.io import read_map
from pgvd.merge import merge
from pgvd.parallel import both
from pgvd.params import MergeParams
from pgvd.speckle import DESPECKLE_RADIUS

EXAMPLES = Path(__file__).resolve().parent.parent / "examples"


def test_results_come_back_in_the_order_of_the_arguments() -> None:
    a, b = np.arange(6.0), -np.arange(6.0)
    assert both(np.cumsum, a, b)[0].tolist() == np.cumsum(a).tolist()
    assert both(np.cumsum, a, b)[1].tolist() == np.cumsum(b).tolist()


def test_the_second_runs_on_another_thread_while_the_first_runs() -> None:
    started = threading.Event()

    def job(name: str) -> str:
        if name == "A":  # A waits for B to start: one after the other would wait forever
            assert started.wait(timeout=10.0)
        else:
            started.set()
        return threading.current_thread().name

    first, second = both(job, "A", "B")
    assert first == threading.current_thread().name and second == "pgvd-map-b"


def test_one_core_runs_them_one_after_the_other(monkeypatch) -> None:
    monkeypatch.setattr("pgvd.parallel.os.cpu_count", lambda: 1)
    assert (
        both(lambda _: threading.current_thread().name, 1, 2)
        == (threading.current_thread().name,) * 2
    )


def _fails_on(bad: set[str]):
    finished: list[str] = []

    def job(name: str) -> str:
        if name in bad:
            raise ValueError(f"map {name} is empty")
        finished.append(name)
        return name

    return job, finished


@pytest.mark.parametrize(
    ("bad", "message"), [({"A"}, "map A"), ({"B"}, "map B"), ({"A", "B"}, "map A")]
)
def test_an_error_in_a_is_reported_before_one_in_b(bad: set[str], message: str) -> None:
    job, finished = _fails_on(bad)
    with pytest.raises(ValueError, match=message):
        both(job, "A", "B")
    # the other call had ended, with its result, before the error came back
    assert finished == [n for n in ("A", "B") if n not in bad]


def test_a_merge_is_the_same_on_one_core_as_on_two(monkeypatch) -> None:
    a, b = read_map(EXAMPLES / "intel_a.yaml"), read_map(EXAMPLES / "intel_b.yaml")
    params = MergeParams(diagnostics=False)
    two = merge(a, b, params)
    monkeypatch.setattr("pgvd.parallel.os.cpu_count", lambda: 1)
    one = merge(a, b, params)
    assert two.accepted and one.accepted
    np.testing.assert_array_equal(two.matrix, one.matrix)
    np.testing.assert_array_equal(two.covariance, one.covariance)
    assert two.margin == one.margin


def test_progress_is_told_on_the_callers_thread_a_before_b() -> None:
    # the CLI prints progress lines; told from two threads, two of them ran into one
    a, b = read_map(EXAMPLES / "intel_a.yaml"), read_map(EXAMPLES / "intel_b.yaml")
    told: list[tuple[str, str]] = []
    params = MergeParams(diagnostics=False, speckle_radius=DESPECKLE_RADIUS)
    merge(a, b, params, progress=lambda line: told.append((threading.current_thread().name, line)))
    assert {thread for thread, _ in told} == {threading.current_thread().name}
    maps = [line.split(":")[0] for _, line in told if "speckle" in line]
    assert maps == ["map A", "map B"]
