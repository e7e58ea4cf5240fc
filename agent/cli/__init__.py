"""The ``pgvd`` command line, one module per sub-command.

- :mod:`agent.cli.dispatch` -- the parser, :func:`main`, and the exit on a closed pipe;
- :mod:`agent.cli.common` -- exit codes, :class:`~agent.cli.common.CliError`, the fleet key;
- :mod:`agent.cli.agent`, :mod:`agent.cli.status`, :mod:`agent.cli.demo`,
  :mod:`agent.cli.router`, :mod:`agent.cli.merge` -- ``pgvd agent``, ``status``, ``demo``,
  ``router`` and ``merge``.

Only the module of the sub-command being run is imported, so ``pgvd merge`` never loads Zenoh
and ``pgvd --help`` loads no command at all.
"""

from agent.cli.dispatch import main

__all__ = ["main"]
