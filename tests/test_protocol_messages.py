"""protocol.messages: constructors refuse what no valid message could hold."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from refusals import refused

from protocol import Geometry, Heartbeat, Link, Manifest, MapTiles, ProtocolError, Status, Tile


def test_geometry_checks_and_tiling():
    g = Geometry((300, 130), 0.05, (1, 2, 0.5), 128)
    assert g.tile_grid == (3, 2) and g.n_tiles == 6
    assert g.tile_shape(5) == (44, 2) and g.tile_window(3) == (slice(128, 256), slice(128, 130))
    for kwargs, why in [
        ({"shape": (0, 5)}, "positive"),
        ({"shape": (5,)}, r"\(H, W\)"),
        ({"resolution": -1.0}, "> 0"),
        ({"resolution": float("inf")}, "finite"),
        ({"origin": (0.0, float("nan"), 0.0)}, "origin.1. must be finite"),
        ({"tile_size": 100}, "tile_size must be one of"),
        ({"tile_size": True}, "tile_size must be one of"),
    ]:
        args = {"shape": (10, 10), "resolution": 0.05, **kwargs}
        with pytest.raises(ProtocolError, match=why):
            Geometry(**args)
    with pytest.raises(ProtocolError, match="tile index 6 outside"):
        g.tile_shape(6)


def test_map_tiles_checks():
    g = Geometry((20, 20), 0.05, tile_size=16)
    t = Tile(0, 0, np.zeros((16, 16), np.int8))
    with pytest.raises(ProtocolError, match=r"has shape \(16, 16\), geometry says \(16, 4\)"):
        MapTiles("f", "r", 1, g, (Tile(1, 0, np.zeros((16, 16), np.int8)),))
    with pytest.raises(ProtocolError, match="appears twice"):
        MapTiles("f", "r", 1, g, (t, t))
    with pytest.raises(ProtocolError, match="at least one tile"):
        MapTiles("f", "r", 1, g, ())
    with pytest.raises(ProtocolError, match="must be older"):
        MapTiles("f", "r", 1, g, (t,), base_version=1)
    with pytest.raises(ProtocolError, match="int8"):
        Tile(0, 0, np.zeros((16, 16), np.int16))
    with pytest.raises(ProtocolError, match="32-bit"):
        Tile(0, 2**32, np.zeros((16, 16), np.int8))
    assert not t.cells.flags.writeable


def test_ids_versions_and_counters():
    with pytest.raises(ProtocolError, match="outside"):
        Heartbeat("f", "r 1", 1)
    with pytest.raises(ProtocolError, match=r"\[0, 2\*\*63\)"):
        Heartbeat("f", "r", -1)
    with pytest.raises(ProtocolError, match="must be an integer"):
        Heartbeat("f", "r", 1.0)
    with pytest.raises(ProtocolError, match="counter name"):
        Status("f", "r", 1, {"a/b": 1})
    with pytest.raises(ProtocolError, match="must be finite"):
        Status("f", "r", 1, {"a": float("nan")})
    with pytest.raises(ProtocolError, match="two different robots"):
        Link("f", "a", "a", "a", 1, 1, True, np.eye(3), np.eye(3), 1.0)
    with pytest.raises(ProtocolError, match="must be 3x3"):
        Link("f", "a", "a", "b", 1, 1, True, np.eye(2), np.eye(3), 1.0)
    with pytest.raises(ProtocolError, match="manifest tile index 4 outside"):
        Manifest("f", "r", 1, Geometry((20, 20), 0.05, tile_size=16), {4: 1})


def test_tile_freezes_a_copy_not_the_callers_array():
    cells = np.zeros((16, 16), np.int8)
    tile = Tile(0, 0, cells)
    cells[0, 0] = 1
    assert tile.cells[0, 0] == 0 and not tile.cells.flags.writeable


GEOMETRY = Geometry((20, 20), 0.05, tile_size=16)


@pytest.mark.parametrize(
    ("digest", "reason", "why"),
    [
        (-5, "value", "64-bit unsigned"),
        (2**64, "value", "64-bit unsigned"),
        (2**70, "value", "64-bit unsigned"),
        (1.5, "schema", "digest must be an integer"),
        (True, "schema", "digest must be an integer"),
        ("7", "schema", "digest must be an integer"),
    ],
)
def test_manifest_refuses_a_digest_outside_64_bits(digest, reason, why):
    with refused(reason, why):
        Manifest("f", "r", 2, GEOMETRY, {1: 9}, base_version=1, digest=digest)


def test_manifest_digest_of_numpy_type_is_kept_as_int():
    m = Manifest("f", "r", 2, GEOMETRY, {1: 9}, base_version=1, digest=np.uint64(2**64 - 1))
    assert type(m.digest) is int and m.digest == 2**64 - 1


@given(
    digest=st.one_of(
        st.integers(max_value=-1),
        st.integers(min_value=2**64),
        st.floats(),
        st.booleans(),
        st.text(max_size=3),
        st.binary(max_size=3),
    )
)
def test_any_other_digest_is_refused_by_the_constructor(digest):
    with pytest.raises(ProtocolError) as err:
        Manifest("f", "r", 2, GEOMETRY, {}, base_version=1, digest=digest)
    assert err.value.reason in ("schema", "value")


@given(
    st.dictionaries(st.integers(-3, GEOMETRY.n_tiles + 3), st.integers(-3, 2**32 + 3), max_size=12)
)
def test_manifest_checksums_read_alike_as_ints_and_as_numpy_ints(checksums):
    """Plain ints (a decoded manifest's) are checked in bulk, numpy ints one by one: the
    same manifest, or the same refusal of the first bad tile."""

    def build(table):
        try:
            return Manifest("f", "r", 2, GEOMETRY, table)
        except ProtocolError as exc:
            return (exc.reason, str(exc))

    as_numpy = {np.int64(k): np.int64(v) for k, v in checksums.items()}
    assert build(checksums) == build(as_numpy)
