"""An output directory that ``pgvd demo`` may empty: only of the files it wrote there itself.

A run claims its ``--out`` directory with :func:`claim` and, once it has written everything,
lists every file it left there, with size and modification time, in a marker file
(:func:`record`). A later run deletes exactly those files, unchanged, and nothing else: a
directory holding any other file (``--out .``, ``--out ~``, or a report the user edited) is
refused with one line, so that no user file is ever lost.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

from agent.cli.common import CliError

MARKER = ".pgvd-demo.json"

_Stat = tuple[int, int]  # (size in bytes, modification time in ns) of a file or symlink


def claim(out: Path) -> None:
    """Make ``out`` an empty directory of this run, deleting only what an earlier run wrote.

    Parameters
    ----------
    out : Path
        The output directory; created if missing.

    Raises
    ------
    CliError
        When ``out`` is not a directory, cannot be read or written, or holds a file that no
        earlier run recorded (or that changed since); nothing is deleted then.
    """
    if out.exists() and not out.is_dir():
        raise CliError(f"--out {out} is not a directory")
    try:
        out.mkdir(parents=True, exist_ok=True)
        found, written = _files(out), _written(out)
        foreign = sorted(rel for rel, stat in found.items() if written.get(rel) != stat)
        if foreign:
            more = f" and {len(foreign) - 1} other files" if len(foreign) > 1 else ""
            raise CliError(
                f"--out {out} holds {foreign[0]}{more} that pgvd demo did not write there; "
                "give a new or empty directory"
            )
        for rel in found:
            (out / rel).unlink()
        _remove_empty_dirs(out, found)
        _write_marker(out, {})
    except OSError as exc:
        raise CliError(f"--out {out}: {exc.strerror or exc}") from None


def record(out: Path) -> None:
    """Mark every file now under ``out`` as written by this run (for :func:`claim` later)."""
    _write_marker(out, _files(out))


def _files(out: Path) -> dict[str, _Stat]:
    """Every file and symlink under ``out`` but the marker, by path relative to ``out``.

    Symlinks are listed, never followed, so that deleting them leaves their targets alone.
    """
    found: dict[str, _Stat] = {}
    pending = [out]
    while pending:
        with os.scandir(pending.pop()) as entries:
            for entry in entries:
                if entry.is_dir(follow_symlinks=False):
                    pending.append(Path(entry.path))
                    continue
                rel = Path(entry.path).relative_to(out).as_posix()
                if rel != MARKER:
                    st = entry.stat(follow_symlinks=False)
                    found[rel] = (st.st_size, st.st_mtime_ns)
    return found


def _written(out: Path) -> dict[str, _Stat]:
    """The files an earlier run recorded in ``out``; none without a readable marker."""
    try:
        files = json.loads((out / MARKER).read_text())["files"]
        return {str(rel): (int(size), int(mtime)) for rel, (size, mtime) in files.items()}
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        return {}


def _write_marker(out: Path, files: dict[str, _Stat]) -> None:
    doc = {"written_by": "pgvd demo", "files": {rel: list(st) for rel, st in files.items()}}
    (out / MARKER).write_text(json.dumps(doc, indent=0, sort_keys=True))


def _remove_empty_dirs(out: Path, removed: dict[str, _Stat]) -> None:
    """Remove the directories that held ``removed`` files once empty, deepest first."""
    dirs = {d for rel in removed for d in (out / rel).parents if out in d.parents}
    for d in sorted(dirs, key=lambda p: len(p.parts), reverse=True):
        if not any(d.iterdir()):
            d.rmdir()
