"""The Zenoh configuration of an agent: peer mode on explicit endpoints, overridable by a file.

Why these defaults (checked with eclipse-zenoh 1.10 on one machine): multicast scouting
finds nobody on loopback, so peers listen on ``tcp/127.0.0.1:PORT`` and connect to seeds, and gossip
links the rest; ``scouting/delay`` 0 keeps ``open()`` from waiting 500 ms.
"""

from __future__ import annotations

import json
import re
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path

import zenoh

MODES = ("peer", "client", "router")

# Zenoh's errors end with the Rust source location, wrap a JSON5 value error in its Debug
# form, and show a JSON5 syntax error as a multi-line caret drawing; a user needs one line.
_RUST_LOCATION = re.compile(r"\s+at \S+\.rs:\d+\.?")
_DEBUG_MESSAGE = re.compile(r'msg: "((?:[^"\\]|\\.)+)"')
# the "= expected ..." line of the caret drawing, not an "=" in the quoted source line
_SYNTAX = re.compile(r"-->\s*(\d+):(\d+).*?^\s*=\s*(.+)", re.S | re.M)


def zenoh_error(exc: BaseException) -> str:
    """Zenoh's error text on one line: the message, or where and what for a syntax error."""
    text = _RUST_LOCATION.sub("", str(exc))
    if message := _DEBUG_MESSAGE.search(text):
        return message.group(1).replace('\\"', '"')
    if syntax := _SYNTAX.search(text):
        line, column, what = syntax.groups()
        return f"line {line}, column {column}: {' '.join(what.split())}"
    return " ".join(text.split()) or type(exc).__name__


@dataclass(frozen=True)
class ZenohOptions:
    """What the command line may set; ``config_file`` is applied first, the rest on top.

    Attributes
    ----------
    mode : "peer" (default), "client" or "router".
    listen : endpoints to listen on, e.g. ``tcp/127.0.0.1:7447``.
    connect : seed endpoints to connect to.
    multicast : enable multicast scouting (LANs; useless on loopback).
    shared_memory : None keeps Zenoh's default (on); False disables it (loss/bandwidth tests).
    lease_ms : transport lease: how fast a frozen peer is declared gone.
    config_file : a Zenoh JSON5 config file that the options above extend.
    """

    mode: str = "peer"
    listen: Sequence[str] = ()
    connect: Sequence[str] = ()
    multicast: bool = False
    shared_memory: bool | None = None
    lease_ms: int | None = None
    config_file: Path | None = None
    extra: dict[str, object] = field(default_factory=dict)


def build_config(opts: ZenohOptions) -> zenoh.Config:
    """A :class:`zenoh.Config` for ``opts``.

    A config file is loaded as-is; the built-in defaults (peer mode, no multicast,
    gossip on, scouting delay 0) are then applied only where the file is silent, and
    explicit options (listen, connect, mode...) always win.

    Raises
    ------
    ValueError
        For an unknown mode or a config file Zenoh rejects (one line).
    """
    if opts.mode not in MODES:
        raise ValueError(f"mode must be one of {', '.join(MODES)}, got {opts.mode!r}")
    file_keys: set[str] = set()
    if opts.config_file is not None:
        try:
            cfg = zenoh.Config.from_file(str(opts.config_file))
        except zenoh.ZError as exc:
            raise ValueError(f"bad Zenoh config {opts.config_file}: {zenoh_error(exc)}") from None
        file_keys = _set_keys(cfg)
    else:
        cfg = zenoh.Config()
    defaults: dict[str, object] = {
        "mode": opts.mode,
        "scouting/delay": 0,
        "scouting/multicast/enabled": opts.multicast,
        "scouting/gossip/enabled": True,
    }
    for key, value in defaults.items():
        if key not in file_keys:
            _insert(cfg, key, value)
    explicit: dict[str, object] = dict(opts.extra)
    if opts.mode != "peer" or opts.config_file is None:
        explicit["mode"] = opts.mode
    if opts.multicast:
        explicit["scouting/multicast/enabled"] = True
    if opts.listen:
        explicit["listen/endpoints"] = list(opts.listen)
    if opts.connect:
        explicit["connect/endpoints"] = list(opts.connect)
        # Seeds may start after us: keep retrying quickly instead of giving up.
        explicit["connect/timeout_ms"] = -1
        explicit["connect/exit_on_failure"] = False
    if opts.shared_memory is not None:
        explicit["transport/shared_memory/enabled"] = opts.shared_memory
    if opts.lease_ms is not None:
        explicit["transport/link/tx/lease"] = int(opts.lease_ms)
    for key, value in explicit.items():
        _insert(cfg, key, value)
    return cfg


#: Zenoh batches of the tile session: a tile message of ``wire.DATAGRAM_BYTES`` plus Zenoh's
#: framing in one batch, and a batch plus UDP/IP headers in one 1500-byte Ethernet frame.
TILE_BATCH_BYTES = 1400
#: A UDP link's handshake under 20 % loss takes up to 23 s with Zenoh's defaults, 0-4 s with
#: these (measured here): a lost open packet is retried after ~1 s instead of waiting 10 s.
_TILE_LINK_SETTINGS: dict[str, object] = {
    "transport/link/tx/batch_size": TILE_BATCH_BYTES,
    "transport/unicast/open_timeout": 1000,
    "transport/unicast/accept_timeout": 1000,
    "connect/retry": {"period_init_ms": 250, "period_max_ms": 1000, "period_increase_factor": 2},
}


def tile_session_options(
    main: ZenohOptions, listen: Sequence[str], connect: Sequence[str]
) -> ZenohOptions:
    """The second session that carries best-effort tiles, e.g. on ``udp/`` endpoints.

    A session of its own rather than a second link of the main session: with a TCP and a UDP
    link in one Zenoh session (``max_links`` 2), about 1 run in 6 at 20 % loss ended with
    peers out of step for good (liveliness and routes that disagree); a session of its own
    can lose only tiles, which the manifest and the ``latest`` queryable of the main session
    recover. It keeps the main session's mode, lease and shared-memory choice, not its file
    (a TLS or ACL file speaks of the main session's links), nor multicast scouting, which would
    find the main sessions' TCP locators and pull the tiles back onto them.
    """
    return replace(
        main,
        listen=tuple(listen),
        connect=tuple(connect),
        multicast=False,
        config_file=None,
        extra={**main.extra, **_TILE_LINK_SETTINGS},
    )


def _insert(cfg: zenoh.Config, key: str, value: object) -> None:
    """``insert_json5`` takes JSON text, not Python values, hence ``json.dumps``."""
    try:
        cfg.insert_json5(key, json.dumps(value))
    except zenoh.ZError as exc:
        raise ValueError(f"bad Zenoh setting {key}={value!r}: {zenoh_error(exc)}") from None


def _set_keys(cfg: zenoh.Config) -> set[str]:
    """The few keys this module sets whose value a config file already fixed."""
    keys = set()
    for key in ("mode", "scouting/delay", "scouting/multicast/enabled", "scouting/gossip/enabled"):
        try:
            value = cfg.get_json(key)
        except Exception:
            continue
        if value not in ("null", None):
            keys.add(key)
    return keys
