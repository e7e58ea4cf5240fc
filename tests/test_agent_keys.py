"""Key expressions of a fleet and the Zenoh configuration an agent builds."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from hypothesis import given
from hypothesis import strategies as st

from agent import wire
from agent.keys import FleetKeys, check_name, is_name
from agent.zenoh_config import (
    TILE_BATCH_BYTES,
    ZenohOptions,
    build_config,
    tile_session_options,
    zenoh_error,
)


def test_keys_live_under_the_fleet_prefix() -> None:
    k = FleetKeys("lab")
    assert k.tiles("r1") == "pgvd/lab/tiles/r1"
    assert k.link("r1", "r2") == "pgvd/lab/link/r1/r2"
    assert k.latest("r1") == "pgvd/lab/latest/r1/**"
    assert k.latest_reply("r1", 4, "t0") == "pgvd/lab/latest/r1/4/t0"
    assert k.robot_of("pgvd/lab/latest/r1/4/m", "latest") == "r1"
    assert k.robot_of("pgvd/other/tiles/r1", "tiles") is None
    assert k.robot_of("pgvd/lab/tiles/r*", "tiles") is None


chunk = st.text(st.characters(codec="ascii"), max_size=12)
keys_like = st.text(max_size=100) | st.builds("pgvd/lab/{}/{}{}".format, chunk, chunk, chunk)


@given(keys_like)
def test_any_key_gives_a_valid_robot_id_or_none(key: str) -> None:
    robot = FleetKeys("lab").robot_of(key)
    if robot is not None:
        parts = key.split("/")
        assert is_name(robot) and parts[:2] == ["pgvd", "lab"] and parts[3] == robot


@given(st.from_regex(r"[A-Za-z0-9][A-Za-z0-9_-]{0,63}", fullmatch=True))
def test_every_valid_robot_id_is_read_back_from_its_keys(robot: str) -> None:
    k = FleetKeys("lab")
    assert k.robot_of(k.tiles(robot)) == k.robot_of(k.manifest(robot), "manifest") == robot
    assert k.robot_of(k.latest_reply(robot, 7, "m"), "latest") == robot
    assert k.robot_of(k.link(robot, "zz")) == robot and k.robot_of(k.tiles(robot), "link") is None


@pytest.mark.parametrize("bad", ["", "a/b", "r*", "$x", "-r", "a" * 65, "r 1", "r.1"])
def test_names_that_cannot_be_one_key_chunk_are_refused(bad: str) -> None:
    with pytest.raises(ValueError, match="robot id"):
        check_name(bad, "robot id")


def test_default_config_is_peer_on_explicit_endpoints() -> None:
    cfg = build_config(
        ZenohOptions(
            listen=["tcp/127.0.0.1:17000"],
            connect=["tcp/127.0.0.1:17001"],
            shared_memory=False,
            lease_ms=2000,
        )
    )
    assert json.loads(cfg.get_json("mode")) == "peer"
    assert json.loads(cfg.get_json("scouting/delay")) == 0
    assert json.loads(cfg.get_json("scouting/multicast/enabled")) is False
    assert json.loads(cfg.get_json("scouting/gossip/enabled")) is True
    assert json.loads(cfg.get_json("listen/endpoints")) == ["tcp/127.0.0.1:17000"]
    assert json.loads(cfg.get_json("connect/endpoints")) == ["tcp/127.0.0.1:17001"]
    assert json.loads(cfg.get_json("transport/shared_memory/enabled")) is False
    assert json.loads(cfg.get_json("transport/link/tx/lease")) == 2000


def test_config_file_is_extended_not_replaced(tmp_path: Path) -> None:
    f = tmp_path / "z.json5"
    f.write_text('{ mode: "client", scouting: { multicast: { enabled: true } } }')
    cfg = build_config(ZenohOptions(config_file=f, connect=["tcp/127.0.0.1:7447"]))
    assert json.loads(cfg.get_json("mode")) == "client"
    assert json.loads(cfg.get_json("scouting/multicast/enabled")) is True
    assert json.loads(cfg.get_json("connect/endpoints")) == ["tcp/127.0.0.1:7447"]


def test_bad_config_is_one_line(tmp_path: Path) -> None:
    f = tmp_path / "z.json5"
    f.write_text("{ mode: ")
    with pytest.raises(ValueError, match="bad Zenoh config") as info:
        build_config(ZenohOptions(config_file=f))
    # where and what, without Zenoh's caret drawing or its Rust source locations
    assert "\n" not in str(info.value) and ".rs:" not in str(info.value)
    assert "line 1, column" in str(info.value)
    with pytest.raises(ValueError, match=r"No such file or directory \(os error 2\)$"):
        build_config(ZenohOptions(config_file=tmp_path / "none.json5"))
    with pytest.raises(ValueError, match="mode"):
        build_config(ZenohOptions(mode="satellite"))


def test_tile_session_keeps_the_main_choices_but_not_its_file_or_multicast(tmp_path: Path) -> None:
    f = tmp_path / "tls.json5"
    f.write_text('{ transport: { link: { tls: { root_ca_certificate: "/nowhere/ca.pem" } } } }')
    main = ZenohOptions(
        mode="client", multicast=True, shared_memory=False, lease_ms=2000, config_file=f
    )
    tiles = tile_session_options(main, ["udp/127.0.0.1:17002"], ["udp/127.0.0.1:17003"])
    cfg = build_config(tiles)
    assert json.loads(cfg.get_json("mode")) == "client"
    assert json.loads(cfg.get_json("scouting/multicast/enabled")) is False
    assert json.loads(cfg.get_json("transport/link/tls/root_ca_certificate")) is None
    assert json.loads(cfg.get_json("transport/shared_memory/enabled")) is False
    assert json.loads(cfg.get_json("transport/link/tx/lease")) == 2000
    assert json.loads(cfg.get_json("transport/link/tx/batch_size")) == TILE_BATCH_BYTES
    assert json.loads(cfg.get_json("listen/endpoints")) == ["udp/127.0.0.1:17002"]
    assert json.loads(cfg.get_json("connect/endpoints")) == ["udp/127.0.0.1:17003"]
    # A tile message packed for a datagram, with Zenoh's framing, fits one batch.
    assert wire.DATAGRAM_BYTES + 100 <= TILE_BATCH_BYTES <= 1500 - 28


@pytest.mark.parametrize(
    ("text", "line"),
    [
        (  # a JSON5 value error in its Debug wrapper, as insert_json5 raises it
            'Json5Err(Message { msg: "Endpoints must be of the form <protocol>/<address>: '
            'garbage at /r/.cargo/zenoh/src/core/endpoint.rs:615.", location: Some(Location '
            "{ line: 1, column: 1 }) }) at /r/.cargo/zenoh/src/api/config.rs:86.",
            "Endpoints must be of the form <protocol>/<address>: garbage",
        ),
        (  # a syntax error whose source line holds an "=" of its own
            ' --> 2:56\n  |\n2 |   connect: { endpoints: ["tcp/1.2.3.4:7447#iface=eth0" ,, ] }'
            "\n  |                                                        ^---\n  |\n  = expected"
            " array, boolean, null, number, object, or string at /r/zenoh-config/src/lib.rs:1486.",
            "line 2, column 56: expected array, boolean, null, number, object, or string",
        ),
        (
            "No such file or directory (os error 2) at /r/zenoh-config/src/lib.rs:1507.",
            "No such file or directory (os error 2)",
        ),
        ('Json5Err(Message { msg: "", location: None }) at /r/config.rs:86.', None),
    ],
)
def test_zenoh_errors_read_as_one_line(text: str, line: str | None) -> None:
    got = zenoh_error(RuntimeError(text))
    assert "\n" not in got and ".rs:" not in got and got
    if line is not None:
        assert got == line
