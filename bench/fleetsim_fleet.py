"""N real :class:`agent.node.FleetNode` s and their :class:`agent.worker.FusionWorker` s in one
process, in simulated time: the host :class:`agent.daemon.Agent` is, without Zenoh or threads.

Each robot replays its segment of a CARMEN log through the real
:class:`agent.sources.CarmenSource` (as ``pgvd demo`` and :mod:`bench.fleet` do), and every 0.1
simulated s, as the daemon's loop, hands a new map to :meth:`FleetNode.on_source` and calls
:meth:`FleetNode.tick`.  The actions come out as the daemon carries them out: ``Publish`` is a
put to every robot (:mod:`bench.fleetsim_net`), ``Fetch`` a query answered by the target's
``answer_latest`` / ``answer_links``, ``PersistMap`` of the own map is on disk at once
(``on_persisted``), ``Register`` wakes the worker, ``Drop`` is counted, and the files (links,
status, global map) are not written.  The worker runs the agent's search gate (``gate=``, as
``pgvd agent`` builds it) on real verdicts (:mod:`bench.fleetsim_gate`).  A worker steps as the
real one: one job per :meth:`FusionWorker.step`, the next right after it while there is more,
else a poll ``poll`` s later or a wake; its decisions and rebuilds reach the node when the
step's charged CPU (:mod:`bench.fleetsim_core`) has passed.  The host's own work (decoding,
reassembly, encoding, the source's ray casting) is charged at its real CPU time, a payload's
decode at that of its first decode in the fleet (:mod:`bench.fleetsim_shared`, which also
keeps one copy of each peer's map for all agents), and keeps its main thread busy that
long: messages wait in the robot's inbox meanwhile, in order, as in the daemon's.  Queries
are answered at once (Zenoh's threads answer them in the daemon).

Start-up: a core is made at 0 s and its daemon's loop first turns ``startup`` s later, when
the robot also comes online.  The real daemon opens its Zenoh session in between, which
takes longer than the change gate's interval (1 s), so that its first version is the map of
its first scans, too small for any search to accept; the fleet's first searches are of those
maps.  Without the delay the gate would hold the first version back for 1 s of replay.

Liveliness: a robot that comes online sees every robot online and is seen by them after one
latency; one that goes offline (churn) or a partition that separates two robots tells both
that the other left, and they see each other again when it ends.
"""

from __future__ import annotations

import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from agent import actions as act
from agent.globalmap import component_of
from agent.node import FleetNode, Instant, NodeOptions
from agent.scenario import random_frames, segments
from agent.sources import CarmenSource, SourceSpec
from agent.status import versions_of
from agent.worker import FusionWorker, GlobalState
from bench.fleetsim_core import Rebuilds, SimClock, simulated_core, simulated_wire
from bench.fleetsim_gate import GateCache
from bench.fleetsim_merges import DrawnMerges, PairOutcome, RobotTruth
from bench.fleetsim_net import EventLoop, NetParams, Network
from bench.fleetsim_shared import SharedMaps

#: The wall clock of simulated time 0 (versions' epochs are wall seconds).
WALL0 = 1.8e9
#: Seconds between two turns of a daemon's loop.
LOOP_PERIOD = 0.1


@dataclass(frozen=True)
class Churn:
    """``robot`` is offline from ``leave`` s until ``back`` s (None: for good)."""

    robot: str
    leave: float
    back: float | None = None


@dataclass(frozen=True)
class Scenario:
    """What is simulated: ``robots`` replaying ``log`` split as :func:`agent.scenario.segments`,
    in the frames of :func:`agent.scenario.random_frames` (seed ``frames_seed``), at ``speed``
    times real time; the agents' options as ``pgvd agent``'s defaults; ``startup``: seconds
    from a core's making to its loop's first turn (module docstring).  ``cores``: the
    workers share that many cores (as :mod:`bench.fleet`'s agents share one machine's), a
    fraction standing for the share of a loaded machine they get; None gives each agent a
    computer of its own."""

    robots: int
    log: Path
    speed: float = 100.0
    resolution: float = 0.1
    link_timeout: float = 6.0
    frames_seed: int = 7
    net: NetParams = field(default_factory=NetParams)
    churn: tuple[Churn, ...] = ()
    poll: float = 0.2
    limit: float = 900.0
    cores: float | None = None
    startup: float = 1.5

    def names(self) -> list[str]:
        return [f"r{i + 1}" for i in range(self.robots)]


