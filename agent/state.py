"""The agent's state directory: own and peers' latest maps and the links, written atomically.

Layout of ``--state-dir``::

    maps/<robot>.npz   latest map of a robot: log-odds, resolution, origin, version, extra JSON,
                       and the robot's first epoch when known
    links.json         the cached links (:mod:`agent.links`)
    status.json        the last status snapshot (for people and for ``pgvd demo``)

Every file is written to a temporary name in the same directory, then renamed over the old
one, so ``kill -9`` leaves either the old or the new file, never half of one.  Only the
robot's own map is also fsynced (file and directory), so that a power cut cannot lose a
version peers may hold: a peer's map, the links and the status can be had again -- a
restarted agent fetches every robot's latest map and links, and writes its status anew.
Fsyncing those too cost the main thread ~20 ms per fsync on a shared 2-core VM; at 16
robots, persisting every peer version received made it fall seconds behind its inbox.
"""

from __future__ import annotations

import io
import json
import zipfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import BinaryIO

import numpy as np

from agent.failpoints import failpoint
from agent.keys import check_name
from agent.links import LinkRecord, dumps, loads
from pgvd.atomic import atomic_write
from pgvd.grid import Grid, check_cell_size
from pgvd.npy_map import NPY_HEADER_ERRORS


@dataclass(frozen=True)
class StoredMap:
    """One robot's latest map as persisted; ``extra`` holds source progress for own maps.

    ``first_epoch`` is the epoch of the robot's first version (the merged frame's anchor is
    chosen by it): kept with the own map, a restarted robot keeps its age; None where it is
    unknown, as in files written before it was kept.
    """

    version: int
    grid: Grid
    extra: dict[str, object] = field(default_factory=dict)
    first_epoch: int | None = None


def atomic_write_bytes(
    path: Path, data: bytes, point: str | None = None, durable: bool = False
) -> None:
    """Write ``data`` to ``path`` with :func:`pgvd.atomic.atomic_write`: old or new file, whole;
    fsynced if ``durable``.

    ``point`` names the failpoint (:mod:`agent.failpoints`) reached with half of the bytes
    written and flushed, so a test can kill the process while a real half-written copy
    (``.<name>.<random>.tmp``) sits on disk.
    """

    def write(fh: BinaryIO) -> None:
        half = len(data) // 2
        fh.write(data[:half])
        fh.flush()
        if point is not None:
            failpoint(point)
        fh.write(data[half:])

    atomic_write(path, write, durable)


class StateDir:
    """Load and save an agent's persisted state under one directory."""

    def __init__(self, root: Path) -> None:
        self.root = Path(root)
        self.maps_dir = self.root / "maps"
        self.maps_dir.mkdir(parents=True, exist_ok=True)
        self.removed_temporaries = remove_temporaries(
            self.root / ".links.json.*", self.root / ".status.json.*", self.maps_dir / ".*.npz.*"
        )

    def save_map(
        self, robot: str, stored: StoredMap, point: str | None = None, durable: bool = False
    ) -> None:
        """Persist ``robot``'s map atomically, fsynced if ``durable`` (the own map); ``point``
        arms a failpoint mid-write (tests)."""
        buf = io.BytesIO()
        g = stored.grid
        first = {} if stored.first_epoch is None else {"first_epoch": np.int64(stored.first_epoch)}
        np.savez(
            buf,
            logodds=np.ascontiguousarray(g.logodds, dtype=np.float32),
            resolution=np.float64(g.resolution),
            origin=np.asarray(g.origin, dtype=np.float64),
            version=np.int64(stored.version),
            extra=np.frombuffer(json.dumps(stored.extra).encode(), dtype=np.uint8),
            **first,
        )
        path = self.maps_dir / f"{check_name(robot, 'robot id')}.npz"
        atomic_write_bytes(path, buf.getvalue(), point, durable)

    def load_maps(self) -> tuple[dict[str, StoredMap], list[str]]:
        """All persisted maps, and one line per file that could not be read (skipped)."""
        maps: dict[str, StoredMap] = {}
        errors: list[str] = []
        for path in sorted(self.maps_dir.glob("*.npz")):
            try:
                maps[check_name(path.stem, "robot id")] = _read_map(path)
            except (*NPY_HEADER_ERRORS, KeyError, zipfile.BadZipFile) as exc:
                errors.append(f"{path.name}: {exc}")
        return maps, errors

    def forget_map(self, robot: str) -> None:
        """Delete ``robot``'s persisted map, if any."""
        (self.maps_dir / f"{check_name(robot, 'robot id')}.npz").unlink(missing_ok=True)

    def save_links(self, records: list[LinkRecord]) -> None:
        atomic_write_bytes(self.root / "links.json", dumps(records).encode())

    def load_links(self) -> tuple[list[LinkRecord], list[str]]:
        path = self.root / "links.json"
        if not path.exists():
            return [], []
        try:
            return loads(path.read_text()), []
        except (OSError, ValueError) as exc:
            return [], [f"links.json: {exc}"]

    def save_status(self, payload: bytes) -> None:
        """Write the status JSON ``payload`` (the bytes a status query is answered with)."""
        atomic_write_bytes(self.root / "status.json", payload)


