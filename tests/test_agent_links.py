"""The link cache, which pairs need registering, whose turn it is, and the links chosen."""

from __future__ import annotations

import contextlib
import json

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from agent.links import (
    EPOCH_SHIFT,
    LinkCache,
    LinkRecord,
    Turns,
    dumps,
    epoch_of,
    first_registrar,
    loads,
    needed_keys,
    open_keys,
    ring_distance,
    select_links,
    wait_before_computing,
)
from pgvd.grid import rigid_matrix


def V(epoch: int, minor: int = 0) -> int:
    """A map version of a registration epoch."""
    return epoch << EPOCH_SHIFT | minor


def rec(
    a: str, ea: int, b: str, eb: int, accepted: bool = True, score: float = 0.9, **kw: object
) -> LinkRecord:
    """A link computed on the versions ``V(ea, ma)`` and ``V(eb, mb)`` (minors default 0)."""
    va, vb = V(ea, int(kw.get("ma", 0))), V(eb, int(kw.get("mb", 0)))
    by = str(kw.get("by", a))
    return LinkRecord(
        a, va, b, vb, accepted, rigid_matrix(0.1, 3.0, -2.0), np.eye(3) * 0.01, score, by
    )


def test_record_round_trips_through_json() -> None:
    r = rec("r1", 3, "r2", 5)
    (back,) = loads(dumps([r]))
    assert back.key == r.key and back.accepted and back.decided_by == "r1"
    np.testing.assert_array_equal(back.matrix, r.matrix)


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"a": "r2", "b": "r1"}, "a < b"),
        ({"matrix": np.full((3, 3), np.nan)}, "finite 3x3"),
        ({"covariance": np.eye(2)}, "finite 3x3"),
        ({"score": float("inf")}, "score"),
    ],
)
def test_record_refuses_malformed_fields(change: dict, message: str) -> None:
    fields = dict(
        a="r1", version_a=1, b="r2", version_b=1, accepted=True, matrix=np.eye(3),
        covariance=np.eye(3), score=0.5, decided_by="r1",
    )  # fmt: skip
    fields.update(change)
    with pytest.raises(ValueError, match=message):
        LinkRecord(**fields)


@given(
    st.lists(
        st.tuples(
            st.integers(1, 99),
            st.integers(1, 99),
            st.booleans(),
            st.floats(-1e6, 1e6),
            st.floats(-np.pi, np.pi),
            st.floats(0.0, 1.0),
        ),
        max_size=8,
    )
)
def test_links_file_round_trips_every_record(fields: list) -> None:
    """loads(dumps(records)) gives the records back, field for field, floats exactly."""
    records = [
        LinkRecord(
            f"a{a}", V(a, 1), f"b{b}", V(b), ok, rigid_matrix(psi, x, -x), np.eye(3) * x * x,
            score, f"a{a}",
        )
        for a, b, ok, x, psi, score in fields
    ]  # fmt: skip
    back = loads(dumps(records))
    assert [r.to_json() for r in back] == [r.to_json() for r in records]
    assert dumps(back) == dumps(records)


@given(st.text(max_size=200))
def test_loads_raises_only_value_error(text: str) -> None:
    with contextlib.suppress(ValueError):
        loads(text)


@given(
    st.lists(
        st.dictionaries(
            st.sampled_from(["a", "version_a", "b", "version_b", "accepted", "matrix", "score"]),
            st.one_of(st.integers(), st.text(max_size=3), st.none(), st.lists(st.integers())),
        ),
        max_size=3,
    )
)
def test_loads_of_json_garbage_raises_only_value_error(items: list) -> None:
    with contextlib.suppress(ValueError):
        loads(json.dumps(items))


def test_a_link_holds_for_every_version_of_its_epochs() -> None:
    link = rec("r1", 3, "r2", 5, ma=7)
    assert link.key == ("r1", 3, "r2", 5) and epoch_of(link.version_a) == 3
    assert link.current({"r1": V(3, 9), "r2": V(5, 1)})
    assert not link.current({"r1": V(4), "r2": V(5)})


