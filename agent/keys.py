"""Key expressions of a fleet: everything lives under ``pgvd/<fleet>/``.

=====================================  ==========================================
``pgvd/<fleet>/tiles/<robot>``         map tiles (pub/sub), deltas of one version
``pgvd/<fleet>/manifest/<robot>``      the manifest closing a version; re-announced
``pgvd/<fleet>/link/<a>/<b>``          a decided pairwise link, ``a < b``
``pgvd/<fleet>/alive/<robot>``         liveliness token: membership
``pgvd/<fleet>/latest/<robot>/...``    queryable: the latest full map (late joiners)
``pgvd/<fleet>/links/<robot>/...``     queryable: the links an agent holds
``pgvd/<fleet>/status/<robot>``        queryable: JSON status of one agent
=====================================  ==========================================

Robot ids and fleet names are single key chunks: no ``/``, no wildcard characters. The rule is
the wire format's (:func:`protocol.messages.check_id`), since every message names them too.
"""

from __future__ import annotations

from protocol.errors import ProtocolError
from protocol.messages import check_id

PREFIX = "pgvd"


def check_name(value: str, what: str) -> str:
    """Return ``value`` if it can be one key chunk, else raise ``ValueError`` (one line).

    The error is a :class:`~protocol.errors.ProtocolError`, itself a ``ValueError``.
    """
    return check_id(value, what)


def is_name(value: str) -> bool:
    """Whether ``value`` can be one key chunk (:func:`check_name` would return it)."""
    try:
        check_id(value, "name")
    except ProtocolError:
        return False
    return True


class FleetKeys:
    """Key expressions of one fleet; ``robot`` arguments are checked chunks."""

    def __init__(self, fleet: str) -> None:
        self.fleet = check_name(fleet, "fleet name")
        self.root = f"{PREFIX}/{fleet}"

    def tiles(self, robot: str = "*") -> str:
        return f"{self.root}/tiles/{robot}"

    def manifest(self, robot: str = "*") -> str:
        return f"{self.root}/manifest/{robot}"

    def link(self, a: str = "*", b: str = "*") -> str:
        return f"{self.root}/link/{a}/{b}"

    def alive(self, robot: str = "*") -> str:
        return f"{self.root}/alive/{robot}"

    def latest(self, robot: str = "*") -> str:
        """Queryable selector; replies carry ``latest/<robot>/<version>/<part>``."""
        return f"{self.root}/latest/{robot}/**"

    def latest_reply(self, robot: str, version: int, part: str) -> str:
        # One concrete key per reply: default consolidation would merge equal keys.
        return f"{self.root}/latest/{robot}/{version}/{part}"

    def links(self, robot: str = "*") -> str:
        return f"{self.root}/links/{robot}/**"

    def links_reply(self, robot: str, index: int) -> str:
        return f"{self.root}/links/{robot}/{index}"

    def status(self, robot: str = "*") -> str:
        return f"{self.root}/status/{robot}"

    def robot_of(self, key: str, kind: str | None = None) -> str | None:
        """The robot chunk of ``<root>/<kind>/<robot>...``, or None if ``key`` is not one.

        With no ``kind``, of any kind: the publisher of tiles and manifests, the answering agent
        of ``latest`` and ``links`` replies, robot ``a`` of a link.
        """
        parts = key.split("/", 4)
        if len(parts) < 4 or "/".join(parts[:2]) != self.root or not is_name(parts[3]):
            return None
        return parts[3] if kind is None or parts[2] == kind else None
