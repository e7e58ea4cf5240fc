"""Atomic file writes: after a crash or a power cut, the old file or the new one, whole."""

from __future__ import annotations

import os
import secrets
from collections.abc import Callable
from pathlib import Path
from typing import BinaryIO


def atomic_write(
    path: str | os.PathLike[str], write: Callable[[BinaryIO], object], durable: bool = True
) -> None:
    """Write a file so that a crash or power cut leaves either the old or the new one whole.

    ``write`` fills a temporary file ``.<name>.<random>.tmp`` in the same
    directory; the file is fsynced, renamed over ``path``, and the directory
    fsynced so that the rename itself is on disk.  On any error the temporary
    file is removed and the old file, if any, is untouched.

    Parameters
    ----------
    path : str or os.PathLike
        The file to create or replace; missing parent directories are created.
    write : callable
        Called once with the temporary file, opened for binary writing.
    durable : bool, optional
        False skips both fsyncs: a crash of the process (``kill -9``) still leaves the old
        or the new file whole (the kernel holds what was written), a power cut may not.
        For files whose content can be had again; each fsync can cost tens of milliseconds.

    Raises
    ------
    OSError
        If the directory or the file cannot be written; whatever ``write`` raises.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.parent / f".{path.name}.{secrets.token_hex(6)}.tmp"
    # mode 0666 minus the umask, like any open(): tempfile.mkstemp would leave the file
    # readable by its owner only
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
    try:
        with os.fdopen(fd, "wb") as f:
            write(f)
            f.flush()
            if durable:
                os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    if not durable:
        return
    dir_fd = os.open(path.parent, os.O_RDONLY)
    try:
        os.fsync(dir_fd)
    finally:
        os.close(dir_fd)