@dataclass
class SimRobot:
    """One simulated agent: its core, worker and source, and what it cost."""

    name: str
    node: FleetNode
    worker: FusionWorker
    source: CarmenSource
    host_cpu: float = 0.0
    worker_cpu: float = 0.0
    #: The part of ``worker_cpu`` the core itself spent (no stand-in's charge).
    core_cpu: float = 0.0
    busy_until: float = 0.0
    host_busy_until: float = 0.0
    inbox: deque[tuple[str, bytes]] = field(default_factory=deque)
    draining: bool = False
    next_step: float | None = None
    token: int = 0
    final_version: int | None = None
    state: GlobalState | None = None
    reports: list[Callable[[], None]] = field(default_factory=list)


class SimFleet:
    """A simulated fleet of :class:`Scenario`; :meth:`run` until agreement or ``limit``.

    Its workers draw registrations from ``outcomes`` and the search gate's verdicts from
    ``gates`` (:mod:`bench.fleetsim_gate`; default: a cache of this fleet's own).
    """

    def __init__(
        self,
        scenario: Scenario,
        outcomes: list[PairOutcome],
        rebuilds: Rebuilds,
        gates: GateCache | None = None,
    ):
        self.sc = scenario
        self.rebuilds = rebuilds
        self.meter = rebuilds.meter
        self.clock: SimClock = self.meter.clock
        self.loop = EventLoop()
        self.net = Network(self.loop, scenario.net, self._deliver, self._query)
        self.robots: dict[str, SimRobot] = {}
        self.merges = DrawnMerges(outcomes, {}, self.meter.charge)
        self.gates = gates or GateCache()
        self.shared = SharedMaps()
        self.agreed_at: float | None = None
        self.last_update: float | None = None
        segs, frames = (
            segments(scenario.robots),
            random_frames(scenario.robots, scenario.frames_seed),
        )
        with simulated_wire(self._now):
            for name, seg, frame in zip(scenario.names(), segs, frames, strict=True):
                self.robots[name] = self._robot(name, seg, frame)

    def _now(self) -> float:
        return self.loop.now

    def _instant(self) -> Instant:
        return Instant(self.loop.now, WALL0 + self.loop.now)

    def _robot(self, name: str, seg, frame) -> SimRobot:
        sc = self.sc
        spec = SourceSpec("carmen", sc.log, seg)
        source = CarmenSource(spec, frame, sc.resolution, sc.speed)
        truth = RobotTruth(source.describe()["world_to_pixel"])
        self.merges.truths[name] = truth
        self.merges.add_robot(name, source.grid())
        node = FleetNode(NodeOptions(name), self._instant())
        self.shared.share(node.inbound)
        robot: SimRobot
        worker = FusionWorker(
            name,
            node.book,
            self.merges.register(),
            lambda rec: robot.reports.append(
                lambda: self._call(robot, node.on_link, rec, self._instant())
            ),
            lambda st: robot.reports.append(lambda: self._on_global(robot, st)),
            sc.link_timeout,
            check=self.merges.check(),
            counters=node.counters,
            gate=self.gates.gate(self.meter),
        )
        robot = SimRobot(name, node, worker, source)
        return robot

    # ------------------------------------------------------------------ run

    def run(self) -> None:
        """Simulate until every agent agrees on the final maps, or ``limit`` s."""
        with simulated_core(self.rebuilds), simulated_wire(self._now):
            leaves = {c.robot: c for c in self.sc.churn}
            for name in self.robots:
                c = leaves.get(name)
                if c is None or c.leave > self.sc.startup:
                    self.loop.at(self.sc.startup, self._online, name, True)
                if c is not None:
                    self.loop.at(c.leave, self._online, name, False)
                    if c.back is not None:
                        self.loop.at(c.back, self._online, name, True)
            for p in self.sc.net.partitions:
                self.loop.at(p.start, self._liveliness)
                self.loop.at(p.end, self._liveliness)
            self.loop.at(self.sc.startup, self._turn)
            self.loop.run(self.sc.limit, stop=lambda: self.agreed_at is not None)

    def _online(self, name: str, up: bool) -> None:
        robot = self.robots[name]
        (self.net.online.add if up else self.net.online.discard)(name)
        self._liveliness()
        if up:
            self._wake(robot)

    def _liveliness(self) -> None:
        """Tell every online robot who it sees now (after one latency)."""
        now = self.loop.now
        for name, robot in self.robots.items():
            if name not in self.net.online:
                continue
            for other in self.robots:
                seen = other != name and self.net.reachable(name, other, now)
                if other != name and robot.node.alive.get(other, False) != seen:
                    when = now + self.sc.net.latency
                    self.loop.at(when, self._alive, robot, other, seen)

    def _alive(self, robot: SimRobot, other: str, up: bool) -> None:
        if robot.name in self.net.online and robot.node.alive.get(other, False) != up:
            self._call(robot, robot.node.on_alive, other, up, self._instant())

    def _turn(self) -> None:
        """One turn of every online daemon's loop: the source, then the core's tick."""
        for robot in self.robots.values():
            if robot.name not in self.net.online:
                continue
            src = robot.source
            t0 = time.thread_time()
            stepped = src.step(self.loop.now)
            grid = src.grid() if stepped else None
            robot.host_cpu += time.thread_time() - t0
            if grid is not None:
                extra = src.resume_state()
                self._call(robot, robot.node.on_source, grid, self._instant(), src.done, extra)
            self._call(robot, robot.node.tick, self._instant())
        self.loop.at(self.loop.now + LOOP_PERIOD, self._turn)

    # -------------------------------------------------------- the core's calls

    def _call(self, robot: SimRobot, method, *args) -> None:
        """Call the core, charge its CPU to the host, carry out what it returns."""
        with self.shared.charging() as decodes:
            t0 = time.thread_time()
            actions = method(*args)
            cpu = time.thread_time() - t0
        cpu = max(cpu + decodes[0], 0.0)
        robot.host_cpu += cpu
        start = max(self.loop.now, robot.host_busy_until)
        robot.host_busy_until = start + cpu * self._stretch(robot)
        self._carry_out(robot, actions)

    def _carry_out(self, robot: SimRobot, actions: list[act.Action]) -> None:
        for action in actions:
            match action:
                case act.Publish(key, payload, _):
                    self.net.put(robot.name, key, payload, list(self.robots))
                case act.Fetch(selector, parameters):
                    params = ";".join(f"{k}={v}" for k, v in (parameters or {}).items())
                    target = robot.node.keys.robot_of(selector) or ""
                    self.net.query(robot.name, target, f"{selector}?{params}")
                case act.PersistMap(name, stored, _) if name == robot.name:
                    if robot.source.done:
                        robot.final_version = stored.version
                    self._call(
                        robot, robot.node.on_persisted, name, stored.version, self._instant()
                    )
                case act.Register():
                    self._wake(robot)
                case act.Drop(reason, sender, detail):
                    robot.node.counters.drop(reason, sender, detail)
                case _:  # files: the simulation keeps no state directory
                    pass

    def _deliver(self, receiver: str, key: str, payload: bytes) -> None:
        """A message into ``receiver``'s inbox, which its main thread drains in order."""
        robot = self.robots[receiver]
        robot.inbox.append((key, payload))
        if not robot.draining:
            robot.draining = True
            self.loop.at(robot.host_busy_until, self._drain, robot)

    def _drain(self, robot: SimRobot) -> None:
        """The next message of the inbox, once the main thread is free."""
        if self.loop.now < robot.host_busy_until:
            self.loop.at(robot.host_busy_until, self._drain, robot)
            return
        key, payload = robot.inbox.popleft()
        self._call(robot, robot.node.on_message, key, payload, self._instant())
        robot.draining = bool(robot.inbox)
        if robot.draining:
            self.loop.at(robot.host_busy_until, self._drain, robot)

    def _query(self, target: str, asker: str, selector: str) -> None:
        robot = self.robots[target]
        key, _, text = selector.partition("?")
        params = dict(p.split("=", 1) for p in text.split(";") if p)
        t0 = time.thread_time()
        if key == robot.node.keys.latest(target):
            replies = robot.node.answer_latest(params.get("v"), params.get("tiles"))
        else:
            replies = robot.node.answer_links()
        robot.host_cpu += time.thread_time() - t0
        for reply in replies:
            if isinstance(reply, act.Reply):
                self.net.reply(target, asker, reply.key, reply.payload)

    # ------------------------------------------------------------- the worker

    def _schedule(self, robot: SimRobot, when: float) -> None:
        """Step ``robot``'s worker at ``when`` unless a step comes sooner already."""
        if robot.next_step is not None and robot.next_step <= when:
            return
        robot.next_step, robot.token = when, robot.token + 1
        self.loop.at(when, self._step, robot, robot.token)

    def _wake(self, robot: SimRobot) -> None:
        """``Register``: the worker looks for work as soon as its current job ends."""
        self._schedule(robot, max(self.loop.now, robot.busy_until))

    def _step(self, robot: SimRobot, token: int) -> None:
        """One job of ``robot``'s worker, charged (:mod:`bench.fleetsim_core`)."""
        if token != robot.token:
            return  # a sooner step took this one's place
        robot.next_step = None
        if robot.name not in self.net.online:
            return
        self.clock.now = start = self.loop.now
        self.meter.stretch = self._stretch(robot)
        charged, excluded = self.meter.charged, self.meter.excluded
        t0 = time.thread_time()
        more = robot.worker.step(start)
        overhead = max(time.thread_time() - t0 - (self.meter.excluded - excluded), 0.0)
        robot.busy_until = self.clock.now + overhead * self.meter.stretch
        robot.worker_cpu += self.meter.charged - charged + overhead
        robot.core_cpu += overhead
        reports, robot.reports = robot.reports, []
        for report in reports:
            self.loop.at(robot.busy_until, report)
        self._schedule(robot, robot.busy_until + (0.0 if more else self.sc.poll))

    def _stretch(self, robot: SimRobot) -> float:
        """Wall seconds per CPU second of ``robot``'s next job: 1 with a core each, else the
        workers and main threads busy now (this one too) shared over ``cores`` (processor
        sharing, as the load stood when the job began)."""
        if self.sc.cores is None:
            return 1.0
        now = self.loop.now
        others = (r for r in self.robots.values() if r is not robot)
        busy = 1 + sum((r.busy_until > now) + (r.host_busy_until > now) for r in others)
        return max(1.0, busy / self.sc.cores)

    def _on_global(self, robot: SimRobot, state: GlobalState) -> None:
        robot.state = state
        self._call(robot, robot.node.on_global, state, self._instant())
        self._check_agreement()

    # -------------------------------------------------------------- agreement

    def _view(self, robot: SimRobot) -> tuple | None:
        """The settled components ``robot`` shows, as :func:`agent.launcher.agreement` reads
        a status; None when not settled."""
        st = robot.state
        versions = robot.node.book.versions()
        if st is None or not st.settled or versions_of(st.components) != versions:
            return None
        return tuple(
            sorted(
                (c.anchor, c.members, c.digest, tuple(sorted(c.versions.items())))
                for c in st.components
            )
        )

    def _check_agreement(self) -> None:
        present = [r for n, r in self.robots.items() if n in self.net.online]
        if self.agreed_at is not None or not present:
            return
        if any(r.final_version is None for r in present):
            return
        final = {r.name: r.final_version for r in present}
        views = set()
        for r in present:
            held = r.node.book.versions()
            if any(held.get(n) != v for n, v in final.items()):
                return
            view = self._view(r)
            if view is None:
                return
            views.add(view)
        if len(views) == 1:
            self.agreed_at = self.loop.now
            self.last_update = max(r.node.last_update or WALL0 for r in present) - WALL0

    def own_component_bytes(self, robot: SimRobot) -> int:
        """Bytes of the grids ``robot`` holds: every robot's latest map and its global map."""
        held = sum(g.logodds.nbytes for _, g in robot.node.book.snapshot().maps.values())
        st = robot.state
        own = None if st is None else component_of(st.components, robot.name)
        return held + (0 if own is None else own.grid.logodds.nbytes)
