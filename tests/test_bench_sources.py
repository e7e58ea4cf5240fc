"""The held-out logs: every log of the shared data that no development source reads."""

from __future__ import annotations

from bench.sources import SOURCES, held_out_logs


def test_held_out_logs_are_the_logs_no_development_source_reads(tmp_path):
    logs = tmp_path / "logs"
    logs.mkdir()
    for name in ("intel-corrected.log.gz", "freiburg-079-corrected.log.gz", "elsewhere.log.gz"):
        (logs / name).write_bytes(b"")
    (logs / "notes.txt").write_text("not a log")
    held = held_out_logs(tmp_path)
    assert [(s.name, s.building, s.path) for s in held] == [
        ("elsewhere-log", "elsewhere", "logs/elsewhere.log.gz")
    ]
    assert not held[0].simulated


def test_the_shared_data_keeps_logs_apart_from_the_development_ones(shared):
    held = held_out_logs(shared)
    development = {s.building for s in SOURCES} | {"freiburg-079"}
    assert held, "the shared data holds no held-out log"
    assert all((shared / s.path).is_file() for s in held)
    assert not {s.path for s in held} & {s.path for s in SOURCES}
    # one building each, none of them a development building under its log's name
    assert len({s.building for s in held}) == len(held)
    assert not {s.building for s in held} & development
