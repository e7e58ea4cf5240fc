"""The agent daemon: one robot's fleet core (:class:`agent.node.FleetNode`) hosted on Zenoh.

The core decides; this module moves bytes and time and carries out what the core asks. Threads:

- Zenoh callback threads only count bytes and enqueue raw payloads (with a map message's
  authenticated robot and version, so that tiles a newer version superseded leave the queue
  undecoded, :mod:`agent.inbox`), because Zenoh runs a subscriber's callbacks one at a time and
  a slow one delays every later sample; queryables answer from bytes prepared in advance, or
  encode just the few tiles a fetch names (at most 256);
- the receiving thread decodes what arrived (pure Python for deltas: most of an agent's
  receiving time) outside the core's lock, then feeds it to the core;
- the main thread (:meth:`Agent.run`) feeds the core membership changes, the source's new maps
  and the time, and is never behind a decode or a disk write;
- the persisting thread (:mod:`agent.persister`) writes the state directory: own versions
  durably, each reported to the core, which publishes it only then; peers' maps newest only;
- the fusion worker (:mod:`agent.worker`) registers pairs and rebuilds the global maps, and
  reports both to the core from its own thread.

One lock serialises the core's calls; each thread carries out the actions of its own calls
(publish, fetch, hand a write to the persisting thread, wake the fusion worker).
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path

import zenoh

from agent import actions as act
from agent.failpoints import failpoint
from agent.globalmap import Component
from agent.inbox import MAX_BYTES, Inbox, held_already, map_tag, offer_or_drop
from agent.memory import fix_mmap_threshold
from agent.node import FleetNode, Instant, NodeOptions
from agent.outputs import OutputOptions, Outputs
from agent.persister import Persister
from agent.pose import Pose
from agent.profiling import profiled
from agent.ros2_io import RosMapSubscription, declare_node
from agent.sources import RosTopicSource, SourceSpec, make_source
from agent.state import StateDir, StoredMap
from agent.status import HostFacts
from agent.worker import (
    FusionWorker,
    RegisterFn,
    merge_gate,
    merge_registration,
    verify_check,
)
from agent.zenoh_config import ZenohOptions, build_config

log = logging.getLogger("pgvd.agent")


@dataclass(frozen=True)
class AgentOptions:
    """Everything ``pgvd agent`` configures; see :mod:`agent.cli.agent` for the meaning."""

    robot: str
    source: SourceSpec
    state_dir: Path
    fleet: str = NodeOptions.fleet
    out_dir: Path | None = None
    zenoh: ZenohOptions = field(default_factory=ZenohOptions)
    key: bytes | None = None
    frame: tuple[float, float, float] | None = None
    resolution: float = 0.1
    speed: float = 50.0
    link_timeout: float = 6.0
    announce_period: float = NodeOptions.announce_period
    status_period: float = NodeOptions.status_period
    tiles: ZenohOptions | None = None
    min_change: float = NodeOptions.min_change
    min_interval: float = NodeOptions.min_interval
    min_agreement: float | None = None
    epoch_change: float = NodeOptions.epoch_change
    forget_after: float = NodeOptions.forget_after
    inbox_bytes: int = MAX_BYTES
    outputs: OutputOptions = field(default_factory=OutputOptions)
    known_poses: tuple[tuple[str, Pose], ...] = ()

    def node_options(self) -> NodeOptions:
        """The core's part; tiles on a session of their own go out packed for datagrams."""
        return NodeOptions(
            self.robot,
            self.fleet,
            self.key,
            self.tiles is not None,
            self.announce_period,
            self.status_period,
            self.min_change,
            self.min_interval,
            self.epoch_change,
            self.forget_after,
        )

    def session_options(self) -> ZenohOptions:
        """The main session's; ROS 2's advanced publishers and subscribers need timestamps."""
        if self.source.kind != "ros2" and not self.outputs.to_ros:
            return self.zenoh
        return replace(self.zenoh, extra={**self.zenoh.extra, "timestamping/enabled": True})


BLOCK, REMOTE = zenoh.CongestionControl.BLOCK, zenoh.Locality.REMOTE
#: Membership changes queued at most for the main thread (one per liveliness token change).
MAX_EVENTS = 4096


def _now() -> Instant:
    return Instant(time.monotonic(), time.time())


