"""The ``pgvd`` command line: one sub-command per module, dispatched from here.

Exit codes (design.md): 0 success, 2 bad input (one line on stderr), 3 no overlap.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable, Sequence
from pathlib import Path

EXIT_OK = 0
EXIT_BAD_INPUT = 2
EXIT_NO_OVERLAP = 3


class CliError(Exception):
    """A user error: printed as one line on stderr, exit code 2."""


def read_fleet_key(path: Path | None) -> bytes | None:
    """The fleet key in ``path`` (surrounding whitespace stripped), or None without a path."""
    if path is None:
        return None
    try:
        key = path.read_bytes().strip()
    except OSError as exc:
        raise CliError(f"cannot read key file: {exc.strerror}: {path}") from None
    if not key:
        raise CliError(f"key file is empty: {path}")
    return key


class _Parser(argparse.ArgumentParser):
    """argparse exits with code 2 on bad arguments already; keep the message to one line."""

    def error(self, message: str) -> None:  # type: ignore[override]
        self.exit(EXIT_BAD_INPUT, f"pgvd: error: {message}\n")


def _subcommands() -> list[Callable[[argparse._SubParsersAction], None]]:
    """Each sub-command module exposes ``register(subparsers)`` setting ``func``."""
    registrars: list[Callable[[argparse._SubParsersAction], None]] = []
    from agent import cmd_agent, cmd_demo, cmd_status

    registrars += [cmd_agent.register, cmd_status.register, cmd_demo.register]
    from agent import cmd_router

    registrars.append(cmd_router.register)
    from agent import cmd_merge

    registrars.append(cmd_merge.register)
    return registrars


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="pgvd", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True, parser_class=_Parser)
    for register in _subcommands():
        register(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return int(args.func(args))
    except CliError as exc:
        print(f"pgvd {args.command}: error: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    # Run as ``python -m agent.cli``: dispatch through the importable module, so that the
    # CliError the sub-commands raise (agent.cli.CliError) is the one caught here.
    from agent.cli import main as _main

    sys.exit(_main())
