"""What the simulated agents share: each payload decoded once, each peer's map held once.

Every simulated :class:`agent.node.FleetNode` receives the same payloads as the others and
decodes them to the same maps; done and held once per agent, the simulating process does N
times the work and holds N copies of every robot's latest map, of its int8 cells (the
reassembler keeps them for the next delta) and of its tiles.  At 128 robots that was 11 GB
and most of the run's CPU.  :class:`SharedMaps` wraps each node's :class:`agent.wire.Inbound`:

- **Decoding.** A payload is decoded (and authenticated) by the real
  :meth:`agent.wire.Inbound.decode` the first time any agent receives it; every agent that
  receives it is charged the CPU seconds (``time.thread_time``) that real decode took, as the
  search gate's verdicts are (:mod:`bench.fleetsim_gate`), and :attr:`SharedMaps.owed` tells
  the host what to charge in place of the wrapper's own time (:meth:`SharedMaps.charging`).
  Decoding is a pure function of the payload and the fleet key, which all agents share.
  A payload that fails to decode is decoded by each agent, uncached.
- **Maps.** A completed version is replaced by the fleet's one copy of it, its int8 cells
  and its tiles, before the node sees it.  Fleet invariant 2 makes this exact: a (robot,
  version) is one published map, so every receiver decodes it to the same cells.

What is shared is read-only (its arrays made unwriteable), so a core that wrote into a map or
message it holds would raise, not change the other agents'.  Maps and cells are held weakly,
freed when no agent holds them; decoded payloads are kept for the last :data:`DECODED`.
"""

from __future__ import annotations

import contextlib
import hashlib
import time
import weakref
from collections import OrderedDict
from collections.abc import Callable, Iterator

import numpy as np

from agent.wire import Inbound, Message, Received
from pgvd.grid import Grid
from protocol.messages import Manifest, MapTiles

#: Decoded payloads kept: all N receivers of a payload decode it within a few simulated
#: seconds, long before this many newer payloads went out.
DECODED = 4096


def _frozen(msg: Message) -> Message:
    """``msg`` with its tiles' cells made read-only (it is shared by every receiver)."""
    if isinstance(msg, MapTiles):
        for tile in msg.tiles:
            tile.cells.flags.writeable = False
    return msg


class SharedMaps:
    """The fleet's decoded payloads, and one copy of each (robot, version) map, its int8
    cells and its tiles (module docstring)."""

    def __init__(self) -> None:
        self._decoded: OrderedDict[bytes, tuple[Message, float]] = OrderedDict()
        #: CPU seconds the agents owe for decodes (each at the real decode's cost) ...
        self.owed = 0.0
        #: ... and the real CPU seconds the wrappers spent meanwhile.
        self.spent = 0.0
        #: Real decodes made (cache misses).
        self.decodes = 0
        self._grids: weakref.WeakValueDictionary[tuple[str, int], Grid] = (
            weakref.WeakValueDictionary()
        )
        self._cells: weakref.WeakValueDictionary[tuple[str, int], np.ndarray] = (
            weakref.WeakValueDictionary()
        )
        self._tiles: weakref.WeakValueDictionary[tuple[str, int, int], np.ndarray] = (
            weakref.WeakValueDictionary()
        )

    def grid(self, robot: str, received: Received) -> Grid:
        """The fleet's copy of ``robot``'s map ``received`` (``received.grid`` if first)."""
        key = (robot, received.version)
        held = self._grids.get(key)
        if held is None:
            received.grid.logodds.flags.writeable = False
            held = self._grids[key] = received.grid
        elif held.shape != received.grid.shape:
            raise ValueError(f"{robot} v{received.version} decoded to two shapes")
        return held

    def cells(self, robot: str, version: int, cells: np.ndarray) -> np.ndarray:
        """The fleet's copy of the int8 cells of ``robot``'s map ``version``."""
        held = self._cells.get((robot, version))
        if held is None:
            held = self._cells[(robot, version)] = cells
        return held

    def decode(self, decode: Callable[[bytes], Message], payload: bytes) -> Message:
        """``decode(payload)``, run once per payload; its real CPU is owed each time."""
        t0 = time.thread_time()
        key = hashlib.blake2b(payload, digest_size=16).digest()
        held = self._decoded.get(key)
        if held is None:
            t1 = time.thread_time()
            msg = decode(payload)  # a ProtocolError propagates, uncached
            held = self._decoded[key] = (_frozen(msg), time.thread_time() - t1)
            self.decodes += 1
            while len(self._decoded) > DECODED:
                self._decoded.popitem(last=False)
        self.owed += held[1]
        self.spent += time.thread_time() - t0
        return held[0]

    @contextlib.contextmanager
    def charging(self) -> Iterator[list[float]]:
        """Yields ``[seconds]``: after the block, the CPU to add to the block's own real CPU
        (decodes owed, less the wrappers' real time) for the agent it ran for."""
        owed, spent = self.owed, self.spent
        delta = [0.0]
        try:
            yield delta
        finally:
            delta[0] = (self.owed - owed) - (self.spent - spent)

    def _share_tiles(self, robot: str, reasm) -> None:
        """The reassembler's held tiles replaced by the fleet's copies (same robot, index and
        CRC-32: the same content)."""
        assembler = reasm._assembler
        if assembler is None:
            return
        for index, content in assembler._held.items():
            key = (robot, index, assembler._crc[index])
            held = self._tiles.get(key)
            if held is None:
                self._tiles[key] = content
            elif held.shape == content.shape:
                assembler._held[index] = held

    def share(self, inbound: Inbound) -> None:
        """Make ``inbound`` decode through the fleet's payloads and hand out the fleet's
        copies of the versions it completes."""
        feed, decode = inbound.feed, inbound.decode

        def shared_feed(msg: MapTiles | Manifest) -> Received | None:
            done = feed(msg)
            if done is None:
                return None
            reasm = inbound._reassemblers[msg.robot]
            if reasm.version == done.version and reasm.quantised is not None:
                reasm.quantised = self.cells(msg.robot, done.version, reasm.quantised)
            self._share_tiles(msg.robot, reasm)
            return done._replace(grid=self.grid(msg.robot, done))

        inbound.feed = shared_feed
        inbound.decode = lambda payload: self.decode(decode, payload)
