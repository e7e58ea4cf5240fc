"""The agent daemon: one Zenoh session, the robot's own source, and the fleet's maps.

Threads (zenoh-notes.md: callbacks run one at a time per subscriber, a slow one stalls it):

- Zenoh callback threads only count bytes and enqueue raw payloads; queryables answer
  from bytes prepared in advance, or encode just the few tiles a fetch names (at most 256);
- the main thread (:meth:`Agent.run`) decodes and reassembles what arrived, steps the
  source, publishes new versions of the own map, re-announces its manifest, fetches what
  is missing from the ``latest`` queryables, and persists;
- the fusion worker (:mod:`agent.worker`) registers pairs and rebuilds the global maps.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import zenoh

from agent import wire
from agent.book import FleetBook, next_version
from agent.counters import Counters
from agent.failpoints import failpoint
from agent.globalmap import Component, FuseFn, component_of
from agent.inbox import MAX_BYTES, Inbox
from agent.keys import FleetKeys
from agent.links import LinkRecord
from agent.sources import ChangeGate, SourceSpec, epoch_due, make_source
from agent.state import StateDir, StoredMap, atomic_write_bytes
from agent.worker import FusionWorker, GlobalState, RegisterFn, merge_registration
from agent.zenoh_config import ZenohOptions, build_config
from pgvd.grid import Grid
from protocol.auth import seal
from protocol.errors import ProtocolError
from protocol.fetch import fetch_parameters, parse_fetch

log = logging.getLogger("pgvd.agent")


@dataclass(frozen=True)
class AgentOptions:
    """Everything ``pgvd agent`` configures; see :mod:`agent.cmd_agent` for the meaning."""

    robot: str
    source: SourceSpec
    state_dir: Path
    fleet: str = "default"
    out_dir: Path | None = None
    zenoh: ZenohOptions = field(default_factory=ZenohOptions)
    key: bytes | None = None
    frame: tuple[float, float, float] | None = None
    resolution: float = 0.1
    speed: float = 50.0
    link_timeout: float = 6.0
    announce_period: float = 2.0
    status_period: float = 1.0
    tiles: ZenohOptions | None = None
    min_change: float = 0.05
    min_interval: float = 1.0
    min_agreement: float | None = None
    epoch_change: float = 0.15
    inbox_bytes: int = MAX_BYTES


class Agent:
    """One robot's daemon; :meth:`run` blocks until ``stop`` is set."""

    def __init__(
        self,
        opts: AgentOptions,
        register: RegisterFn | None = None,
        fuse: FuseFn | None = None,
    ) -> None:
        self.opts = opts
        self.me = opts.robot
        self.keys = FleetKeys(opts.fleet)
        self.counters = Counters()
        self.book = FleetBook()
        self.state = StateDir(opts.state_dir)
        self.out_dir = Path(opts.out_dir or opts.state_dir)
        # Bounded in count and bytes; what does not fit is dropped as "overload".
        self.inbox = Inbox(max_bytes=opts.inbox_bytes)
        self.inbound = wire.Inbound(opts.fleet, opts.key)
        self.outbound = wire.Outbound(
            opts.fleet, self.me, opts.key, datagrams=opts.tiles is not None
        )
        self.alive: dict[str, bool] = {}
        self.started = time.time()
        self._fetch_after: dict[str, float] = {}
        self._fetched_at: dict[str, float] = {}
        self._links_dirty = False
        self._global: GlobalState | None = None
        self._global_lock = threading.Lock()
        self._own_digest: str | None = None
        self._status_bytes = b"{}"
        self._last_update: float | None = None
        self._settled_at: float | None = None
        self._source_pending = False
        self._epoch_base: Grid | None = None  # own map when the current epoch began
        self._status_due = threading.Event()  # a new global map: refresh the status now
        self._load_state()
        self.source = make_source(
            opts.source, self.me, opts.frame, opts.resolution, opts.speed, self._resume
        )
        self.gate = ChangeGate(opts.min_change, opts.min_interval)
        own = self.book.map_of(self.me)
        self.gate.reset(own[1] if own else None, time.monotonic())
        self.worker = FusionWorker(
            self.me,
            self.book,
            register or merge_registration(opts.min_agreement),
            self._on_link,
            self._on_global,
            opts.link_timeout,
            fuse,
        )

    # ------------------------------------------------------------------ state

    def _load_state(self) -> None:
        maps, errors = self.state.load_maps()
        links, link_errors = self.state.load_links()
        for line in errors + link_errors:
            log.warning("state: skipped %s", line)
        self._resume: StoredMap | None = maps.get(self.me)
        for robot, stored in maps.items():
            # Own maps are persisted as the source holds them (to resume integrating).
            grid = wire.on_the_wire(stored.grid) if robot == self.me else stored.grid
            self.book.put_map(robot, stored.version, grid)
        for rec in links:
            self.book.add_link(rec)
        if maps:
            log.info("state: loaded %d maps and %d links", len(maps), len(links))

    # --------------------------------------------------------------- callbacks

    def _enqueue(self, kind: str) -> Callable[[zenoh.Sample], None]:
        def callback(sample: zenoh.Sample) -> None:
            data = sample.payload.to_bytes()
            self.counters.add("bytes_received", len(data))
            self.counters.add("messages_received")
            self._offer((kind, str(sample.key_expr), data))

        return callback

    def _on_reply(self, reply: zenoh.Reply) -> None:
        if reply.ok is None:
            return
        sample = reply.ok
        data = sample.payload.to_bytes()
        self.counters.add("bytes_received", len(data))
        self._offer(("reply", str(sample.key_expr), data))

    def _offer(self, item: tuple[str, str, bytes]) -> None:
        """Queue for the main thread, or count an ``overload`` drop: never block Zenoh."""
        if not self.inbox.offer(item):
            detail = f"receive queue full ({len(self.inbox)} messages, {self.inbox.queued_bytes} B)"
            self.counters.drop("overload", item[1], detail)

    def _on_alive(self, sample: zenoh.Sample) -> None:
        robot = self.keys.robot_of(str(sample.key_expr), "alive")
        if robot is None or robot == self.me:
            return
        joined = sample.kind == zenoh.SampleKind.PUT
        self._offer(("alive", robot, b"1" if joined else b"0"))

    def _answer_latest(self, query: zenoh.Query) -> None:
        params = query.parameters
        try:
            fetch = parse_fetch(params.get("v"), params.get("tiles"))
        except ProtocolError as exc:
            self.counters.drop(exc.reason, "query", f"fetch {str(params)[:80]!r}: {exc}")
            return
        for key, data in self.outbound.latest_replies(self.keys, fetch):
            query.reply(key, data)
            self.counters.add("bytes_sent", len(data))

    def _answer_links(self, query: zenoh.Query) -> None:
        for i, rec in enumerate(self.book.link_candidates()):
            data = wire.encode_link(self.opts.fleet, rec, self.opts.key)
            query.reply(self.keys.links_reply(self.me, i), data)
            self.counters.add("bytes_sent", len(data))

    def _answer_status(self, query: zenoh.Query) -> None:
        payload = self._status_bytes
        mac = None if self.opts.key is None else seal(payload, self.opts.key)
        query.reply(self.keys.status(self.me), payload, attachment=mac)

    # ---------------------------------------------------------- worker hooks

    def _on_link(self, rec: LinkRecord) -> None:
        data = wire.encode_link(self.opts.fleet, rec, self.opts.key)
        self.session.put(
            self.keys.link(rec.a, rec.b), data, congestion_control=zenoh.CongestionControl.BLOCK
        )
        self.counters.add("bytes_sent", len(data))
        self.counters.add("links_published")
        self._links_dirty = True

    def _on_global(self, state: GlobalState) -> None:
        with self._global_lock:
            self._global = state
        own = component_of(state.components, self.me)
        if own is not None and own.digest != self._own_digest:
            self._write_global(own)
            self._own_digest = own.digest
        if state.settled and self._settled_at is None:
            self._settled_at = time.time()
        elif not state.settled:
            self._settled_at = None
        self._status_due.set()

    def _write_global(self, comp: Component) -> None:
        from pgvd.io import write_map, write_png
        from pgvd.render import grid_image

        try:
            write_map(self.out_dir / "global.yaml", comp.grid)
            write_png(self.out_dir / "global.png", grid_image(comp.grid.probability()))
        except OSError as exc:
            log.error("cannot write the global map to %s: %s", self.out_dir, exc)

    # ------------------------------------------------------------------- run

    def run(self, stop: threading.Event) -> int:
        """Serve until ``stop`` is set; returns 0 after a clean shutdown."""
        cfg = build_config(self.opts.zenoh)
        k = self.keys
        remote = zenoh.Locality.REMOTE
        with zenoh.open(cfg) as session, contextlib.ExitStack() as stack:
            self.session = session
            self.tiles_pub = self._tile_publisher(session, stack)
            self.manifest_pub = stack.enter_context(
                session.declare_publisher(
                    k.manifest(self.me), congestion_control=zenoh.CongestionControl.BLOCK
                )
            )
            for key, kind in ((k.tiles(), "tiles"), (k.manifest(), "manifest"), (k.link(), "link")):
                stack.enter_context(
                    session.declare_subscriber(key, self._enqueue(kind), allowed_origin=remote)
                )
            stack.enter_context(session.declare_queryable(k.latest(self.me), self._answer_latest))
            stack.enter_context(session.declare_queryable(k.links(self.me), self._answer_links))
            stack.enter_context(session.declare_queryable(k.status(self.me), self._answer_status))
            stack.enter_context(session.liveliness().declare_token(k.alive(self.me)))
            stack.enter_context(
                session.liveliness().declare_subscriber(k.alive(), self._on_alive, history=True)
            )
            log.info("agent %s up in fleet %s (pid %d)", self.me, self.opts.fleet, os.getpid())
            self._republish_persisted()
            self.worker.start()
            try:
                self._loop(stop)
            finally:
                self.worker.stop(timeout=0.5)
                self._persist_links()
                self._refresh_status()
        return 0

    def _tile_publisher(
        self, session: zenoh.Session, stack: contextlib.ExitStack
    ) -> zenoh.Publisher:
        """Tiles go reliably on ``session``, or best-effort on a tile session of their own.

        A tile session also gets a tiles subscriber, so that peers on either plane are heard.
        """
        if self.opts.tiles is None:
            return stack.enter_context(
                session.declare_publisher(
                    self.keys.tiles(self.me), congestion_control=zenoh.CongestionControl.BLOCK
                )
            )
        tile_session = stack.enter_context(zenoh.open(build_config(self.opts.tiles)))
        stack.enter_context(
            tile_session.declare_subscriber(
                self.keys.tiles(), self._enqueue("tiles"), allowed_origin=zenoh.Locality.REMOTE
            )
        )
        return stack.enter_context(
            tile_session.declare_publisher(
                self.keys.tiles(self.me),
                congestion_control=zenoh.CongestionControl.DROP,
                reliability=zenoh.Reliability.BEST_EFFORT,
            )
        )

    def _loop(self, stop: threading.Event) -> None:
        next_announce = next_status = 0.0
        while not stop.is_set():
            self._drain_inbox(deadline=time.monotonic() + 0.1)
            now = time.monotonic()
            self._step_source(now)
            self._fetch_due(now)
            if now >= next_announce:
                self._announce()
                next_announce = now + self.opts.announce_period
            if now >= next_status or self._status_due.is_set():
                self._status_due.clear()
                self._persist_links()
                self._refresh_status()
                next_status = now + self.opts.status_period

    # ------------------------------------------------------------- receiving

    def _drain_inbox(self, deadline: float) -> None:
        while time.monotonic() < deadline:
            item = self.inbox.get(timeout=0.05)
            if item is None:
                return
            kind, key, data = item
            if kind == "alive":
                self._membership(key, data == b"1")
            else:
                self._receive(kind, key, data)

    def _membership(self, robot: str, joined: bool) -> None:
        was = self.alive.get(robot)
        self.alive[robot] = joined
        self.book.set_alive({self.me} | {r for r, up in self.alive.items() if up})
        if joined and not was:
            log.info("robot %s joined", robot)
            self._fetch(robot, links=True)
        elif not joined and was:
            log.info("robot %s left", robot)

    def _receive(self, kind: str, key: str, data: bytes) -> None:
        sender = key.split("/")[3] if key.count("/") >= 3 else key
        try:
            msg = self.inbound.decode(data)
        except ProtocolError as exc:  # counted by what it broke: framing, auth, schema, ...
            self.counters.drop(exc.reason, sender, str(exc))
            return
        if msg.fleet != self.opts.fleet:
            self.counters.drop("foreign_fleet", sender, f"fleet {msg.fleet!r}")
            return
        if isinstance(msg, wire.Link):
            self._receive_link(msg, sender)
            return
        if not isinstance(msg, wire.MAP_MESSAGES):
            self.counters.drop("unexpected_kind", sender, type(msg).__name__)
            return
        if sender != msg.robot:
            self.counters.drop("key_mismatch", sender, f"key {key} carries robot {msg.robot}")
            return
        if msg.robot == self.me:
            self.counters.drop("own_robot_id", sender, "a peer publishes under this robot's id")
            return
        held = self.book.version(msg.robot)
        if held is not None and msg.version < held:
            self.counters.drop("stale_version", msg.robot, f"v{msg.version} < held v{held}")
            return
        if held is not None and msg.version == held:
            return  # a re-announce or a duplicate reply: nothing new
        try:
            done = self.inbound.feed(msg)
        except ProtocolError as exc:  # e.g. a tile that contradicts its manifest: value
            self.counters.drop(exc.reason, msg.robot, str(exc))
            self._fetch_later(msg.robot)
            return
        if done is None:
            if self.inbound.incomplete(msg.robot):
                self._fetch_later(msg.robot)
            return
        version, grid = done
        if self.book.put_map(msg.robot, version, grid):
            self.counters.add("maps_received")
            self.state.save_map(msg.robot, StoredMap(version, grid))
            self._fetch_after.pop(msg.robot, None)
            log.info("map %s v%d received (%dx%d)", msg.robot, version, *grid.shape)

    def _receive_link(self, msg: wire.Link, sender: str) -> None:
        try:
            rec = wire.link_record(msg)
        except ValueError as exc:
            self.counters.drop("bad_link", sender, str(exc))
            return
        if self.book.add_link(rec):
            self.counters.add("links_received")
            self._links_dirty = True

    def _fetch_later(self, robot: str, delay: float = 0.3) -> None:
        """Tiles may still be in flight: fetch the full latest map if they do not come."""
        self._fetch_after.setdefault(robot, time.monotonic() + delay)

    def _fetch_due(self, now: float) -> None:
        for robot, when in list(self._fetch_after.items()):
            if now >= when:
                del self._fetch_after[robot]
                self._fetch(robot, links=False)

    def _fetch(self, robot: str, links: bool) -> None:
        last = self._fetched_at.get(robot, -1e9)
        if time.monotonic() - last < 1.0 and not links:
            self._fetch_later(robot, 1.0)
            return
        self._fetched_at[robot] = time.monotonic()
        self.counters.add("fetches")
        consolidation = zenoh.ConsolidationMode.NONE
        self.session.get(
            self._latest_selector(robot), self._on_reply, consolidation=consolidation, timeout=5.0
        )
        if links:
            self.session.get(
                self.keys.links(robot), self._on_reply, consolidation=consolidation, timeout=5.0
            )

    def _latest_selector(self, robot: str) -> str | zenoh.Selector:
        """Only the tiles missing from the version being assembled, when that is few of them."""
        wanted = self.inbound.wanted(robot)
        params = None if wanted is None else fetch_parameters(*wanted)
        if params is None:
            return self.keys.latest(robot)
        self.counters.add("tile_fetches")
        return zenoh.Selector(self.keys.latest(robot), params)

    # ------------------------------------------------------------ publishing

    def _republish_persisted(self) -> None:
        own = self.book.map_of(self.me)
        if own is not None:
            self.outbound.prepare(own[0], own[1], previous=None)

    def _step_source(self, now: float) -> None:
        if self.source.step(now):
            self._source_pending = True
        if not self._source_pending:
            return
        grid = self.source.grid()
        if not self.gate.due(grid, now, final=self.source.done):
            return
        self._source_pending = False
        held = self.book.version(self.me)
        previous = self.book.map_of(self.me)
        try:
            sent = wire.on_the_wire(grid)
            new_epoch = epoch_due(self._epoch_base, sent, self.opts.epoch_change)
            version = next_version(held, time.time(), new_epoch)
            tiles, manifest = self.outbound.prepare(version, sent, previous)
        except ProtocolError as exc:  # e.g. a map beyond the wire's limits: keep serving
            self.counters.drop("own_map_unencodable", self.me, str(exc))
            return
        if new_epoch:
            self._epoch_base = sent
        # Persist before publishing: a peer never holds a version this agent could lose.
        own = StoredMap(version, grid, self.source.resume_state())
        self.state.save_map(self.me, own, point="state-write")  # a crash test stops mid-write
        self.book.put_map(self.me, version, sent)
        self._last_update = time.time()
        for i, data in enumerate(tiles):
            self.tiles_pub.put(data)
            self.counters.add("bytes_sent", len(data))
            if i == 0:
                failpoint("tiles-send")  # a crash test stops here: mid-publication
        self.manifest_pub.put(manifest)
        self.counters.add("bytes_sent", len(manifest))
        self.counters.add("versions_published")
        log.info("published own map v%d (%d tile messages)", version, len(tiles))

    def _announce(self) -> None:
        manifest = self.outbound.manifest()
        if manifest is not None:
            self.manifest_pub.put(manifest)
            self.counters.add("bytes_sent", len(manifest))

    def _persist_links(self) -> None:
        if self._links_dirty:
            self._links_dirty = False
            self.state.save_links(self.book.link_candidates())

    # ---------------------------------------------------------------- status

    def status(self) -> dict[str, object]:
        """The JSON status: robots, versions, links, components, traffic, drops."""
        with self._global_lock:
            glob = self._global
        versions = self.book.versions()
        robots = {
            r: {"version": v, "alive": r == self.me or self.alive.get(r, False)}
            for r, v in sorted(versions.items())
        }
        for r, up in self.alive.items():
            robots.setdefault(r, {"version": None, "alive": up})
        counters = self.counters.snapshot()
        comps = [] if glob is None else glob.components
        own = component_of(comps, self.me)
        return {
            "robot": self.me,
            "fleet": self.opts.fleet,
            "pid": os.getpid(),
            "time": time.time(),
            "started": self.started,
            "source": self.source.describe(),
            "own_version": versions.get(self.me),
            "last_update": self._last_update,
            "robots": robots,
            "links": [_link_json(rec, versions) for rec in self.book.links()],
            "components": [
                {
                    "anchor": c.anchor,
                    "members": list(c.members),
                    "versions": c.versions,
                    "used": [list(p) for p in c.used],
                    "rejected": [list(p) for p in c.rejected],
                    "digest": c.digest,
                    "shape": list(c.grid.shape),
                    "unblurred": list(c.unblurred),
                }
                for c in comps
            ],
            "global": None
            if own is None
            else {"anchor": own.anchor, "digest": own.digest, "members": list(own.members)},
            "settled": bool(glob and glob.settled and _versions_of(comps) == versions),
            "settled_at": self._settled_at,
            "merges": self.worker.merges,
            "merge_seconds": round(self.worker.merge_seconds, 3),
            "bytes_sent": counters["counts"].get("bytes_sent", 0),
            "bytes_received": counters["counts"].get("bytes_received", 0),
            "counts": counters["counts"],
            "drops": counters["drops"],
            "inbox": {"messages": len(self.inbox), "bytes": self.inbox.queued_bytes},
        }

    def _refresh_status(self) -> None:
        status = self.status()
        self._status_bytes = json.dumps(status).encode()
        try:
            atomic_write_bytes(self.state.root / "status.json", self._status_bytes)
        except OSError as exc:
            log.error("cannot write status: %s", exc)


def _link_json(rec: LinkRecord, versions: dict[str, int]) -> dict[str, object]:
    psi = float(np.degrees(np.arctan2(rec.matrix[0, 1], rec.matrix[0, 0])))
    return {
        "a": rec.a,
        "version_a": rec.version_a,
        "b": rec.b,
        "version_b": rec.version_b,
        "accepted": rec.accepted,
        "score": round(rec.score, 4),
        "rotation_deg": round(psi, 3),
        "matrix": rec.matrix.tolist(),
        "decided_by": rec.decided_by,
        # False for a link of older epochs that stands in while the current one is computed.
        "current": rec.current(versions),
    }


def _versions_of(components: list[Component]) -> dict[str, int]:
    return {r: v for c in components for r, v in c.versions.items()}
