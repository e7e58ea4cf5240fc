"""What a bench result was measured with: the code's commit, Python, and the numerical libraries.

Two runs of the merge bench on the same commit can differ when the libraries
under it differ: the pairs drawn from map images are rendered by a simulated
lidar and cut with numpy, scipy, scikit-image, OpenCV and Pillow, and their
cells move with those versions.  Measured on one commit (c597ba2): with the
libraries of a fresh install on 2026-12-02 (numpy 2.4.6, scipy 1.17.1,
scikit-image 0.26.0, opencv-python-headless 4.14.0.94, Pillow 13.0.0), 42 of
the 292 pgvd margins differed from the committed run's, two stata standard
pairs changed outcome (one each way) and every total stayed the same; two runs
in the same environment, each from an empty pair cache, agree to the last bit.
So a result is recorded with what it was measured on, runs are compared only
where this record matches, and the bench's pair cache is kept per set of
library versions (:func:`libraries_key`): pairs made under other versions are
made again, not mixed into a run that records these.
"""

from __future__ import annotations

import hashlib
import json
import os
import platform
import subprocess
from importlib import metadata
from pathlib import Path

#: The distributions whose versions move a bench result.
LIBRARIES = ("numpy", "scipy", "scikit-image", "opencv-python-headless", "pillow")

ROOT = Path(__file__).resolve().parents[1]


def _version(name: str) -> str | None:
    try:
        return metadata.version(name)
    except metadata.PackageNotFoundError:
        return None


def commit() -> str | None:
    """The checkout's commit, with ``+dirty`` when tracked files are changed; None outside git."""
    try:
        head = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"],
            cwd=ROOT,
            capture_output=True,
            text=True,
            check=True,
        ).stdout.strip()
        dirty = subprocess.run(
            ["git", "status", "--porcelain", "--untracked-files=no"],
            cwd=ROOT,
            capture_output=True,
            text=True,
            check=True,
        ).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return None
    return f"{head}+dirty" if dirty else head


def environment() -> dict:
    """The commit, Python, machine, CPU count and :data:`LIBRARIES` versions of this run.

    Returns
    -------
    dict
        ``commit``, ``python``, ``machine``, ``cpus`` and ``libraries`` (name ->
        version, None when not installed).
    """
    return {
        "commit": commit(),
        "python": platform.python_version(),
        "machine": f"{platform.system()} {platform.machine()}",
        "cpus": os.cpu_count(),
        "libraries": {name: _version(name) for name in LIBRARIES},
    }


def libraries_key() -> str:
    """A short stable name for this Python and :data:`LIBRARIES` versions, for cache keys."""
    versions = {"python": platform.python_version(), **{n: _version(n) for n in LIBRARIES}}
    return hashlib.sha1(json.dumps(versions, sort_keys=True).encode()).hexdigest()[:8]


def describe(env: dict) -> str:
    """One line of :func:`environment` for a report's notes."""
    libs = ", ".join(f"{k} {v}" for k, v in env["libraries"].items() if v is not None)
    return (
        f"Measured on commit {env['commit'] or 'unknown'}, Python {env['python']}, "
        f"{env['machine']}, {env['cpus']} CPUs; {libs}. Sim pairs' cells move with these "
        "libraries' versions (bench.environment): compare runs only where this line matches."
    )