def test_every_agent_uses_the_same_candidate_whatever_the_arrival_order() -> None:
    first, second = rec("r1", 1, "r2", 1, by="r2", ma=3), rec("r1", 1, "r2", 1, by="r1", mb=2)
    one, other = LinkCache([first]), LinkCache([second])
    assert other.add(first) is False and one.add(second) is True  # r1's candidate wins
    assert one.get(("r1", 1, "r2", 1)) is second and other.get(("r1", 1, "r2", 1)) is second
    assert not one.add(second) and len(one.candidates()) == 2


def test_prune_keeps_current_future_and_newest_superseded_epochs() -> None:
    cache = LinkCache([rec("r1", 1, "r2", 1), rec("r1", 2, "r2", 1), rec("r1", 3, "r2", 2)])
    cache.add(rec("r1", 4, "r2", 2))
    cache.prune({"r1": V(4, 6), "r2": V(2, 1)})
    assert [r.key for r in cache.records()] == [("r1", 3, "r2", 2), ("r1", 4, "r2", 2)]
    cache.prune({"r1": V(3), "r2": V(2)})  # a link of epochs not yet seen here is kept
    assert ("r1", 4, "r2", 2) in [r.key for r in cache.records()]


def test_needed_keys_are_pairs_without_a_link_of_the_current_epochs() -> None:
    cache = LinkCache([rec("r1", 2, "r2", 1), rec("r1", 1, "r3", 1)])
    versions = {"r1": V(2, 5), "r2": V(1, 3), "r3": V(4)}
    assert needed_keys(versions, cache) == [("r1", 2, "r3", 4), ("r2", 1, "r3", 4)]


def test_one_robot_of_the_pair_registers_first_others_after_timeouts() -> None:
    key = ("r2", 1, "r5", 1)
    first = first_registrar("r2", "r5", ["r1", "r2", "r5"])
    second = "r5" if first == "r2" else "r2"
    ring = ["r1", "r2", "r5"]
    assert wait_before_computing(first, key, 4.0, ring) == 0.0
    assert wait_before_computing(second, key, 4.0, ring) == 4.0
    assert wait_before_computing("r1", key, 4.0, ring) == 8.0
    seen = {key: 100.0}
    assert Turns().due(second, [key], seen, 103.9, 4.0, ring) == []
    assert Turns().due(second, [key], seen, 104.0, 4.0, ring) == [key]
    assert Turns().due(first, [key], seen, 100.0, 4.0, ring) == [key]


@pytest.mark.parametrize("n", [2, 3, 5, 8])
def test_first_registrars_spread_the_work_evenly(n: int) -> None:
    robots = [f"r{i}" for i in range(1, n + 1)]
    pairs = [(a, b) for i, a in enumerate(robots) for b in robots[i + 1 :]]
    load = [sum(first_registrar(a, b, robots) == r for a, b in pairs) for r in robots]
    assert sum(load) == len(pairs) and max(load) - min(load) <= 1


def test_own_pairs_are_due_first() -> None:
    keys = [("r1", 1, "r2", 1), ("r3", 1, "r4", 1)]
    first = dict.fromkeys(keys, 0.0)
    assert Turns().due("r3", keys, first, 100.0, 1.0) == [("r3", 1, "r4", 1), ("r1", 1, "r2", 1)]


_ROBOTS = [f"r{i}" for i in range(1, 7)]
_KEY = st.tuples(
    st.sampled_from(_ROBOTS), st.integers(1, 3), st.sampled_from(_ROBOTS), st.integers(1, 3)
).filter(lambda k: k[0] < k[2])
_CALL = st.tuples(
    st.lists(_KEY, max_size=8, unique=True),
    st.sampled_from([0.0, 1.5, 4.5]),  # now: before, between and after the waits of 4 s
    st.sampled_from([4.0, 4.0, 1.0]),  # timeout
    st.none() | st.frozensets(st.sampled_from(_ROBOTS)),  # alive
    st.booleans(),  # the circle without its last robot
)


@settings(max_examples=300)
@given(
    st.sampled_from(_ROBOTS),
    st.lists(st.sampled_from(_ROBOTS), min_size=3, unique=True),
    st.lists(_CALL, min_size=1, max_size=12),
)
def test_turns_kept_from_call_to_call_answer_as_new_ones(me, robots, calls) -> None:
    """A worker's Turns keeps each key's wait while the circle, the robots alive and the
    timeout stay: whatever the calls before, it answers as a new Turns would."""
    turns, circle = Turns(), sorted(robots)
    for keys, now, timeout, alive, smaller in calls:
        robots = circle[:-1] if smaller else circle
        opened = dict.fromkeys(keys, 0.0)
        want = Turns().due(me, keys, opened, now, timeout, robots, alive)
        assert turns.due(me, keys, opened, now, timeout, robots, alive) == want


