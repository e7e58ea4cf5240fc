"""A global map's component built by hand from maps and placements, for the output tests."""

from __future__ import annotations

import numpy as np

from agent.globalmap import Component
from pgvd.grid import Grid


def component(
    maps: dict[str, tuple[int, Grid]], transforms: dict[str, np.ndarray], digest: str = "d"
) -> Component:
    """The component of ``maps`` (robot -> (version, grid)) placed by ``transforms``, anchored
    at its lowest id, with no links and zero covariances."""
    members = tuple(sorted(maps))
    return Component(
        anchor=members[0],
        members=members,
        versions={r: v for r, (v, _) in maps.items()},
        transforms=transforms,
        covariances={r: np.zeros((3, 3)) for r in members},
        used=(),
        rejected=(),
        grid=maps[members[0]][1],
        digest=digest,
    )
