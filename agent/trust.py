"""A link's lifecycle: accepted, candidate, confirmed, rejected, withdrawn.

The merge decides one pair at one moment; a fleet sees more.  Its maps grow version by
version, a right pose stays put and gains agreeing walls while a mirror or look-alike pose is
contradicted as more of the building appears, and links close cycles.  So a pair is not
simply accepted or rejected on its first decision:

- **accepted**: a first search's margin (:mod:`pgvd.decision`) clears the *high bar*
  :data:`HIGH_BAR`, or a check confirms the pose the accepted links or known poses predict
  (the prediction is the evidence a lone search lacks).
- **provisional** (a candidate): a first search clears the merge's own bar
  ``margin >= min_margin`` but not :data:`HIGH_BAR`.  On the development bench no negative or
  wrong winner reaches ``min_margin`` (``python3 -m bench greyzone``), yet a fleet tries
  many more bad pairs than that bench holds (every pair, at every epoch, on maps still
  small), and near misses accepted just above it were shown wrong for seconds.  It is
  confirmed as a grey-zone candidate is (below).
- **candidate**: the best pose sits in the *grey zone*, ``GREY_FLOOR <= margin < min_margin``:
  right poses and mirror or look-alike ones both land there, and no threshold on one decision
  separates them.  A candidate does not enter the global map.  It is checked again at its own
  pose (:func:`pgvd.verify.verify`, ~0.05 s) at each new version of either map, which drops
  it when contradicted.
- **confirmed**: a candidate that earned its place, and enters the global map.  A re-check
  on a newer *version* of the same epochs (:func:`recheck_verdict`) may keep or reject a
  candidate, but never confirms it: a version adds a few scans, and on maps still small the
  search and the check (:func:`pgvd.verify.verify`, a local basin) both converge on a near
  miss (0.7 deg, some 5 cells off at the maps' corners, inside the hold) that the next
  *epoch* (a map changed by a set share of its cells, :mod:`agent.links`) refined to the
  truth; confirmed on the next version, such near misses were shown wrong for up to 12 s.
  Nor does a pose held in the grey zone, however its margin grows: a look-alike 18 m off
  held its pose over two newer epochs' searches, its margin grown from 0.01 to 0.40, before
  a third contradicted it.  So a candidate is confirmed when

  1. it is a search's accept (a provisional one, its re-checks kept above the bar,
     :func:`standing_accept`) and the first decision of a newer epoch of either map (a
     search, or a check at the pose the accepted links predict) accepts it again at its
     pose, within the hold (:data:`HOLD_M`, :data:`HOLD_DEG`): the pose that enters is that
     newer decision's, refined on more map.  A grey-zone candidate that a newer epoch
     accepts is a provisional accept, which the epoch after must accept again: in the fleet
     bench a look-alike 27 m off, searched at margins 0.16, 0.30, 0.38 over three epochs,
     was accepted at 0.68 on the fourth, and shown wrong for 7 s.

     A search that finds it again confirms it only when its own covariance pins the map
     within the hold: the largest spread of the map's canvas corners under that pose
     (:func:`corner_spread`, eq. (4)) at most :data:`HOLD_M`; else it is a provisional
     accept again, for the epoch after.  On maps still small a search's best pose can be a
     near miss that the next epoch's search finds again as itself: in the fleet bench two
     robots were shown 3.8-3.9 cells off (0.3-0.5 deg) for 5.4 s, placed by a link searched
     at 0.62 and found again at 0.70 one epoch later; replayed, those searches accepted r4
     on r1 at 0.64 and 0.76, 4.1 and 5.6 cells off, and the next epochs', on more map,
     found the truth (0.4 and 0.3 cells off), loose by 0.14 and 0.08 m.  Over 17 fleet
     runs of the development buildings, of 46 such confirmations the 2 near misses moved
     1.3 and 0.0 cells from the pose they confirmed and right ones up to 2.6, so no hold on
     the move tells them apart, nor does the two poses' consistency under their
     covariances (both near misses well within it); their own spread does: 0.28-0.29 m,
     while 35 of the 44 right ones were within the hold (the other 9 wait an epoch).

     A pose already in the map that a newer epoch's search finds again stays confirmed,
     however loose: taking it out would hide right poses for an epoch (5 of 58 such
     re-finds in those runs were right and loose).  This leaves the same kind of near miss
     a way in: 2 of those re-finds were 3.5 and 8.7 cells off, loose by 0.43 and 1.6 m; or
  2. it lies on a consistent cycle: the accepted links of the current epochs already place
     its robots where its pose does, within the hold (at any version: a cycle's evidence is
     other pairs' decisions, not more of the same two maps); so does a candidate of margin
     0.2 or more that the other pairs' *candidates* and the links in the map place there, a
     cycle of grey-zone decisions (:mod:`agent.greycycle`, for buildings whose right poses
     all score at the bar).  Either way its own covariance must pin map B within the hold,
     as a search's re-find must (:func:`cycle_verdict`): a near miss closes a cycle as a
     right pose does; or
  3. it is a search's provisional accept on maps that will not change
     (:func:`settled_verdict`): both robots' *final* maps, their sources' last versions,
     which their manifests mark (:class:`protocol.messages.Manifest`), at once; or maps
     that stayed unchanged for :data:`QUIET_S`, for sources that never say they are done
     (a parked robot, a live SLAM that stopped).  It is the same evidence as a one-shot
     ``pgvd merge`` of the same two maps: no newer version can come to re-check it on, and
     holding the link back for ever would do worse than that merge.  Waiting on final
     maps bought nothing but the wait: 10 s of the fleet bench's 13-17 s to agree after
     the last update at 8 robots.

     Being a lone pair's decision on the merge's own bar, it is the weakest evidence, and
     never overrides other evidence: if links in the map already place its two robots
     together (accepted links of current epochs, the pose graph's robust solution), it is
     confirmed only where they predict it, within the hold, as a cycle is; elsewhere it
     stays a candidate, its reason saying how far off it is (on a held-out run, a fleet of
     6 ended with a robot wrong, placed by a link the quiet rule confirmed).  While links
     of older epochs join the two robots (their prediction maps the pixels of older maps,
     metres off), it waits for their current decisions.  The final mark is not persisted:
     an agent restarted holds its maps as not final, and waits :data:`QUIET_S` on them.

  A search on a newer epoch that accepts another pose is a first try of its own.  An
  accepted or confirmed link whose pair a new epoch re-decides in the grey zone at the same
  pose stays confirmed.

  A check carrying a search's provisional accept onto the maps of a newer epoch
  (:func:`carried_verdict`) starts from that accept's own pose, so it is no evidence for
  it: on maps barely grown it converged on a near miss (0.4 deg, 3.3 cells) again and
  confirmed it.  Only an accept at or above :data:`HIGH_BAR` is carried; a provisional one
  waits for the newer epoch's own decision (a search, or a check from the chain's
  prediction).

  A look-alike that searches accept on two epochs (27 m off, at 0.63 and 0.62) is
  confirmed all the same.  Once right links close a cycle around it, the cycle is
  inconsistent, and a lone cycle cannot say which link is wrong: the pose graph's GNC drops
  the one its covariances leave with the largest residual, and kept the look-alike over a
  right link of margin 0.82.  So links are graded by their margin (:func:`link_strength`)
  and an inconsistent cycle's weakest link is the one left out
  (:func:`pgvd.posegraph.solve`'s ``strength``), on every agent alike: the margin travels
  in the link record.
- **rejected**: no pose, a margin below the grey zone, or a candidate that a re-check
  contradicted (margin below :data:`GREY_FLOOR`, or the pose moved beyond the hold or out
  of the check's basin).
- **withdrawn**: an accepted or confirmed link whose next epoch contradicts it (no pose, or a
  margin below the grey zone): the global map is rebuilt without it.  A new epoch's pose in
  the grey zone elsewhere is a candidate again.

The state travels in the link record (:class:`agent.links.LinkRecord`) and on the wire, so the
global map stays a function of the maps and the link records (fleet invariant 2): whoever
decided a state, every agent reads the same one.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pgvd.grid import Grid, heading
from pgvd.params import DecisionParams
from pgvd.uncertainty import check_covariance, transform_covariance

ACCEPTED = "accepted"
CANDIDATE = "candidate"
CONFIRMED = "confirmed"
REJECTED = "rejected"
WITHDRAWN = "withdrawn"
#: Every state a link record may have.
STATES = (ACCEPTED, CANDIDATE, CONFIRMED, REJECTED, WITHDRAWN)
#: The states whose links enter the global map.
IN_MAP = frozenset({ACCEPTED, CONFIRMED})

#: The margin at or above which a first search's accept enters the global map at once.
#: Derived from the development bench's bad winners (``python3 -m bench greyzone``: 53 wrong
#: poses and 110 negatives, the largest margin 0.53): an exponential tail fitted to their
#: margins above the grey floor gives 0.89 for a rate of 1 in 1,000 bad winners (0.57, the
#: merge's bar, is 1 in 150).  No bad winner reaches it: 0 of 163, below 1.8 % at 95 %
#: confidence by count alone, the tail's 0.1 % resting on the fit.
HIGH_BAR = 0.89
#: Seconds a provisional accept's two maps must stay unchanged before the agent that decided
#: it confirms it on the merge's own bar (:func:`settled_verdict`), unless both are marked
#: final.  Finished maps that do not say so (a robot parked, a SLAM that stopped) bring no
#: newer version to re-check on, and holding their link back for ever would do worse than a
#: one-shot ``pgvd merge``.  Twice the 5 s map interval of gmapping and slam_toolbox: a
#: robot still mapping re-checks first.
QUIET_S = 10.0
#: Lowest margin of the grey zone, the merge's own (:class:`pgvd.params.DecisionParams`):
#: below it, on the development bench, almost no right pose is worth keeping
#: (``python3 -m bench greyzone`` prints the counts).
GREY_FLOOR = DecisionParams.GREY_MARGIN
#: A re-checked pose holds when it moved at most this far (3 cells of 5 cm) ...
HOLD_M = 0.15
#: ... and turned at most this much.
HOLD_DEG = 2.0
#: How far a margin may fall from the last check's and still count as holding: a re-check
#: refines the pose anew, and its margin wobbles by a few hundredths at a right pose.
MARGIN_SLACK = 0.02


@dataclass(frozen=True)
class Verdict:
    """A decision on a link: its ``state``, why, and how many re-checks its pose held."""

    state: str
    reason: str
    holds: int = 0


def clean_reason(text: str, limit: int = 400) -> str:
    """``text`` as a link's reason travels (:class:`protocol.messages.LinkTrust`): printable
    characters only, at most ``limit`` of them (an exception's text may hold newlines)."""
    flat = "".join(c if c.isprintable() else " " for c in text)
    return flat if len(flat) <= limit else flat[: limit - 3] + "..."


def in_grey_zone(margin: float | None, min_margin: float) -> bool:
    """Whether ``margin`` lies in ``[GREY_FLOOR, min_margin)``."""
    return margin is not None and bool(np.isfinite(margin)) and GREY_FLOOR <= margin < min_margin


def pose_change(before: np.ndarray, after: np.ndarray, b: Grid) -> tuple[float, float]:
    """How far map ``b`` moved between two B-pixel -> A-pixel matrices: metres at the centre
    of ``b`` (a turn about a far pixel origin would read as a shift) and degrees."""
    centre = np.array([(b.shape[1] - 1) / 2.0, (b.shape[0] - 1) / 2.0, 1.0])
    before, after = np.asarray(before, np.float64), np.asarray(after, np.float64)
    shift = float(np.hypot(*(after @ centre - before @ centre)[:2])) * b.resolution
    step = np.linalg.inv(before) @ after
    turn = abs(float(np.degrees(np.arctan2(step[1, 0], step[0, 0]))))
    return shift, turn


def within_hold(shift: float, turn: float) -> bool:
    """Whether a pose moved by ``shift`` metres and ``turn`` degrees (:func:`pose_change`)
    stays within :data:`HOLD_M` and :data:`HOLD_DEG`."""
    return shift <= HOLD_M and turn <= HOLD_DEG


def corner_spread(matrix: np.ndarray, covariance: np.ndarray, b: Grid) -> float:
    """How loosely a pose places map ``b``: metres, the largest standard deviation, over the
    four corners of ``b``'s canvas, of where the pose ``matrix`` (B pixel -> A pixel) puts
    them given its ``covariance`` (x px, y px, psi rad about B's pixel origin).

    Each corner's covariance is eq. (4), ``F Sigma_tr F^T`` with the Jacobian ``F`` of
    eq. (7) (:func:`pgvd.uncertainty.transform_covariance`); its spread is the square root
    of the larger eigenvalue.  The corners, not the centre: a heading error of a few tenths
    of a degree moves the far corners by cells.  ``inf`` for a covariance that is not
    finite, symmetric and positive semi-definite: such a pose places nothing.
    """
    try:
        cov = check_covariance(covariance)
    except ValueError:
        return float("inf")
    h, w = b.shape
    corners = np.array([[0.0, 0.0], [w - 1.0, 0.0], [0.0, h - 1.0], [w - 1.0, h - 1.0]])
    at_corners = transform_covariance(corners, heading(np.asarray(matrix, np.float64)), cov)
    return float(np.sqrt(np.linalg.eigvalsh(at_corners)[:, -1].max())) * b.resolution


def holds(before: np.ndarray, after: np.ndarray, b: Grid) -> bool:
    """Whether the pose ``after`` of map ``b`` is ``before`` within :data:`HOLD_M` and
    :data:`HOLD_DEG`."""
    return within_hold(*pose_change(before, after, b))


def _margin_text(margin: float | None) -> str:
    return "none" if margin is None or not np.isfinite(margin) else f"{margin:.2f}"


def provisional(state: str, margin: float | None, min_margin: float) -> bool:
    """Whether a link of ``state`` and ``margin`` is a search's accept below
    :data:`HIGH_BAR` waiting for its re-check: a candidate whose margin clears ``min_margin``
    (a grey-zone candidate's never does)."""
    return state == CANDIDATE and margin is not None and margin >= min_margin


def standing_accept(
    state: str, margin: float | None, first_margin: float | None, min_margin: float
) -> bool:
    """Whether a link is a search's provisional accept (its first decision's margin
    ``first_margin`` cleared ``min_margin``) that its re-checks left above the bar: the kind
    a newer epoch's accept at the same pose confirms (:func:`first_verdict`), and
    :func:`settled_verdict` too.  A grey-zone candidate that a re-check lifted above the bar
    is not: the check weighs only rivals within its basin, so no search of its epochs ever
    accepted it."""
    return provisional(state, margin, min_margin) and provisional(state, first_margin, min_margin)


def settled_verdict(
    margin: float | None, quiet_s: float | None, off: tuple[float, float] | None
) -> Verdict:
    """A search's provisional accept on maps that will not change: confirmed on the merge's
    own bar, as a one-shot merge of the same two maps would be, unless other links in the
    map place its robots elsewhere.

    Parameters
    ----------
    margin : the accept's margin.
    quiet_s : None when both maps are their robots' final versions; else the seconds both
        stayed unchanged (:data:`QUIET_S`).
    off : how far the accept's pose lies from the one the links in the map predict for the
        pair, ``(metres, degrees)`` (:func:`pose_change`); None when no such link places
        the two robots together.  Beyond the hold (:func:`within_hold`) the accept stays a
        candidate: the weakest evidence never overrides other evidence.
    """
    m = _margin_text(margin)
    why = (
        "on both robots' final maps"
        if quiet_s is None
        else f"unchallenged on unchanged maps for {quiet_s:.0f} s"
    )
    if off is not None and not within_hold(*off):
        return Verdict(
            CANDIDATE,
            f"not confirmed {why}: the links in the map place the pair {off[0]:.2f} m and "
            f"{off[1]:.1f} deg from its pose (hold {HOLD_M} m, {HOLD_DEG} deg): margin {m}",
        )
    agree = "" if off is None else ", where the links in the map place the pair"
    return Verdict(CONFIRMED, f"provisional accept {why}{agree}: margin {m}")


def searched_accept(margin: float | None, min_margin: float, why: str = "") -> Verdict:
    """A search's accept: :data:`ACCEPTED` at or above :data:`HIGH_BAR`, else a provisional
    :data:`CANDIDATE`.  An unscored accept (``margin`` None: a registration that reports no
    margin) cannot be graded and is taken at its word."""
    m = _margin_text(margin)
    if margin is None or margin >= HIGH_BAR:
        return Verdict(ACCEPTED, f"{why}margin {m} clears {HIGH_BAR}")
    return Verdict(CANDIDATE, f"{why}provisional: margin {m} clears {min_margin}, not {HIGH_BAR}")


def first_verdict(
    accepted: bool,
    margin: float | None,
    has_pose: bool,
    reason: str,
    min_margin: float,
    previous: str | None = None,
    held: bool = False,
    searched: bool = False,
    standing: bool = False,
    spread: float = 0.0,
) -> Verdict:
    """The state of a pair's first decision in its epochs.

    Parameters
    ----------
    accepted : the merge or check accepted the pose (its margin cleared ``min_margin``).
    margin : the acceptance statistic at the best pose, None or NaN when none was scored.
    has_pose : the decision holds a finite rigid pose.
    reason : the merge's or check's words.
    min_margin : the merge's bar.
    previous : the state of the pair's link of an earlier epoch, if any.
    held : the pose is that earlier link's, within the hold (:func:`holds`).
    searched : the decision is a full search's, with no prediction behind it: its accept
        must clear :data:`HIGH_BAR` to enter the global map at once.
    standing : the earlier link is a candidate that a search accepted
        (:func:`standing_accept`): an accept at its pose confirms it, if the accept places
        the map within the hold by its own covariance (``spread``).  A grey-zone
        candidate's first accept is only a provisional one.
    spread : metres, how loosely the decision's own pose places the corners of map B
        (:func:`corner_spread`).  Beyond :data:`HOLD_M`, finding a standing accept again
        within the hold says nothing its covariance did not: a searched accept stays
        provisional, for the next epoch to find again.
    """
    was_in = previous in IN_MAP
    m = _margin_text(margin)
    again = "found again at the same pose on a newer epoch"
    found = accepted and held and (was_in or (standing and previous == CANDIDATE))
    if found and (was_in or spread <= HOLD_M):
        return Verdict(CONFIRMED, f"{again}: margin {m}")
    if accepted and searched:
        loose = f"{again}, its corners loose by {spread:.2f} m (hold {HOLD_M} m); " if found else ""
        return searched_accept(margin, min_margin, loose)
    if accepted:
        return Verdict(ACCEPTED, f"margin {m} clears {min_margin}")
    if has_pose and in_grey_zone(margin, min_margin):
        if was_in and held:
            return Verdict(CONFIRMED, f"held over a new epoch: margin {m} at the same pose")
        # elsewhere than an earlier link: a canvas that moved shifts every pixel pose, so
        # the new pose earns its place as any candidate does, re-checked at each version
        moved = "; the earlier epoch's link moved" if was_in else ""
        return Verdict(CANDIDATE, f"grey zone: margin {m} below {min_margin}{moved}")
    if was_in:
        return Verdict(WITHDRAWN, f"contradicted by a new epoch: {reason or f'margin {m}'}")
    return Verdict(REJECTED, reason or f"margin {m} below the grey zone")


def cycle_verdict(margin: float | None, spread: float, cycle: str) -> Verdict | None:
    """The confirmation of a pose that a consistent ``cycle`` (words for the log) predicts
    within the hold, if its own covariance pins map B within the hold too (``spread``,
    :func:`corner_spread`); None if it does not: no cycle confirms it.

    A near miss (a pose 3-5 cells off at the maps' corners, inside the hold at the centre)
    composes with right links as a right pose does, so no cycle tells it from the truth;
    two near misses of one robot's early map compose with each other as well.  In the
    development fleet runs two robots were shown 4 cells off for 5.8 s so: one robot's
    early map gave two searches near misses alike (0.78 and a provisional accept), which
    closed a cycle with a right link.  Its covariance is what a near miss on a map still
    small cannot hide (0.28-0.29 m for the near misses of :func:`first_verdict`).  It reads
    the pose alone, so it is asked before the pose graph a cycle needs.
    """
    if spread > HOLD_M:
        return None
    return Verdict(CONFIRMED, f"on a {cycle}: margin {_margin_text(margin)}")


def link_strength(link: object) -> float:
    """How far a link's pose is trusted where a cycle contradicts it: its margin (the
    merge's acceptance statistic, :mod:`pgvd.decision`), ``-inf`` when none was scored (an
    unscored accept cannot outrank a scored one; between unscored ones the pose graph's own
    choice stands)."""
    margin = getattr(link, "margin", None)
    return float(margin) if margin is not None and np.isfinite(margin) else -np.inf


def carries(found_margin: float | None, min_margin: float) -> bool:
    """Whether a search's accept of margin ``found_margin`` may be carried onto the maps
    of a newer epoch by a check from its own pose: only one at or above :data:`HIGH_BAR`.
    For a provisional accept such a check is no confirmation (it starts from the pose it
    would confirm, see the module docstring); the newer epoch's own decision is."""
    return searched_accept(found_margin, min_margin).state == ACCEPTED


def carried_verdict(accepted: bool, margin: float | None, min_margin: float) -> Verdict | None:
    """The state of a search's accept (one that :func:`carries`) checked on newer versions
    of its maps, or None: nothing is taken.  ``accepted``, ``margin``: the check's outcome
    and its margin."""
    if not accepted:
        return None
    return Verdict(ACCEPTED, f"margin {_margin_text(margin)} clears {min_margin}")


def recheck_verdict(
    held_holds: int,
    held_margin: float | None,
    first_margin: float | None,
    accepted: bool,
    margin: float | None,
    held: bool,
    reason: str,
) -> Verdict:
    """A candidate re-checked at its pose on a newer version of its epochs: kept or rejected,
    never confirmed (a version is too little new map to tell a near miss from the truth; a
    newer epoch confirms, see the module docstring).

    ``held_holds``, ``held_margin``, ``first_margin``: the candidate's count of holds, its
    last margin and its first decision's; ``accepted``, ``margin``, ``held``: the re-check's
    outcome, its margin and whether the refined pose stayed within the hold of the
    candidate's.  The verdict's holds count the versions its pose held on, for the log.
    """
    m = _margin_text(margin)
    n = held_holds + 1
    wait = "; a newer epoch's accept here confirms"
    if accepted and held:
        return Verdict(CANDIDATE, f"re-check holds at the bar: margin {m}{wait}", n)
    if accepted:  # the refined pose stands out on its own, away from the candidate's
        return Verdict(CANDIDATE, f"re-check clears the bar, moved: margin {m}", held_holds)
    if margin is None or not np.isfinite(margin) or margin < GREY_FLOOR:
        return Verdict(REJECTED, f"contradicted: {reason or f'margin {m}'}", held_holds)
    if not held:
        return Verdict(REJECTED, f"contradicted: the pose moved (margin {m})", held_holds)
    floor = -np.inf if held_margin is None else held_margin - MARGIN_SLACK
    if margin < floor:
        return Verdict(CANDIDATE, f"margin fell: {m} < {_margin_text(held_margin)}", held_holds)
    gain = margin - (margin if first_margin is None else first_margin)
    return Verdict(CANDIDATE, f"pose held on {n} newer versions: margin {m}, {gain:+.2f}{wait}", n)