def _write_global(out_dir: Path, comp: Component) -> None:
    """This robot's global map as ``global.yaml`` (with its image) and ``global.png``."""
    from pgvd.io import write_map, write_png
    from pgvd.render import grid_image

    try:
        write_map(out_dir / "global.yaml", comp.grid)
        write_png(out_dir / "global.png", grid_image(comp.grid.probability()))
    except OSError as exc:
        log.error("cannot write the global map to %s: %s", out_dir, exc)


class Agent:
    """One robot's daemon; :meth:`run` blocks until ``stop`` is set."""

    def __init__(
        self,
        opts: AgentOptions,
        register: RegisterFn | None = None,
    ) -> None:
        fix_mmap_threshold()  # before the first merge: its arrays then never fragment the heap
        self.opts = opts
        self.state = StateDir(opts.state_dir)
        self.out_dir = Path(opts.out_dir or opts.state_dir)
        # Bounded in count and bytes; what does not fit is dropped as "overload". Messages go
        # to the receiving thread, membership changes to the main thread.
        self.inbox = Inbox(max_bytes=opts.inbox_bytes)
        self.events = Inbox(max_items=MAX_EVENTS)
        self.node = FleetNode(opts.node_options(), _now())
        self.counters, self.keys = self.node.counters, self.node.keys
        self._lock = threading.Lock()  # every thread that calls the core takes it
        self.persister = Persister(
            self.state,
            opts.robot,
            lambda robot, version: self._call(self.node.on_persisted, robot, version, _now()),
            self.counters,
        )
        self._status_bytes = b"{}"
        self._status_body = b""
        self.session: zenoh.Session | None = None  # while run() serves
        self._publishers: dict[str, zenoh.Publisher] = {}
        self._source_error: str | None = None  # the last one logged
        resume = self._load_state()
        self.source = make_source(
            opts.source, opts.robot, opts.frame, opts.resolution, opts.speed, resume
        )
        self.worker = FusionWorker(
            opts.robot,
            self.node.book,
            register or merge_registration(opts.min_agreement),
            lambda rec: self._call(self.node.on_link, rec, _now()),  # from the worker's thread
            lambda state: self._call(self.node.on_global, state, _now()),
            opts.link_timeout,
            # an injected registration (tests) decides alone; the real one verifies first
            check=verify_check(opts.min_agreement) if register is None else None,
            counters=self.counters,
            poses=dict(opts.known_poses),
            gate=merge_gate(opts.min_agreement) if register is None else None,
        )

    def _load_state(self) -> StoredMap | None:
        maps, errors = self.state.load_maps()
        links, link_errors = self.state.load_links()
        for line in errors + link_errors:
            log.warning("state: skipped %s", line)
        self.node.restore(maps, links, _now())
        if maps:
            log.info("state: loaded %d maps and %d links", len(maps), len(links))
        return maps.get(self.opts.robot)

    # ------------------------------------------------------- Zenoh callbacks

    def _on_sample(self, sample: zenoh.Sample) -> None:
        data = sample.payload.to_bytes()
        self.counters.add("bytes_received", len(data))
        self.counters.add("messages_received")
        self._enqueue(str(sample.key_expr), data)

    def _on_reply(self, reply: zenoh.Reply) -> None:
        if reply.ok is not None:
            data = reply.ok.payload.to_bytes()
            self.counters.add("bytes_received", len(data))
            self._enqueue(str(reply.ok.key_expr), data)

    def _enqueue(self, key: str, data: bytes) -> None:
        """Queue a payload for the receiving thread, tagged if it is an authentic map message
        published (or answered) under its own robot's key."""
        tag = map_tag(self.node.inbound, self.keys, key, data)
        offer_or_drop(self.inbox, ("message", key, data), self.counters, tag)

    def _on_alive(self, sample: zenoh.Sample) -> None:
        robot = self.keys.robot_of(str(sample.key_expr), "alive")
        if robot is not None:
            up = b"1" if sample.kind == zenoh.SampleKind.PUT else b"0"
            offer_or_drop(self.events, ("alive", robot, up), self.counters)

    def _answer_latest(self, query: zenoh.Query) -> None:
        params = query.parameters
        self._answer(query, self.node.answer_latest(params.get("v"), params.get("tiles")))

    def _answer_links(self, query: zenoh.Query) -> None:
        self._answer(query, self.node.answer_links())

    def _answer_status(self, query: zenoh.Query) -> None:
        self._answer(query, [self.node.answer_status(self._status_bytes)])

    def _answer(self, query: zenoh.Query, actions: list[act.Action]) -> None:
        for action in actions:
            if isinstance(action, act.Reply):
                query.reply(action.key, action.payload, attachment=action.attachment)
                self.counters.add("bytes_sent", len(action.payload))
            else:
                self._carry_out([action])

    # ------------------------------------------------------ the core's calls

    def _call(self, method: Callable[..., list[act.Action]], *args: object) -> None:
        """Call the core (one call at a time), then carry out its actions outside the lock."""
        with self._lock:
            actions = method(*args)
        self._carry_out(actions)

    def _carry_out(self, actions: list[act.Action]) -> None:
        for action in actions:
            match action:
                case act.Publish(key, payload, point):
                    self._publish(key, payload)
                    if point is not None:
                        failpoint(point)  # a crash test stops here
                case act.Fetch(selector, parameters):
                    assert self.session is not None
                    where = selector if parameters is None else zenoh.Selector(selector, parameters)
                    mode = zenoh.ConsolidationMode.NONE
                    self.session.get(where, self._on_reply, consolidation=mode, timeout=5.0)
                case act.PersistMap(robot, stored, point):
                    self.persister.save_map(robot, stored, point)
                case act.PersistLinks(records):
                    self.persister.save_links(records)
                case act.ForgetMap(robot):
                    self.persister.forget_map(robot)
                case act.PersistGlobal(component):
                    _write_global(self.out_dir, component)
                case act.WriteStatus():
                    self._write_status()
                case act.Register():
                    self.worker.wake()
                case act.Drop(reason, sender, detail):
                    self.counters.drop(reason, sender, detail)

    def _publish(self, key: str, payload: bytes) -> None:
        publisher = self._publishers.get(key)
        if publisher is not None:
            publisher.put(payload)
        else:
            assert self.session is not None
            self.session.put(key, payload, congestion_control=BLOCK)
        self.counters.add("bytes_sent", len(payload))

    def _write_status(self) -> None:
        host = HostFacts(
            os.getpid(), self.source.describe(), self.worker.merges, self.worker.merge_seconds,
            len(self.inbox), self.inbox.queued_bytes,
        )  # fmt: skip
        with self._lock:
            status = self.node.status(_now(), host)
        stamp = status.pop("time")
        body = json.dumps(status).encode()
        if body == self._status_body:
            return  # only the clock moved: readers see a change the moment one happens
        self._status_body = body
        # The time first, spliced: the rest is the body compared above, encoded once.
        self._status_bytes = b'{"time": ' + json.dumps(stamp).encode() + b", " + body[1:]
        try:
            self.state.save_status(self._status_bytes)
        except OSError as exc:
            log.error("cannot write status: %s", exc)

    # ------------------------------------------------------------------- run

    def run(self, stop: threading.Event) -> int:
        """Serve until ``stop`` is set; returns 0 after a clean shutdown."""
        k, me = self.keys, self.opts.robot
        config = build_config(self.opts.session_options())
        with zenoh.open(config) as session, contextlib.ExitStack() as stack:
            self.session = session
            manifests = session.declare_publisher(k.manifest(me), congestion_control=BLOCK)
            self._publishers = {
                k.tiles(me): self._tile_publisher(session, stack),
                k.manifest(me): stack.enter_context(manifests),
            }
            for key in (k.tiles(), k.manifest(), k.link()):
                stack.enter_context(
                    session.declare_subscriber(key, self._on_sample, allowed_origin=REMOTE)
                )
            stack.enter_context(session.declare_queryable(k.latest(me), self._answer_latest))
            stack.enter_context(session.declare_queryable(k.links(me), self._answer_links))
            stack.enter_context(session.declare_queryable(k.status(me), self._answer_status))
            stack.enter_context(session.liveliness().declare_token(k.alive(me)))
            stack.enter_context(
                session.liveliness().declare_subscriber(k.alive(), self._on_alive, history=True)
            )
            self._declare_ros_node(session, stack)
            self._follow_ros_topic(session, stack)
            outputs = Outputs(self.opts.outputs, session, self.counters)
            stack.callback(outputs.close)
            log.info("agent %s up in fleet %s (pid %d)", me, self.opts.fleet, os.getpid())
            self.persister.start()
            self.worker.start()
            halt = threading.Event()
            receiver = threading.Thread(
                target=profiled,
                args=(me, "receive", lambda: self._receive(halt)),
                name="pgvd-receive",
                daemon=True,
            )
            receiver.start()
            try:
                profiled(me, "main", lambda: self._loop(stop, outputs))
            finally:
                halt.set()
                receiver.join(timeout=0.2)  # a decode in progress is not waited for
                self.worker.stop(timeout=0.5)
                self._call(self.node.flush)
                if not self.persister.close():
                    log.error("state: writes still pending at shutdown")
        return 0

    def _tile_publisher(
        self, session: zenoh.Session, stack: contextlib.ExitStack
    ) -> zenoh.Publisher:
        """Tiles go reliably on ``session``, or best-effort on a tile session of their own.

        A tile session also gets a tiles subscriber, so that peers on either plane are heard.
        """
        key = self.keys.tiles(self.opts.robot)
        if self.opts.tiles is None:
            return stack.enter_context(session.declare_publisher(key, congestion_control=BLOCK))
        tiles = stack.enter_context(zenoh.open(build_config(self.opts.tiles)))
        heard = tiles.declare_subscriber(self.keys.tiles(), self._on_sample, allowed_origin=REMOTE)
        stack.enter_context(heard)
        drop, best_effort = zenoh.CongestionControl.DROP, zenoh.Reliability.BEST_EFFORT
        publisher = tiles.declare_publisher(key, congestion_control=drop, reliability=best_effort)
        return stack.enter_context(publisher)

    def _declare_ros_node(self, session: zenoh.Session, stack: contextlib.ExitStack) -> None:
        """The ROS 2 node token, when the agent reads or publishes a ROS topic; declared on
        the stack before the subscription and publishers, so that it is undeclared after."""
        if not (isinstance(self.source, RosTopicSource) or self.opts.outputs.to_ros):
            return
        token = declare_node(session, self.opts.outputs.ros)
        if token is not None:
            stack.callback(token.undeclare)

    def _follow_ros_topic(self, session: zenoh.Session, stack: contextlib.ExitStack) -> None:
        """A ``ros2:`` source reads the topic's subscription; refusals count as ``ros2_*``."""
        if not isinstance(self.source, RosTopicSource):
            return
        topic = self.opts.source.topic
        assert topic is not None

        def on_drop(what: str, detail: str) -> None:
            self.counters.drop(f"ros2_{what}", topic, detail)

        sub = RosMapSubscription(session, topic, self.opts.outputs.ros, on_drop)
        stack.callback(sub.close)
        self.source.attach(sub.take)

    def _loop(self, stop: threading.Event, outputs: Outputs) -> None:
        while not stop.is_set():
            self._drain_events(deadline=time.monotonic() + 0.1)
            now = _now()
            src = self.source
            if src.step(now.mono):
                self._call(self.node.on_source, src.grid(), now, src.done, src.resume_state())
            self._warn_source_error()
            self._call(self.node.tick, now)
            outputs.tick(now.mono, self.node.global_component(), self.node.book)

    def _warn_source_error(self) -> None:
        """Log a source's error when it changes: a map file that never reads (a bad YAML, an
        image that is not one) is retried every poll and would otherwise only be counted in
        the status, with the agent up and silent."""
        # the attribute, not describe(): this runs every loop, and a log replay's describe()
        # builds its grid's pixel transform; only sources that read files have one
        error = getattr(self.source, "last_error", None)
        if error and error != self._source_error:
            log.warning("source %s: %s", self.opts.source.path or self.opts.source.topic, error)
        self._source_error = error

    def _drain_events(self, deadline: float) -> None:
        """Feed the core the membership changes that come until ``deadline``."""
        while time.monotonic() < deadline:
            item = self.events.get(timeout=0.05)
            if item is None:
                return
            _, robot, up = item
            self._call(self.node.on_alive, robot, up == b"1", _now())

    def _receive(self, halt: threading.Event) -> None:
        """The receiving thread: decode each queued message outside the core's lock, then
        feed it to the core, until ``halt`` is set."""
        while not halt.is_set():
            got = self.inbox.get_tagged(timeout=0.1)
            if got is None:
                continue
            (_, key, data), tag = got
            if held_already(tag, self.opts.robot, self.node.book.version):
                continue  # the core would decode it to find nothing new
            try:
                msg = self.node.read(key, data)
                if halt.is_set():  # a decode outlasted the shutdown: the session may be gone
                    return
                if isinstance(msg, act.Drop):
                    self._carry_out([msg])
                else:
                    self._call(self.node.on_decoded, key, msg, _now())
            except Exception:  # a bug here must not leave the agent deaf
                log.exception("receiving a message on %s failed", key)
