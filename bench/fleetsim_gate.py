"""The agent's search gate in the simulator: the real verdict on each map version replayed.

Every simulated :class:`agent.worker.FusionWorker` is built with ``gate=``, as ``pgvd
agent`` builds it, so the worker's own code decides when to ask (once per (robot, version)
of a map A it would search, :meth:`FusionWorker._gated`), counts ``searches_gated``,
records the rejection ``not searched: ...`` and holds the later waves of searches
(:data:`agent.worker.GATE_HOLD_S`).  Only the answer is drawn from a cache:

- **How it is drawn.** The verdict on a grid is that of the real
  :func:`agent.worker.merge_gate` (:func:`pgvd.merge.a_side_rejection` with the
  registration's parameters) on that very grid: the map version the simulation replays,
  not a nearest cached pair.  Verdicts are keyed by the grid's content (SHA-256 of its
  log-odds, shape, origin and resolution), so the 128 agents of a fleet that ask about one
  version run it once.  They are kept beside the outcome cache of :mod:`bench.fleetsim_merges`
  (``fleetsim-gates-v{GATE_CACHE_VERSION}{suffix}.pkl``), and a rerun of the same scenario,
  whose replayed versions are the same maps, finds them all there.
- **How it is charged.** Each agent that asks is charged the CPU seconds
  (``time.thread_time``) the real call took when it was first made, the same on every later
  ask and run, as the real agent pays its own gate per version; the real call's CPU in the
  simulating process is left out of the agent's own (:meth:`bench.fleetsim_core.Meter.excluding`).
"""

from __future__ import annotations

import hashlib
import os
import pickle
import time
from pathlib import Path

from agent.worker import GateFn, merge_gate
from bench.environment import cache_suffix
from bench.fleetsim_core import Meter
from pgvd.grid import Grid

#: Bump when what is stored of a verdict changes: the gate cache is then made again.
GATE_CACHE_VERSION = 1

#: A verdict: the gate's rejection reason (None: a search may pass) and its CPU seconds.
Verdict = tuple[str | None, float]


def grid_digest(grid: Grid) -> bytes:
    """What tells one map version from another: a digest of its content and canvas."""
    h = hashlib.sha256(grid.logodds.tobytes())
    h.update(repr((grid.shape, tuple(map(float, grid.origin)), grid.resolution)).encode())
    return h.digest()


class GateCache:
    """The real gate's verdicts by map content, and the :data:`GateFn` s that draw them
    (module docstring).

    Parameters
    ----------
    path : the pickle the verdicts are read from and saved to; None keeps them in memory.
    gate : the real gate (default :func:`agent.worker.merge_gate`).
    """

    def __init__(self, path: Path | None = None, gate: GateFn | None = None) -> None:
        self.path = path
        self._gate = gate or merge_gate()
        self.verdicts: dict[bytes, Verdict] = {}
        if path is not None and path.exists():
            self.verdicts = pickle.loads(path.read_bytes())
        self._saved = len(self.verdicts)
        #: Real gate calls made in this process (cache misses).
        self.computed = 0

    @classmethod
    def beside(cls, cache: Path) -> GateCache:
        """The gate cache in the bench's cache directory ``cache``."""
        return cls(cache / f"fleetsim-gates-v{GATE_CACHE_VERSION}{cache_suffix()}.pkl")

    def verdict(self, grid: Grid) -> Verdict:
        """The real gate's verdict on ``grid`` and its CPU seconds, run on a miss."""
        key = grid_digest(grid)
        held = self.verdicts.get(key)
        if held is None:
            t0 = time.thread_time()
            why = self._gate(grid)
            held = self.verdicts[key] = (why, time.thread_time() - t0)
            self.computed += 1
        return held

    def gate(self, meter: Meter) -> GateFn:
        """A worker's :data:`GateFn`: the cached verdict, its CPU charged on ``meter`` (as
        ``"gate"``), the simulation's own work left out of the agent's."""

        def drawn(a: Grid) -> str | None:
            with meter.excluding():
                why, cpu = self.verdict(a)
            meter.charge(cpu, "gate")
            return why

        return drawn

    def save(self) -> None:
        """Write the verdicts if any were added (no-op in memory)."""
        if self.path is None or len(self.verdicts) == self._saved:
            return
        self.path.parent.mkdir(parents=True, exist_ok=True)
        tmp = self.path.with_suffix(f".{os.getpid()}.tmp")  # runs may share a cache
        tmp.write_bytes(pickle.dumps(self.verdicts))
        tmp.replace(self.path)
        self._saved = len(self.verdicts)
