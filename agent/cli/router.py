"""``pgvd router``: a Zenoh router in this process, for fleets that span several sites.

This is Zenoh's own router (a session opened in mode ``"router"`` through the Python API; ``zenohd``
is not installable here): it routes publications, queries and liveliness between the clients and
peers attached to it and the other routers it is linked to. Agents need no code change to use it,
only a client or peer config that connects to it (``deploy/``).

    pgvd router [--listen EP ...] [--connect EP ...] [--config FILE]

One line on stdout when the router is up (``ready``), then one line per session that opens or
closes a transport with it (``open``/``close``, the remote's role and ZID). SIGINT and SIGTERM
close the session and exit 0.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import sys
import threading
from collections.abc import Sequence
from pathlib import Path
from types import FrameType

import zenoh

from agent.cli.common import EXIT_OK, CliError
from agent.zenoh_config import zenoh_error

#: Longest wait (s) for the Zenoh session to close on a stop signal.
CLOSE_TIMEOUT_S = 3.0


def router_config(
    config_file: Path | None, listen: Sequence[str], connect: Sequence[str]
) -> zenoh.Config:
    """The Zenoh config of a router: ``config_file`` (JSON5) if given, mode forced to router.

    ``listen`` and ``connect`` endpoints, when given, replace those of the file.

    Raises
    ------
    CliError
        When the file cannot be read or parsed, or an endpoint list is rejected.
    """
    try:
        config = zenoh.Config.from_file(str(config_file)) if config_file else zenoh.Config()
        config.insert_json5("mode", json.dumps("router"))
        if listen:
            config.insert_json5("listen/endpoints", json.dumps(list(listen)))
        if connect:
            config.insert_json5("connect/endpoints", json.dumps(list(connect)))
    except zenoh.ZError as exc:
        where = f"Zenoh config {config_file}" if config_file else "endpoints"
        raise CliError(f"bad {where}: {zenoh_error(exc)}") from exc
    return config


def run_router(config: zenoh.Config, stop: threading.Event) -> None:
    """Open a router session with ``config`` and serve until ``stop`` is set, then close it.

    Raises
    ------
    CliError
        When Zenoh refuses to open (an endpoint already in use, an unknown protocol, bad TLS files).
    """
    try:
        session = zenoh.open(config)
    except zenoh.ZError as exc:
        raise CliError(f"cannot start the router: {zenoh_error(exc)}") from exc
    endpoints = json.loads(config.get_json("listen/endpoints") or "[]")
    # "ready" first: declared before it, the listener's callback thread could print a
    # session's "open" line ahead of it (seen under load), breaking the one-line contract.
    print(f"ready {session.info.zid()} listening on {json.dumps(endpoints)}", flush=True)
    # history: a router linking to us while we were opening is reported too.
    listener = session.info.declare_transport_events_listener(_print_transport_event, history=True)
    # Polled, not one untimed wait: SIGTERM may be delivered to one of Zenoh's own
    # threads, and then nothing interrupts the main thread's untimed wait, so the
    # Python handler that sets ``stop`` never runs (the router hung on SIGTERM in 2
    # of 20 tries with the CPU loaded).  Each timeout returns to the interpreter,
    # which runs pending handlers.
    while not stop.wait(0.2):
        pass
    _close(session, listener)


def _close(session: zenoh.Session, listener: object) -> None:
    """Undeclare the listener (one still declared can hang the close) and close the session,
    waiting at most :data:`CLOSE_TIMEOUT_S`.

    With a ``--connect`` endpoint where nobody listens, the close sometimes never returned
    (CI, SIGINT: still running 14 minutes later, deaf to further signals).  The process
    then exits without it; the operating system closes its sockets.
    """

    def close() -> None:
        listener.undeclare()
        session.close()

    closer = threading.Thread(target=close, name="zenoh-close", daemon=True)
    closer.start()
    closer.join(CLOSE_TIMEOUT_S)
    if closer.is_alive():
        print(
            f"the Zenoh session did not close within {CLOSE_TIMEOUT_S:g} s; exiting without it",
            file=sys.stderr,
            flush=True,
        )
        print("closed", file=sys.stderr, flush=True)
        sys.stdout.flush()
        # not sys.exit: interpreter shutdown would wait on Zenoh's close again
        os._exit(EXIT_OK)


def _print_transport_event(event: zenoh.TransportEvent) -> None:
    kind = "open" if "put" in str(event.kind).lower() else "close"
    print(f"{kind} {event.transport.whatami} {event.transport.zid}", flush=True)


def _handle(args: argparse.Namespace) -> int:
    config = router_config(args.config, args.listen, args.connect)
    stop = threading.Event()

    def on_signal(signum: int, frame: FrameType | None) -> None:
        stop.set()

    previous = {sig: signal.signal(sig, on_signal) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        run_router(config, stop)
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    print("closed", file=sys.stderr, flush=True)
    return EXIT_OK


def configure(parser: argparse.ArgumentParser) -> None:
    """Add the arguments of ``pgvd router`` to its parser."""
    parser.description = __doc__.splitlines()[0]
    parser.add_argument(
        "--listen",
        action="append",
        default=[],
        metavar="EP",
        help="endpoint to listen on, e.g. tcp/0.0.0.0:7447 (repeatable; default: the config's)",
    )
    parser.add_argument(
        "--connect",
        action="append",
        default=[],
        metavar="EP",
        help="another router to link to, e.g. tcp/site-b.example:7447 (repeatable)",
    )
    parser.add_argument("--config", type=Path, metavar="FILE", help="Zenoh JSON5 config file")
    parser.set_defaults(func=_handle)
