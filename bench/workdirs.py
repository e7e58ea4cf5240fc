"""Where a fleet bench's agents keep their logs, state and status: a temporary directory
removed after the run, or one the user keeps to look into (``--keep DIR``)."""

from __future__ import annotations

import argparse
import contextlib
import tempfile
from collections.abc import Iterator
from pathlib import Path


def add_keep_argument(ap: argparse.ArgumentParser, layout: str) -> None:
    """``--keep DIR``: each run's agents in ``DIR/<layout>``, run verbose."""
    ap.add_argument(
        "--keep",
        type=Path,
        help=f"keep each run's agent logs (verbose), state and status files in DIR/{layout} "
        "(default: a temporary directory, removed after the run)",
    )


def check_keep(ap: argparse.ArgumentParser, keep: Path | None) -> None:
    """Refuse a ``--keep`` directory that holds anything (one line, exit 2): a fleet's
    agents would restore the state an earlier run left there."""
    if keep is not None and keep.exists() and any(keep.iterdir()):
        ap.error(f"--keep must be a new or empty directory: {keep}")


@contextlib.contextmanager
def fleet_dir(keep: Path | None, name: str) -> Iterator[Path]:
    """The directory of one fleet run: ``keep / name``, kept, or a temporary one removed
    when the run ends."""
    if keep is not None:
        yield keep / name
        return
    with tempfile.TemporaryDirectory(prefix=f"pgvd-{name}-") as tmp:
        yield Path(tmp)
