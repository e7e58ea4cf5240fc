"""Peers' decoded maps shared by the simulated agents: one copy per (robot, version).

Every simulated :class:`agent.node.FleetNode` decodes each version it receives, as a real
agent does, and is charged its real CPU for it; but all of them decode the same tiles to the
same map.  Held once per agent, a fleet of N robots keeps N copies of every robot's latest
map, of its int8 cells (the reassembler keeps them for the next delta) and of its tiles: at
128 robots that is the bulk of the simulating process's memory (``bench/results/notes/
fleetsim.md``).  :class:`SharedMaps` wraps a node's :class:`agent.wire.Inbound` so that a
completed version is replaced by the fleet's one copy of it before the node sees it.

Fleet invariant 2 makes this exact: a (robot, version) is one published map, so every
receiver decodes it to the same cells; the copies are shared read-only (their arrays made
unwriteable), so a core that wrote into a map it holds would raise, not corrupt the others'.
Copies are held weakly: a version no agent holds any longer is freed.
"""

from __future__ import annotations

import weakref

import numpy as np

from agent.wire import Inbound, Received
from pgvd.grid import Grid


class SharedMaps:
    """The fleet's one copy of each decoded (robot, version) map and of its int8 cells."""

    def __init__(self) -> None:
        self._grids: weakref.WeakValueDictionary[tuple[str, int], Grid] = (
            weakref.WeakValueDictionary()
        )
        self._cells: weakref.WeakValueDictionary[tuple[str, int], np.ndarray] = (
            weakref.WeakValueDictionary()
        )

    def __len__(self) -> int:
        return len(self._grids)

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

    def share(self, inbound: Inbound) -> None:
        """Make ``inbound`` hand out the fleet's copies of the versions it completes."""
        feed = inbound.feed

        def shared(msg):
            done = feed(msg)
            if done is None:
                return None
            reasm = inbound._reassemblers[msg.robot]
            if reasm.version == done.version and reasm.quantised is not None:
                reasm.quantised = self.cells(msg.robot, done.version, reasm.quantised)
            return done._replace(grid=self.grid(msg.robot, done))

        inbound.feed = shared
