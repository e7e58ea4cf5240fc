"""Atomic persistence of maps and links in the state directory."""

from __future__ import annotations

import io
import os
import zipfile
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from agent.links import LinkRecord
from agent.state import StateDir, StoredMap
from pgvd.grid import Grid


def grid(seed: int) -> Grid:
    rng = np.random.default_rng(seed)
    lo = rng.normal(0, 3, (30, 40)).astype(np.float32)
    lo[rng.random(lo.shape) < 0.3] = 0.0
    return Grid(lo, 0.1, (1.5, -2.0, 0.0))


def test_only_the_own_map_is_fsynced(tmp_path: Path, monkeypatch) -> None:
    """The own map (durable) is fsynced, file and directory; a peer's map, the links and
    the status are renamed into place without: the peers have them again."""
    synced: list[int] = []
    real_fsync = os.fsync

    def fsync(fd: int) -> None:
        synced.append(fd)
        real_fsync(fd)

    monkeypatch.setattr(os, "fsync", fsync)
    sd = StateDir(tmp_path)
    sd.save_map("r2", StoredMap(3, grid(2)))
    sd.save_links([LinkRecord("r1", 7, "r2", 3, True, np.eye(3), np.eye(3), 0.95, "r1")])
    sd.save_status(b"{}")
    assert synced == []
    sd.save_map("r1", StoredMap(7, grid(1)), durable=True)
    assert len(synced) == 2
    maps, errors = StateDir(tmp_path).load_maps()
    assert errors == [] and maps["r2"].version == 3 and maps["r1"].version == 7
    assert sorted(p.name for p in tmp_path.iterdir()) == ["links.json", "maps", "status.json"]


def test_maps_and_links_round_trip(tmp_path: Path) -> None:
    sd = StateDir(tmp_path)
    sd.save_map("r1", StoredMap(7, grid(1), {"cursor": 120}))
    sd.save_map("r2", StoredMap(3, grid(2)))
    link = LinkRecord("r1", 7, "r2", 3, True, np.eye(3), np.eye(3), 0.95, "r1")
    sd.save_links([link])
    maps, errors = StateDir(tmp_path).load_maps()
    assert errors == [] and sorted(maps) == ["r1", "r2"]
    assert maps["r1"].version == 7 and maps["r1"].extra == {"cursor": 120}
    np.testing.assert_array_equal(maps["r1"].grid.logodds, grid(1).logodds)
    assert maps["r2"].grid.origin == (1.5, -2.0, 0.0)
    links, errors = sd.load_links()
    assert errors == [] and [r.key for r in links] == [link.key]