def test_select_links_prefers_current_epochs_and_reports_settled() -> None:
    cache = LinkCache([rec("r1", 1, "r2", 1), rec("r1", 2, "r2", 1)])
    chosen, settled = select_links({"r1": V(2, 4), "r2": V(1, 9)}, cache)
    assert [c.key for c in chosen] == [("r1", 2, "r2", 1)] and settled
    chosen, settled = select_links({"r1": V(3), "r2": V(1)}, cache)
    assert [c.key for c in chosen] == [("r1", 2, "r2", 1)] and not settled
    _, settled = select_links({"r1": V(2), "r2": V(1), "r3": V(1)}, cache)
    assert not settled  # pairs with r3 have no link at all yet


def test_a_robot_that_left_hands_its_turn_on_at_once() -> None:
    ring = ["r1", "r2", "r3"]
    key = ("r1", 1, "r2", 1)
    first = first_registrar("r1", "r2", ring)
    second = "r2" if first == "r1" else "r1"
    everyone = {"r1", "r2", "r3"}
    assert wait_before_computing(second, key, 6.0, ring, everyone) == 6.0
    assert wait_before_computing(second, key, 6.0, ring, everyone - {first}) == 0.0
    assert wait_before_computing("r3", key, 6.0, ring, everyone) == 12.0
    assert wait_before_computing("r3", key, 6.0, ring, {"r3"}) == 6.0


def test_ring_distance_is_the_shorter_way_round() -> None:
    ring = ["r1", "r2", "r3", "r4", "r5"]
    assert [ring_distance("r1", b, ring) for b in ring[1:]] == [1, 2, 2, 1]
    assert ring_distance("r4", "r2", ring) == ring_distance("r2", "r4", ring) == 2


def test_searches_go_by_waves_checks_are_always_open() -> None:
    """Nothing linked: only neighbours on the circle; a pair a chain reaches, at any time."""
    ring = ["r1", "r2", "r3", "r4", "r5"]
    keys = [(a, 1, b, 1) for i, a in enumerate(ring) for b in ring[i + 1 :]]
    first = open_keys(keys, set(), ring)
    assert sorted((k[0], k[2]) for k in first) == [
        ("r1", "r2"), ("r1", "r5"), ("r2", "r3"), ("r3", "r4"), ("r4", "r5"),
    ]  # fmt: skip
    # every first-wave pair decided, r1-r3 predicted by a chain: the second wave opens
    rest = [k for k in keys if k not in first]
    chained = {("r1", 1, "r3", 1)}
    assert sorted(open_keys(rest, chained, ring)) == sorted(rest)
    # a first-wave pair still to search holds the second wave back, not the check
    held = [("r1", 1, "r2", 1), ("r1", 1, "r3", 1), ("r2", 1, "r4", 1)]
    assert open_keys(held, chained, ring) == held[:2]


@given(st.integers(2, 12), st.data())
def test_open_keys_always_leave_something_to_do(n: int, data: st.DataObject) -> None:
    """Whatever is needed and predicted, some key is open: no wave waits forever."""
    ring = [f"r{i:02d}" for i in range(n)]
    pairs = [(a, 1, b, 1) for i, a in enumerate(ring) for b in ring[i + 1 :]]
    keys = data.draw(st.lists(st.sampled_from(pairs), min_size=1, unique=True))
    predicted = set(data.draw(st.lists(st.sampled_from(keys), unique=True)))
    opened = open_keys(keys, predicted, ring)
    assert opened and predicted <= set(opened) and set(opened) <= set(keys)
    waves = {ring_distance(k[0], k[2], ring) for k in opened if k not in predicted}
    assert len(waves) <= 1


