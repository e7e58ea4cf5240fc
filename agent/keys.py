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

Robot ids and fleet names are single key chunks: no ``/``, no wildcard characters.
"""

from __future__ import annotations

import re

PREFIX = "pgvd"
#: Same rule as ``protocol.messages.check_id``: ids travel inside key expressions.
_CHUNK = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_-]{0,63}$")


def check_name(value: str, what: str) -> str:
    """Return ``value`` if it can be one key chunk, else raise ``ValueError`` (one line)."""
    if not _CHUNK.match(value):
        raise ValueError(
            f"{what} must be 1-64 of [A-Za-z0-9_-], starting alphanumeric, got {value!r}"
        )
    return value


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

    def robot_of(self, key: str, kind: str) -> str | None:
        """The robot chunk of ``<root>/<kind>/<robot>...``, or None if ``key`` is not one."""
        head = f"{self.root}/{kind}/"
        if not key.startswith(head):
            return None
        robot = key[len(head) :].split("/", 1)[0]
        return robot if _CHUNK.match(robot) else None
