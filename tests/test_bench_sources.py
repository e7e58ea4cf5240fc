"""The held-out data: every log and map image of the shared data that development does not use."""

from __future__ import annotations

from bench.data.sources import DEVELOPMENT_MAPS, SOURCES, held_out_logs, held_out_maps


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


def test_held_out_maps_are_the_map_images_outside_the_development_directories(tmp_path):
    for name in ("intel/intel.yaml", "uos_avz/avz.yaml", "elsewhere/a.yaml", "elsewhere/b.yaml"):
        (tmp_path / "maps" / name).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / "maps" / name).write_text("image: x.pgm\n")
    (tmp_path / "maps" / "elsewhere" / "a.pgm").write_bytes(b"")
    held = held_out_maps(tmp_path)
    assert [p.relative_to(tmp_path).as_posix() for p in held] == [
        "maps/elsewhere/a.yaml",
        "maps/elsewhere/b.yaml",
    ]


def test_every_development_map_image_lies_in_a_development_directory(shared):
    simulated = [s for s in SOURCES if s.simulated]
    assert {s.path.split("/")[1] for s in simulated} <= DEVELOPMENT_MAPS
    held = held_out_maps(shared)
    assert held, "the shared data holds no held-out map image"
    assert not {p.parent.name for p in held} & DEVELOPMENT_MAPS
