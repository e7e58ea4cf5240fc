"""protocol.fetch: a fetch's tile list survives the selector, and strangers' text is refused."""

from __future__ import annotations

import pytest
from hypothesis import given
from hypothesis import strategies as st
from refusals import refused

from protocol import (
    MAX_FETCH_TILES,
    Limits,
    ProtocolError,
    TileFetch,
    fetch_parameters,
    parse_fetch,
)

indices = st.sets(st.integers(0, Limits().max_tiles - 1), min_size=1, max_size=MAX_FETCH_TILES)


@given(st.integers(0, 2**63 - 1), indices)
def test_parameters_round_trip(version: int, wanted: set[int]) -> None:
    params = fetch_parameters(version, wanted)
    assert params is not None
    assert parse_fetch(params["v"], params["tiles"]) == TileFetch(version, frozenset(wanted))


def test_no_tiles_or_too_many_ask_for_the_whole_map() -> None:
    assert fetch_parameters(5, []) is None
    assert fetch_parameters(5, range(MAX_FETCH_TILES + 1)) is None
    assert parse_fetch(None, None) is None


@pytest.mark.parametrize(
    ("version", "tiles", "reason", "match"),
    [
        ("7", None, "schema", "needs both"),
        (None, "1,2", "schema", "needs both"),
        ("x7", "1", "schema", "not a number"),
        ("-1", "1", "schema", "not a number"),
        ("\u0663", "1", "schema", "not a number"),  # an Arabic-Indic digit
        ("7", "1,,2", "schema", "decimal"),
        ("7", "1;2", "schema", "decimal"),
        ("7", "", "schema", "decimal"),
        ("7", "1,1", "value", "repeated"),
        ("7", str(Limits().max_tiles), "value", "out of range"),
        ("9" * 19, "1", "value", "63 bits"),
        ("1" * 20, "1", "limit", "characters"),
        ("7", ",".join(map(str, range(MAX_FETCH_TILES + 1))), "limit", "characters|exceeds"),
        ("7", "1," * 100_000, "limit", "characters"),
    ],
)
def test_malformed_fetches_are_refused_precisely(version, tiles, reason, match) -> None:
    with refused(reason, match):
        parse_fetch(version, tiles)


@given(st.one_of(st.none(), st.text(max_size=40)), st.one_of(st.none(), st.text(max_size=300)))
def test_any_text_parses_or_is_refused_with_a_protocol_error(version, tiles) -> None:
    try:
        out = parse_fetch(version, tiles)
    except ProtocolError as exc:
        assert exc.reason in ("schema", "limit", "value")
        return
    if out is not None:
        assert 0 <= out.version < 2**63 and 0 < len(out.indices) <= MAX_FETCH_TILES
        assert max(out.indices) < Limits().max_tiles
