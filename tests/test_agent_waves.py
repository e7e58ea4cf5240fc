"""The keys open kept from one book change to the next (:class:`agent.links.Waves`), and the
chains built of the book's accepted links, are those computed from scratch
(:func:`agent.links.open_keys` over every key needed, :class:`Chains` of every link), at every
step: on random sequences of book events, and in a simulated fleet replaying the Intel log."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from agent.book import FleetBook, Snapshot
from agent.links import EPOCH_SHIFT, GATED, LinkKey, LinkRecord, open_keys
from agent.scenario import LOG
from agent.worker import Chains, FusionWorker, Registration
from pgvd.grid import Grid
from pgvd.posegraph import components

ROBOTS = [f"r{i}" for i in range(1, 9)]


def _grid(seed: int) -> Grid:
    lo = np.zeros((20, 20), np.float32)
    lo[seed % 12 : seed % 12 + 5, 3:15] = 2.0
    return Grid(lo, 0.1)


def _fresh(
    worker: FusionWorker, snap: Snapshot, robots: list[str], now: float
) -> tuple[set[LinkKey], list[LinkKey]]:
    """The keys checkable and open, computed from scratch as before any memo: every key
    needed looked at, on :class:`Chains` built anew."""
    chains = Chains(snap.maps, snap.links)
    checkable = set(snap.rechecks) | {
        k for k in snap.needed if worker._checkable(chains, k[0], k[2])
    }
    return checkable, open_keys(snap.needed, checkable, robots, worker._holding(snap, now))


def _assert_same_chains(worker: FusionWorker, snap: Snapshot) -> None:
    """The book's accepted links and re-checks, and the worker's :class:`Chains` and own
    group, are those picked and built from all the links of ``snap``."""
    assert list(snap.accepted()) == [ln for ln in snap.links if ln.accepted]
    held = {ln.key for ln in snap.links}
    assert snap.rechecks == frozenset(k for k in snap.needed if k in held)
    kept, fresh = worker._chains_of(snap), Chains(snap.maps, snap.links)
    assert kept.groups == fresh.groups
    assert [ln.identity for ln in kept.usable] == [ln.identity for ln in fresh.usable]
    pairs = [ln.pair for ln in snap.links if ln.accepted]
    own = next((g for g in components(snap.maps, pairs) if worker.me in g), ())
    assert worker._own_group(snap) == own


def _assert_same(worker: FusionWorker, snap: Snapshot, now: float) -> None:
    robots = sorted(set(snap.maps) | (snap.alive or frozenset()))
    checkable, opened = worker._open(snap, robots, now)
    want_checkable, want_opened = _fresh(worker, snap, robots, now)
    assert checkable == want_checkable
    assert opened == want_opened
    _assert_same_chains(worker, snap)


def _worker(book: FleetBook, poses: dict[str, tuple[float, float, float]]) -> FusionWorker:
    def nothing(*_: object) -> None:
        return None

    def never(a: Grid, b: Grid) -> Registration:
        raise AssertionError("no registration runs here")

    return FusionWorker("r1", book, never, nothing, nothing, check=lambda *_: None, poses=poses)


#: A book event: (kind, robot a, robot b, a choice among the kind's variants).
_events = st.lists(
    st.tuples(
        st.sampled_from(
            ["epoch", "minor", "minor", "link", "link", "late", "alive", "forget", "time"]
        ),
        st.sampled_from(ROBOTS),
        st.sampled_from(ROBOTS),
        st.integers(0, 3),
    ),
    min_size=40,
    max_size=160,
)


@settings(max_examples=60, deadline=None)
@given(events=_events, posed=st.sets(st.sampled_from(ROBOTS), max_size=3))
def test_kept_keys_open_are_those_computed_afresh_over_any_book_events(
    events: list[tuple[str, str, str, int]], posed: set[str]
) -> None:
    """New epochs and minor versions, links of every kind (accepted, rejected, gated,
    candidates re-checked at new versions), some decided on an earlier version, liveliness,
    robots forgotten, time passing past the gate's hold: after each event, the same keys
    checkable and open, accepted links, re-checks and chains as from scratch."""
    book = FleetBook()
    worker = _worker(book, {r: (1.0, 2.0, 0.0) for r in posed})
    epochs = dict.fromkeys(ROBOTS, 1)
    now = 0.0
    for step, (kind, a, b, variant) in enumerate(events, start=1):
        if kind in ("epoch", "minor"):
            epochs[a] += kind == "epoch"
            book.put_map(a, epochs[a] << EPOCH_SHIFT | step, _grid(step))
        elif kind in ("link", "late") and a != b and None not in (book.version(a), book.version(b)):
            a, b = sorted((a, b))
            accepted = variant == 0
            state = ["accepted", "rejected", "rejected", "candidate"][variant]
            reason = f"{GATED}map A has no GVD edge" if variant == 2 else ""
            # a late link was decided on an earlier minor version of a's epoch
            va, vb = book.version(a) - (kind == "late"), book.version(b)
            rec = LinkRecord(a, va, b, vb, accepted, np.eye(3), np.eye(3) * 0.1, 0.9, "r9",
                             state=state, reason=reason)  # fmt: skip
            book.add_link(rec)
        elif kind == "alive":
            book.set_alive(set(ROBOTS[: 2 + variant * 2]) | {a})
        elif kind == "forget":
            book.forget(a)
        elif kind == "time":
            now += 4.0 * variant
        _assert_same(worker, book.snapshot(), now)


@pytest.fixture(scope="module")
def intel_outcomes():
    """The three pairs of three robots on the Intel log, measured for real."""
    from bench.fleetsim_merges import measure_outcomes

    return measure_outcomes(LOG, [(3, 1.0, [(0, 1), (1, 2), (0, 2)])])


def test_kept_keys_open_are_those_computed_afresh_in_a_simulated_fleet(
    intel_outcomes, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Six robots replay their segments of the Intel log on the real fleet core; at every
    step of every agent's worker, the keys checkable and open are those from scratch."""
    from bench.fleetsim_core import Meter, Rebuilds, SimClock
    from bench.fleetsim_fleet import Scenario, SimFleet

    kept = FusionWorker._open
    compared: list[int] = []

    def checked(
        self: FusionWorker, snap: Snapshot, robots: list[str], now: float
    ) -> tuple[set[LinkKey], list[LinkKey]]:
        got = kept(self, snap, robots, now)
        assert got == _fresh(self, snap, robots, now)
        _assert_same_chains(self, snap)
        compared.append(len(snap.needed))
        return got

    monkeypatch.setattr(FusionWorker, "_open", checked)
    fleet = SimFleet(
        Scenario(6, LOG, speed=200.0, limit=120.0), intel_outcomes, Rebuilds(Meter(SimClock()))
    )
    fleet.run()
    assert fleet.agreed_at is not None
    assert len(compared) > 100 and max(compared) >= 5  # steps with many keys needed
