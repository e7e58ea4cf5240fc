"""The fusion worker: pairwise registration and global-map rebuilds on a thread of their own.

Zenoh callbacks only enqueue (Zenoh runs a subscriber's callbacks one at a time, so a slow one
delays every later sample), and the receiving thread only reassembles and stores maps;
everything that takes CPU time, the merge (Sec. IV) and the fusion (33)-(37), runs here, one
job at a time:

1. if some pair lacks a link of its latest versions and it is this agent's turn
   (:func:`agent.links.due_keys`), register it, cache and publish the link, loop;
2. otherwise, if the maps or the chosen links changed, rebuild the global maps.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from agent.book import FleetBook, Snapshot
from agent.globalmap import Component, FuseFn, build_components
from agent.links import LinkKey, LinkRecord, due_keys
from agent.memory import release_free_memory
from pgvd.grid import Grid

log = logging.getLogger("pgvd.agent")


@dataclass(frozen=True)
class Registration:
    """What a pairwise registration decided; ``matrix`` maps B pixels to A pixels."""

    accepted: bool
    matrix: np.ndarray
    covariance: np.ndarray
    score: float


RegisterFn = Callable[[Grid, Grid], Registration]


def merge_registration(min_agreement: float | None = None) -> RegisterFn:
    """:func:`pgvd.merge.merge` as a :data:`RegisterFn` (rho test (32) plus global check).

    ``min_agreement`` overrides the merge's acceptance threshold on the overlay agreement
    (None keeps the merge's own): a fleet may want it stricter than a one-off merge,
    because a false link corrupts the global map of every agent, not one output file.
    """
    from dataclasses import replace

    from pgvd.merge import MergeParams, merge

    params = MergeParams(diagnostics=False)
    if min_agreement is not None:
        params = replace(params, min_agreement=min_agreement)

    def register(a: Grid, b: Grid) -> Registration:
        res = merge(a, b, params)
        matrix = np.asarray(res.matrix, dtype=np.float64)
        cov = np.asarray(res.covariance, dtype=np.float64)
        score = float(res.score) if np.isfinite(res.score) else 0.0
        if not (res.accepted and np.isfinite(matrix).all() and np.isfinite(cov).all()):
            # A rejection's transform means nothing; keep the record finite for the wire.
            return Registration(False, np.eye(3), np.zeros((3, 3)), score)
        return Registration(True, matrix, cov, score)

    return register


@dataclass(frozen=True)
class GlobalState:
    """The last rebuild: its components, and whether every pair had its latest link."""

    components: list[Component]
    settled: bool
    built_at: float


class FusionWorker:
    """Runs registrations and rebuilds until :meth:`stop`.

    Parameters
    ----------
    me : this agent's robot id (decides whose turn a pair is).
    book : the shared :class:`FleetBook`.
    register : pairwise registration, deterministic in its inputs.
    on_link : called with each link this worker decided (to publish and persist it).
    on_global : called with each new :class:`GlobalState`.
    link_timeout : seconds to wait for the lower robot's agent before registering.
    fuse : fusion function for :func:`agent.globalmap.build_components`.
    """

    def __init__(
        self,
        me: str,
        book: FleetBook,
        register: RegisterFn,
        on_link: Callable[[LinkRecord], None],
        on_global: Callable[[GlobalState], None],
        link_timeout: float = 4.0,
        fuse: FuseFn | None = None,
    ) -> None:
        self.me = me
        self.book = book
        self.register = register
        self.on_link = on_link
        self.on_global = on_global
        self.link_timeout = link_timeout
        self.fuse = fuse
        self.merges = 0
        self.merge_seconds = 0.0
        self._stop = threading.Event()
        self._wake = threading.Event()
        self._built: tuple[object, ...] | None = None
        self._rebuilt_at = -np.inf
        #: Seconds between rebuilds of a global map still waiting for links.
        self.preview_interval = 3.0
        self._thread = threading.Thread(target=self._run, name="pgvd-fusion", daemon=True)

    def start(self) -> None:
        self._thread.start()

    def wake(self) -> None:
        """The book moved forward: look for work now rather than at the next poll."""
        self._wake.set()

    def stop(self, timeout: float = 1.0) -> None:
        self._stop.set()
        self._wake.set()
        self._thread.join(timeout)

    def _run(self) -> None:
        while not self._stop.is_set():
            self._wake.wait(0.2)  # also polls: a pair's turn comes with time alone
            self._wake.clear()
            try:
                while not self._stop.is_set():
                    more = self.step()
                    # After every job, not only when idle: under continuous updates the worker
                    # is rarely idle, and a soak then showed RSS at merge high-water marks
                    # (growth 14 % against 7 %). Faulting pages back in costs ~5 % of a merge.
                    release_free_memory()
                    if not more:
                        break
            except Exception:  # a bug here must not kill the agent silently
                log.exception("fusion worker step failed")
                time.sleep(0.5)

    def step(self, now: float | None = None) -> bool:
        """Do one job; True if there may be more to do right away."""
        now = time.monotonic() if now is None else now
        snap = self.book.snapshot(now)
        due = due_keys(
            self.me,
            snap.needed,
            snap.first_needed,
            now,
            self.effective_timeout(len(snap.maps)),
            sorted(snap.maps),
            snap.alive,
        )
        if due:
            self._register(snap, due[0])
            return True
        signature = (
            tuple(sorted((r, v) for r, (v, _) in snap.maps.items())),
            tuple(ln.key for ln in snap.links),
        )
        # An unsettled map is only a preview: rebuilding it on every link of a round
        # would take CPU from the registrations the settled map waits for.
        if (
            snap.maps
            and signature != self._built
            and (snap.settled or now - self._rebuilt_at >= self.preview_interval)
        ):
            self._built = signature  # a failing rebuild is not retried until inputs change
            self._rebuilt_at = now
            self._rebuild(snap)
        return False

    def effective_timeout(self, n_robots: int) -> float:
        """``link_timeout`` plus the time a peer needs for its share of a round of pairs.

        When every map changes at once, the first registrar of a pair has about
        ``(n - 1) / 2`` pairs queued; stepping in before it could finish them only
        duplicates work on a busy machine.  This agent's own mean registration time
        stands in for the peers'.
        """
        mean = self.merge_seconds / self.merges if self.merges else 0.0
        return self.link_timeout + mean * max(n_robots - 1, 0) / 2.0

    def _register(self, snap: Snapshot, key: LinkKey) -> None:
        a, _, b, _ = key  # epochs; the link records the versions it was computed on
        va, vb = snap.maps[a][0], snap.maps[b][0]
        t0 = time.monotonic()
        try:
            res = self.register(snap.maps[a][1], snap.maps[b][1])
        except Exception as exc:  # bad maps are an outcome (rejected), not a crash
            log.warning("registration of %s v%d / %s v%d failed: %s", a, va, b, vb, exc)
            res = Registration(False, np.eye(3), np.zeros((3, 3)), 0.0)
        self.merges += 1
        self.merge_seconds += time.monotonic() - t0
        rec = LinkRecord(a, va, b, vb, res.accepted, res.matrix, res.covariance, res.score, self.me)
        log.info(
            "link %s v%d - %s v%d: %s score %.3f (%.2f s)",
            a, va, b, vb, "accepted" if res.accepted else "rejected", res.score,
            time.monotonic() - t0,
        )  # fmt: skip
        if self.book.add_link(rec):
            self.on_link(rec)

    def _rebuild(self, snap: Snapshot) -> None:
        components = build_components(snap.maps, snap.links, self.fuse)
        self.on_global(GlobalState(components, snap.settled, time.time()))