@given(st.permutations(range(4)))
def test_one_robots_two_decisions_on_the_same_versions_are_chosen_alike_everywhere(order):
    # A robot that decided a pair, crashed before its links file was written and decided it
    # again on the same versions holds the second decision first; its peers hold the first.
    # Both come to hold both, in whatever order: each must then use the same one.
    v = 5 << EPOCH_SHIFT
    cov = np.diag([0.5, 0.5, 1e-5])

    def decided(matrix, accepted=True, score=0.9):
        return LinkRecord("r1", v, "r2", v, accepted, matrix, cov, score, "r1")

    candidates = [
        decided(rigid_matrix(0.0, 10.0, 0.0)),
        decided(rigid_matrix(0.02, 13.0, 1.0), score=0.8),
        decided(rigid_matrix(0.0, 10.0, 0.0), accepted=False, score=0.0),
        decided(rigid_matrix(-0.0, 10.0, -0.0)),  # the first as the wire gives it back
    ]
    cache = LinkCache()
    for i in order:
        cache.add(candidates[i])
    used = cache.get(candidates[0].key)
    reference = LinkCache(candidates)
    assert used is not None and used.to_json() == reference.get(candidates[0].key).to_json()
    # the two copies of one decision that differ only in the sign of a zero are one
    assert len(cache.candidates()) == 3


def candidate(minor_b: int, revision: int, by: str = "r1", holds: int = 0) -> LinkRecord:
    """A grey-zone candidate of epochs (1, 1) decided on ``V(1, 0)`` / ``V(1, minor_b)``."""
    return LinkRecord(
        "r1", V(1), "r2", V(1, minor_b), False, rigid_matrix(0.1, 2.0, 3.0), np.eye(3), 0.7, by,
        state="candidate", margin=0.4, reason="grey zone", holds=holds, revision=revision,
    )  # fmt: skip


def test_a_candidate_of_older_versions_is_needed_again_and_its_recheck_supersedes_it() -> None:
    cache = LinkCache([candidate(0, 0)])
    assert needed_keys({"r1": V(1), "r2": V(1)}, cache) == []
    assert needed_keys({"r1": V(1), "r2": V(1, 1)}, cache) == [("r1", 1, "r2", 1)]
    # a later revision wins whoever decided it, so every agent ends on the re-check
    assert cache.add(candidate(1, 1, by="r2", holds=1))
    assert cache.get(("r1", 1, "r2", 1)).holds == 1
    assert needed_keys({"r1": V(1), "r2": V(1, 1)}, cache) == []
    assert not cache.add(candidate(0, 0, by="r0"))  # an older revision does not come back
    # and only the latest revision is held: a candidate's history does not pile up
    assert [r.revision for r in cache.candidates()] == [1]


def test_a_links_file_of_before_the_lifecycle_reads_as_its_outcome() -> None:
    old = rec("r1", 1, "r2", 1, accepted=False).to_json()
    for name in ("state", "margin", "first_margin", "reason", "first_a", "first_b", "holds",
                 "revision"):  # fmt: skip
        del old[name]
    (back,) = loads(json.dumps([old]))
    assert (back.state, back.revision, back.first_b) == ("rejected", 0, V(1))
    kept = candidate(1, 1)
    (again,) = loads(dumps([kept]))
    assert again.to_json() == kept.to_json()


def test_a_record_whose_state_contradicts_its_outcome_is_refused() -> None:
    with pytest.raises(ValueError, match="a candidate link cannot have accepted=True"):
        LinkRecord("r1", 1, "r2", 1, True, np.eye(3), np.eye(3), 0.9, "r1", state="candidate")
    with pytest.raises(ValueError, match="first_b is newer"):
        LinkRecord("r1", 1, "r2", 1, False, np.eye(3), np.eye(3), 0.9, "r1", first_b=2)


def test_a_pair_decided_without_a_search_holds_the_later_waves() -> None:
    """A first-wave pair whose map was too small to search keeps the second wave closed;
    held in the second wave, it closes nothing the first wave holds open."""
    ring = ["r1", "r2", "r3", "r4", "r5"]
    second = [("r1", 1, "r3", 1), ("r2", 1, "r4", 1)]
    assert open_keys(second, set(), ring, holding=[("r1", "r2")]) == []
    assert open_keys(second, set(), ring) == second
    assert open_keys(second, set(), ring, holding=[("r2", "r4")]) == second
