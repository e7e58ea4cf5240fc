"""A planar pose ``x,y,yaw`` as a user types it (metres, radians; REP 103).

Kept apart from :mod:`agent.priors` so that ``pgvd merge --prior`` parses its argument
without loading the agent's protocol stack.
"""

from __future__ import annotations

import math
import re

Pose = tuple[float, float, float]

#: A decimal number.  Its integer and fraction parts cannot split one run of digits two
#: ways, so a failing match is linear in the text, not quadratic.
NUMBER = r"[-+]?(?:\d+(?:\.\d*)?|\.\d+)(?:[eE][-+]?\d+)?"
#: ``x,y,yaw``, the groups named so.
POSE = rf"(?P<x>{NUMBER}),(?P<y>{NUMBER}),(?P<yaw>{NUMBER})"
_BARE_POSE = re.compile(POSE)


def parse_pose(text: str) -> Pose:
    """``x,y,yaw`` (metres, radians) -> a finite pose; ``ValueError`` (one line) otherwise."""
    m = _BARE_POSE.fullmatch(text.strip())
    if m is None:
        raise ValueError(f"a pose is x,y,yaw (metres, radians), e.g. 4.0,-1.5,0.3; got {text!r}")
    pose = (float(m["x"]), float(m["y"]), float(m["yaw"]))
    if not all(math.isfinite(v) for v in pose):
        raise ValueError(f"a pose must be finite, got {text!r}")
    return pose
