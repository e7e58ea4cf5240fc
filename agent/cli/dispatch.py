"""Map-fusion fleets of robots, peer to peer over Zenoh, and the PGVD map merge.

Exit codes: 0 success, 1 not achieved (see each command), 2 bad input (one line on stderr),
3 no overlap.
"""

from __future__ import annotations

import argparse
import importlib
import os
import re
import sys
import textwrap
from collections.abc import Collection, Sequence

from agent.cli.common import EXIT_BAD_INPUT, EXIT_FAILED, CliError

#: Sub-command -> (the module whose ``configure(parser)`` adds its arguments and sets ``func``,
#: its line in ``pgvd --help``). The help lines live here so that the list of commands costs no
#: import; a command's module, and what it imports, is loaded only when that command runs.
COMMANDS: dict[str, tuple[str, str]] = {
    "agent": ("agent.cli.agent", "run one robot's map-fusion daemon (peer to peer over Zenoh)"),
    "status": ("agent.cli.status", "robots, versions, links and traffic of a running fleet"),
    "demo": ("agent.cli.demo", "N agents on localhost map a building together (--log, --map)"),
    "router": (
        "agent.cli.router",
        "run a Zenoh router (links sites; agents connect to it as clients or peers)",
    ),
    "merge": (
        "agent.cli.merge",
        "merge occupancy-grid maps (map_server .yaml, bare .pgm/.png, .npy)",
    ),
}


#: reStructuredText markup of the module docstrings that serve as descriptions: ``x`` and
#: :role:`x` read as x in a terminal.
_RST = re.compile(r":[a-z]+:`([^`]+)`|``([^`]+)``")


def plain(text: str | None, width: int = 88) -> str | None:
    """A docstring with its reStructuredText roles and literals as plain text (for ``--help``),
    its lines wrapped at ``width`` (the help keeps line breaks, so a one-line description would
    otherwise run off the terminal)."""
    if text is None:
        return None
    text = _RST.sub(lambda m: m.group(1) or m.group(2), text)
    return "\n".join(
        textwrap.fill(line, width, subsequent_indent=" " * (len(line) - len(line.lstrip(" -"))))
        if len(line) > width
        else line
        for line in text.splitlines()
    )


class _Formatter(argparse.RawDescriptionHelpFormatter):
    """Descriptions keep their line breaks (their lists stay lists); an option's default is
    shown when it has one worth showing and its help does not give it already."""

    def _get_help_string(self, action: argparse.Action) -> str | None:
        text = action.help or ""
        default = action.default
        # by identity: 0 and 0.0 equal False but are defaults worth showing
        unset = default is None or default is False or default == [] or default == argparse.SUPPRESS
        if action.option_strings and not unset and "default" not in text:
            return f"{text} (default: %(default)s)"
        return action.help


class _Parser(argparse.ArgumentParser):
    """argparse exits with code 2 on bad arguments already; keep the message to one line."""

    def error(self, message: str) -> None:  # type: ignore[override]
        self.exit(EXIT_BAD_INPUT, f"pgvd: error: {message}\n")


class _Version(argparse.Action):
    """``pgvd --version``: the installed distribution's version, looked up only when asked."""

    def __init__(self, option_strings: Sequence[str], dest: str, **kwargs: object) -> None:
        super().__init__(option_strings, dest, nargs=0, **kwargs)  # type: ignore[arg-type]

    def __call__(self, parser: argparse.ArgumentParser, *_: object) -> None:
        from importlib.metadata import PackageNotFoundError, version

        try:
            found = version("pgvd-fleet")
        except PackageNotFoundError:  # run from a source tree that was never installed
            found = "unknown (not installed)"
        print(f"pgvd {found}")  # on stdout, as argparse's own version action does
        parser.exit(0)


def build_parser(commands: Collection[str] = COMMANDS.keys()) -> argparse.ArgumentParser:
    """The ``pgvd`` parser, with the arguments of ``commands`` (every command by default).

    Parameters
    ----------
    commands : collection of str
        The sub-commands whose modules are imported to add their arguments; the others are
        listed with their help line only.

    Returns
    -------
    argparse.ArgumentParser
        A parser whose ``parse_args`` sets ``command`` and ``func(args) -> exit code``.
    """
    parser = _Parser(prog="pgvd", description=__doc__.splitlines()[0])
    parser.add_argument("--version", action=_Version, help="print the version and exit")
    sub = parser.add_subparsers(dest="command", required=True, parser_class=_Parser)
    for name, (module, help_line) in COMMANDS.items():
        command = sub.add_parser(
            name, help=help_line, description=help_line, formatter_class=_Formatter
        )
        if name in commands:
            importlib.import_module(module).configure(command)
            command.description = plain(command.description)
    return parser


def _run(argv: Sequence[str]) -> int:
    args = build_parser(set(argv[:1]) & COMMANDS.keys()).parse_args(argv)
    try:
        return int(args.func(args))
    except CliError as exc:
        print(f"pgvd {args.command}: error: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except KeyboardInterrupt:
        return 130


def main(argv: Sequence[str] | None = None) -> int:
    """Run ``pgvd`` with ``argv`` (default: the process's arguments); the exit code.

    A reader that closes standard output early (``pgvd merge A B --json | head -c 1``) ends
    the command quietly with exit code 1 instead of a ``BrokenPipeError`` traceback, as the
    Python documentation recommends (signal module, "Note on SIGPIPE"). SIGPIPE itself keeps
    Python's disposition (ignored): with the default one, a peer closing a Zenoh socket would
    kill the agent.
    """
    argv = sys.argv[1:] if argv is None else list(argv)
    try:
        try:
            return _run(argv)
        finally:
            # Flush here, not at interpreter exit, so a closed pipe raises where it is caught;
            # also when argparse exits after printing --help.
            sys.stdout.flush()
    except BrokenPipeError:
        # Python flushes stdout again at exit: point it at /dev/null so that flush succeeds.
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        return EXIT_FAILED