def test_a_crash_during_a_write_leaves_the_old_file_whole(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    sd = StateDir(tmp_path)
    sd.save_map("r1", StoredMap(1, grid(1)))

    def crash(*_: object) -> None:
        raise OSError("disk gone")

    monkeypatch.setattr(os, "replace", crash)  # the writer is pgvd.atomic.atomic_write
    with pytest.raises(OSError):
        sd.save_map("r1", StoredMap(2, grid(2)))
    monkeypatch.undo()
    maps, _ = sd.load_maps()
    assert maps["r1"].version == 1
    assert sorted(os.listdir(sd.maps_dir)) == ["r1.npz"]  # no temporary left behind


def test_corrupt_files_are_skipped_with_one_line_each(tmp_path: Path) -> None:
    sd = StateDir(tmp_path)
    sd.save_map("r1", StoredMap(1, grid(1)))
    (sd.maps_dir / "r2.npz").write_bytes(b"PK\x03\x04 not a zip")
    (tmp_path / "links.json").write_text("{not json")
    maps, errors = sd.load_maps()
    assert sorted(maps) == ["r1"] and len(errors) == 1 and "r2.npz" in errors[0]
    links, errors = sd.load_links()
    assert links == [] and "links.json" in errors[0]


def test_well_formed_archives_of_the_wrong_arrays_are_skipped_too(tmp_path: Path) -> None:
    # A 0-d origin once raised TypeError out of load_maps: the agent could not start.
    sd = StateDir(tmp_path)
    good = {
        "logodds": np.zeros((4, 4), np.float32),
        "resolution": np.float64(0.1),
        "origin": np.zeros(3),
        "version": np.int64(1 << 31),
        "extra": np.frombuffer(b"{}", np.uint8),
    }
    bad = {
        "r1": {"origin": np.float64(0.0)},
        "r2": {"logodds": np.zeros(4, np.float32)},
        "r3": {"version": np.float64(np.nan)},
        "r4": {"extra": np.frombuffer(b"[1]", np.uint8)},
        "r5": {"logodds": np.full((4, 4), 1e300)},
        "r6": {"resolution": np.float64(1e9)},
        "r7": {"origin": np.array([0.0, np.inf, 0.0])},
        "r8": {"resolution": np.zeros(2)},
    }
    for robot, change in bad.items():
        np.savez(sd.maps_dir / f"{robot}.npz", **{**good, **change})
    np.savez(sd.maps_dir / "r9.npz", **good)
    maps, errors = sd.load_maps()
    assert sorted(maps) == ["r9"] and len(errors) == len(bad)
    assert all("\n" not in e for e in errors)


def test_leftover_temporaries_are_removed_at_start_and_never_loaded(tmp_path: Path) -> None:
    sd = StateDir(tmp_path)
    sd.save_map("r1", StoredMap(1, grid(1)))
    left = [sd.maps_dir / ".r1.npz.a1b2", sd.maps_dir / ".r2.npz.c3d4", tmp_path / ".links.json.x"]
    for path in left:
        path.write_bytes(b"PK\x03\x04 half a file")
    keep = [tmp_path / ".hidden", sd.maps_dir / "notes.txt"]  # not ours to delete
    for path in keep:
        path.write_text("x")
    maps, errors = sd.load_maps()  # loading alone never reads them
    assert sorted(maps) == ["r1"] and errors == []
    again = StateDir(tmp_path)
    assert again.removed_temporaries == sorted(p.name for p in left)
    assert not any(p.exists() for p in left) and all(p.exists() for p in keep)


def test_an_archive_whose_array_header_does_not_parse_is_skipped(tmp_path: Path) -> None:
    # numpy reads a .npy header with the tokenizer: "(" left open is a TokenError
    sd = StateDir(tmp_path)
    sd.save_map("r1", StoredMap(1, grid(1)))
    with zipfile.ZipFile(sd.maps_dir / "r2.npz", "w") as z:
        z.writestr("logodds.npy", b"\x93NUMPY\x01\x00\x03\x00\x00\x00(")
    maps, errors = sd.load_maps()
    assert sorted(maps) == ["r1"] and len(errors) == 1 and "r2.npz" in errors[0]


_GOOD_MEMBERS = {
    "logodds": np.zeros((4, 4), np.float32),
    "resolution": np.float64(0.1),
    "origin": np.zeros(3),
    "version": np.int64(7),
    "extra": np.frombuffer(b"{}", np.uint8),
}
_ODD_ARRAYS = st.sampled_from(
    [
        np.zeros((2, 2), [("a", "f4"), ("b", "i4")]),  # structured
        np.array(["0.1"]),
        np.array(0.1 + 2j),
        np.zeros((0, 3)),
        np.full(3, np.nan),
        np.array(True),
        np.zeros((2, 2, 2), np.float16),
        np.array(2**40, np.int64),
        np.frombuffer(b"\xff\xfe", np.uint8),
    ]
)


def _npy(arr: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.save(buf, arr, allow_pickle=False)
    return buf.getvalue()


@settings(max_examples=150, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(
    members=st.dictionaries(
        st.sampled_from(sorted(_GOOD_MEMBERS)),
        st.one_of(
            _ODD_ARRAYS.map(_npy),
            st.binary(max_size=64).map(lambda b: b"\x93NUMPY\x01\x00" + b),
            st.binary(max_size=64),
        ),
    ),
    whole=st.one_of(st.none(), st.binary(max_size=200)),
)
def test_loading_any_archive_skips_it_or_reads_a_sound_map(
    tmp_path: Path, members: dict[str, bytes], whole: bytes | None
) -> None:
    """Whatever a stored map file holds, load_maps returns: a sound map or one error line."""
    sd = StateDir(tmp_path)
    path = sd.maps_dir / "r1.npz"
    if whole is not None:
        path.write_bytes(whole)
    else:
        with zipfile.ZipFile(path, "w") as z:
            for name, arr in _GOOD_MEMBERS.items():
                z.writestr(f"{name}.npy", members.get(name, _npy(arr)))
    maps, errors = sd.load_maps()
    assert len(maps) + len(errors) == 1
    assert all("\n" not in e for e in errors)
    for stored in maps.values():
        assert np.isfinite(stored.grid.logodds).all() and stored.grid.resolution > 0
