"""Where the bench's robots drive: the development logs, and simulated runs over map images.

A *run* is a time-ordered list of scans with their true poses.  Log runs are
the corrected intel and freiburg-079 logs; simulated runs are a
:mod:`pgvd.trajectory` tour through a development map image, scanned by
:mod:`pgvd.lidar`'s LMS200 model.  Both feed the same pair generator
(:mod:`bench.data.pairs`), so a simulated pair is made exactly as a log pair is.
The bench uses only development data (the project's shared data notes);
:func:`held_out_logs` and :func:`held_out_maps` find the logs and map images kept for
evaluation (``bench.merge --held-out``, ``bench.mapimages --held-out``).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from bench.environment import cache_suffix
from pgvd.carmen import LaserScan, read_carmen
from pgvd.grid import Grid
from pgvd.io import read_map
from pgvd.lidar import LMS200, RayCaster, scan_at
from pgvd.trajectory import tour

ROOT = Path(__file__).resolve().parents[2]
SHARED = ROOT.parent / "shared"
#: Bump when the simulator, the trajectory or a source changes, so caches are not reused.
SIM_VERSION = 2


@dataclass(frozen=True)
class Source:
    """One development source of runs.

    Attributes
    ----------
    name : row label of the report, e.g. ``"willow-sim"``.
    building : the place; negatives never pair two sources of one building.
    path : log (``.log.gz``) or map (``.yaml``) under the shared data directory.
    unknown_blocks : for a simulated run, treat the map's unknown cells as walls.
    """

    name: str
    building: str
    path: str
    unknown_blocks: bool = False

    @property
    def simulated(self) -> bool:
        return self.path.endswith(".yaml")


#: willow's image marks almost no wall (544 occupied cells, against 16,637 free cells that
#: border unknown ones): its walls are the edge of its free space, so unknown blocks beams.
SOURCES = (
    Source("intel-log", "intel", "logs/intel-corrected.log.gz"),
    Source("fr079-log", "fr079", "logs/freiburg-079-corrected.log.gz"),
    Source("intel-sim", "intel", "maps/intel/intel.yaml"),
    Source("fr079-sim", "fr079", "maps/fr079_albertB/map312.yaml"),
    Source("willow-sim", "willow", "maps/willow/willow-2010-02-18-0.10.yaml", True),
    Source("ritsumeikan-sim", "ritsumeikan_cc4f", "maps/ritsumeikan_cc4f/cc4.1.yaml"),
    Source("stata-sim", "mit_stata_basement", "maps/mit_stata_basement/stata_basement.yaml"),
    Source("avz-sim", "uos_avz", "maps/uos_avz/avz.yaml"),
)


#: The map directories the shared data notes give to development (tests and the bench);
#: every other one is kept to evaluate the merge on buildings it was never tuned on.
DEVELOPMENT_MAPS = frozenset(
    {
        "intel",
        "intel_split_gt",
        "fr079_albertB",
        "fr079_split_gt",
        "willow",
        "ritsumeikan_cc4f",
        "mit_stata_basement",
        "uos_avz",
    }
)


def held_out_maps(shared: Path = SHARED) -> tuple[Path, ...]:
    """Every map image (map_server YAML) of the shared data outside :data:`DEVELOPMENT_MAPS`.

    Found by leaving the development directories out, so the project's code names
    none of the held-out ones.
    """
    return tuple(
        sorted(
            p for p in (shared / "maps").glob("*/*.yaml") if p.parent.name not in DEVELOPMENT_MAPS
        )
    )


def held_out_logs(shared: Path = SHARED) -> tuple[Source, ...]:
    """Every laser log of the shared data that no development source reads.

    The shared data keeps these buildings to evaluate the merge on places its
    parameters were never tuned on.  They are found by leaving out what
    :data:`SOURCES` reads, so the project's code names none of them; each log is
    a building of its own, named after its file.
    """
    used = {s.path for s in SOURCES}
    return tuple(
        Source(f"{building}-log", building, f"logs/{path.name}")
        for path in sorted((shared / "logs").glob("*.log.gz"))
        if f"logs/{path.name}" not in used
        for building in [path.name.removesuffix(".log.gz").removesuffix("-corrected")]
    )


def caster_for(source: Source, shared: Path = SHARED) -> RayCaster:
    """The ray caster over a source's map image, in the image's own frame (origin 0, yaw 0)."""
    grid = read_map(shared / source.path)
    return RayCaster(Grid(grid.logodds, grid.resolution), unknown_blocks=source.unknown_blocks)


def simulate(source: Source, seed: int, shared: Path = SHARED) -> list[LaserScan]:
    """A simulated run through a source's map: tour poses, then one LMS200 scan per pose."""
    caster = caster_for(source, shared)
    rng = np.random.default_rng(seed)
    return scan_at(caster, tour(caster, rng), rng, LMS200)


def load_run(
    source: Source, seed: int, cache: Path | None, shared: Path = SHARED
) -> list[LaserScan]:
    """A source's run: the log as read, or a simulated run (stored in ``cache`` if given).

    A cached run is plain arrays (ranges, poses, field of view), not pickled scans, so
    it survives a move of the scan class; it is kept per set of library versions
    (:func:`bench.environment.cache_suffix`), as the pairs are.
    """
    if not source.simulated:
        return read_carmen(shared / source.path)
    name = f"run-{source.name}-{seed}-v{SIM_VERSION}{cache_suffix()}.npz"
    key = None if cache is None else cache / name
    if key is not None and key.exists():
        with np.load(key) as z:
            fov = float(z["fov"])
            return [
                LaserScan(float(i), r, pose, pose.copy(), fov)
                for i, (r, pose) in enumerate(zip(z["ranges"], z["poses"], strict=True))
            ]
    scans = simulate(source, seed, shared)
    if key is not None:
        key.parent.mkdir(parents=True, exist_ok=True)
        ranges = np.array([sc.ranges for sc in scans])
        poses = np.array([sc.pose for sc in scans])
        with key.open("wb") as f:
            np.savez(f, ranges=ranges, poses=poses, fov=scans[0].fov)
    return scans