def remove_temporaries(*patterns: Path) -> list[str]:
    """Delete the ``.<name>.*`` copies a killed writer left behind; their names, sorted.

    Loading never reads them (``load_maps`` globs ``*.npz``), but an agent killed in a loop
    would otherwise leave one per crash until the disk fills. Call only before this process
    writes: another agent never shares a state directory.
    """
    removed = []
    for pattern in patterns:
        for tmp in pattern.parent.glob(pattern.name):
            if tmp.is_file():
                tmp.unlink(missing_ok=True)
                removed.append(tmp.name)
    return sorted(removed)


def _member(archive: np.lib.npyio.NpzFile, name: str, kinds: str) -> np.ndarray:
    """The array ``name`` of ``archive``; ``ValueError`` unless its dtype kind is in ``kinds``
    (a structured, complex or string array cannot be cast to a map's numbers)."""
    arr = np.asarray(archive[name])
    if arr.dtype.kind not in kinds:
        raise ValueError(f"corrupt map arrays: {name} is {arr.dtype}")
    return arr


def _read_map(path: Path) -> StoredMap:
    """One persisted map; ``ValueError`` for any array of the wrong shape or value (a file
    written by something else, or damaged on disk), so that loading skips it."""
    # the file opened here, not by np.load: np.load leaves it open when it is no zip
    with path.open("rb") as f, np.load(f, allow_pickle=False) as z:
        with np.errstate(over="ignore"):  # a value past float32 fails the finite check below
            logodds = _member(z, "logodds", "biuf").astype(np.float32)
        origin = _member(z, "origin", "iuf").astype(np.float64)
        resolution, version = _member(z, "resolution", "iuf"), _member(z, "version", "iu")
        if (
            logodds.ndim != 2
            or origin.shape != (3,)
            or resolution.shape != ()
            or version.shape != ()
            or not (np.isfinite(logodds).all() and np.isfinite(origin).all())
        ):
            raise ValueError("corrupt map arrays")
        extra = json.loads(bytes(_member(z, "extra", "u")).decode() or "{}")
        if not isinstance(extra, dict):
            raise ValueError("corrupt resume state: not a JSON object")
        check_cell_size(float(resolution))
        grid = Grid(logodds, float(resolution), tuple(origin.tolist()))  # type: ignore[arg-type]
        return StoredMap(int(version), grid, extra, _first_epoch(z))


def _first_epoch(archive: np.lib.npyio.NpzFile) -> int | None:
    """The persisted first epoch, None if the file has none; ``ValueError`` if it is no
    non-negative integer scalar."""
    if "first_epoch" not in archive.files:
        return None
    first = _member(archive, "first_epoch", "iu")
    if first.shape != () or int(first) < 0:
        raise ValueError("corrupt map arrays: first_epoch")
    return int(first)
