"""Grey-zone candidates confirmed by a consistent cycle of candidates.

A grey-zone candidate (:mod:`agent.trust`) enters the global map when a newer epoch accepts
it, when the accepted links close a consistent cycle through it, or (a search's provisional
accept) when both maps are final.  In a building whose right poses all score at the bar, a
fleet's last maps can leave every pair there: each pair's searches land at the same right
pose epoch after epoch at margins of 0.23-0.57, a few just above the bar and most just
below, and once the maps are final no newer epoch comes to lift them.

What no lone decision says, a cycle does: three robots' candidates, each found by its own
search on its own maps, compose to the identity only where all three are right, or where
their errors cancel (two mirror poses of a symmetric building and a right one).  So a
candidate of margin at least :data:`CYCLE_FLOOR` is confirmed when the other pairs'
candidates of at least that margin, with the links in the map, place its two robots where
its own pose does, within the trust hold (:func:`agent.trust.holds`): the pose graph of
those links (:func:`pgvd.posegraph.solve`, robust: of an inconsistent cycle its weakest
link leaves) predicts the pair, and the prediction must run through other pairs, so it
closes a cycle.

Only links of the robots' current epochs count (a link of an older epoch maps the pixels
of older maps).  The agent that decided the candidate confirms it
(:meth:`agent.worker.FusionWorker._cycled`), so the decision travels in the link record
and every agent's global map follows the record (fleet invariant 2).

On 17 development fleet runs (seed 7, N=3-6, every development building), 53 wrong
grey-zone poses scored 0.00-0.56 (10 of them at 0.2 or more: 7-74 m off at the maps'
corners, half and quarter turns among them, and one near miss), and none lay on a 3-cycle
of the pairs' latest decisions that composed to the identity within the hold, of 339 such
cycles; the right ones of ritsumeikan closed cycles at 0.23-0.57.  A near miss (a pose 3-5
cells off at the corners, inside the hold at the centre) composes with right links as a
right pose does: a cycle cannot tell it from the truth.  The one seen (0.55, 3.5 cells,
0.8 deg) was refined by its pair's next search 2.4 s later, before any cycle through it
had closed.
"""

from __future__ import annotations

import numpy as np

from agent.links import LinkRecord
from agent.trust import CANDIDATE

#: The lowest margin at which a candidate counts as a link of a cycle (its own, or one that
#: confirms another).  On the development fleet runs 43 of the 53 wrong grey-zone poses
#: scored below it, against 15 of the 63 right ones; the cycle, not the floor, is what
#: keeps the rest out.  A right pose of ritsumeikan's that closed its robot's only cycle
#: scored 0.23.
CYCLE_FLOOR = 0.2


def on_cycle_candidate(ln: LinkRecord, versions: dict[str, int]) -> bool:
    """Whether ``ln`` is a candidate that counts as a cycle's link: of the robots' current
    epochs (``versions``, the latest map versions) and of margin at least
    :data:`CYCLE_FLOOR`."""
    margin = ln.margin
    return (
        ln.state == CANDIDATE
        and margin is not None
        and bool(np.isfinite(margin))
        and margin >= CYCLE_FLOOR
        and ln.current(versions)
    )
