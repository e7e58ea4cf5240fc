"""What a bench result was measured with: the code's commit, Python, and the numerical libraries.

Two runs of the merge bench on the same commit can differ when the machine
under it differs: the pairs drawn from map images are rendered by a simulated
lidar and cut with numpy, scipy, scikit-image, OpenCV and Pillow, and their
cells move with those libraries.  Measured on one commit: on one machine, with
the libraries of a fresh install (numpy 2.4.6, scipy 1.17.1, scikit-image
0.26.0, OpenCV 4.14.0, Pillow 13.0.0), 42 of the 292 pgvd margins differed from
a run made on another machine, two stata standard pairs changed outcome (one
each way) and every total stayed the same; two runs on one machine and install,
each from an empty pair cache, agree to the last bit.  The library versions and
the CPU changed together there, so either may move the pairs.

So a result is recorded with what it was measured on, and runs are compared
only where the Python and library versions match.  The bench's pair cache is
kept per set of them (:func:`cache_suffix`): pairs made under other versions
are made again, not mixed into a run that records these.
"""

from __future__ import annotations

import hashlib
import importlib
import json
import os
import platform
import subprocess
from pathlib import Path

#: The libraries whose versions move a bench result: name -> module.  The version is
#: the imported module's own, whichever distribution installed it (OpenCV comes as
#: opencv-python, -headless or -contrib).
LIBRARIES = {
    "numpy": "numpy",
    "scipy": "scipy",
    "scikit-image": "skimage",
    "opencv": "cv2",
    "pillow": "PIL",
}

ROOT = Path(__file__).resolve().parents[1]

#: Written by the benches themselves: a change there does not make the code dirty.
RESULTS = "bench/results"


def _version(module: str) -> str | None:
    try:
        return str(importlib.import_module(module).__version__)
    except ImportError:
        return None


def _git(*args: str) -> str:
    return subprocess.run(
        ["git", *args], cwd=ROOT, capture_output=True, text=True, check=True
    ).stdout.strip()


def commit() -> str | None:
    """This checkout's commit, with ``+dirty`` when tracked code is changed.

    Returns
    -------
    str or None
        The commit (12 hex digits), ``+dirty`` when a tracked file outside
        ``bench/results`` differs from it; None without git, or when this file is
        not tracked by the repository git finds (a source export unpacked inside
        another repository).
    """
    try:
        _git("ls-files", "--error-unmatch", str(Path(__file__).relative_to(ROOT)))
        head = _git("rev-parse", "--short=12", "HEAD")
        dirty = _git("status", "--porcelain", "--untracked-files=no", "--", ".", f":!{RESULTS}")
    except (OSError, subprocess.CalledProcessError):
        return None
    return f"{head}+dirty" if dirty else head


def digest(values: dict) -> str:
    """A short stable name for a dict of JSON values, for cache keys."""
    return hashlib.sha1(json.dumps(values, sort_keys=True).encode()).hexdigest()[:8]


def libraries() -> dict[str, str | None]:
    """The version of each of :data:`LIBRARIES` (None when it cannot be imported)."""
    return {name: _version(module) for name, module in LIBRARIES.items()}


def cache_suffix() -> str:
    """``-e`` and the :func:`digest` of Python's and :func:`libraries` versions: the end of
    every cached file's stem that the simulated pairs come from."""
    return "-e" + digest({"python": platform.python_version(), **libraries()})


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
        "libraries": libraries(),
    }


def describe(env: dict) -> str:
    """One line of :func:`environment` for a report's notes."""
    libs = ", ".join(f"{k} {v}" for k, v in env["libraries"].items() if v is not None)
    return (
        f"Measured on commit {env['commit'] or 'unknown'}, Python {env['python']}, "
        f"{env['machine']}, {env['cpus']} CPUs; {libs}. Sim pairs' cells move with these "
        "libraries (bench.environment): compare runs only where Python and the library "
        "versions match."
    )
