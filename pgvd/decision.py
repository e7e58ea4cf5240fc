"""Acceptance of a merge: the winning hypothesis against the wrong ones of the same pair.

The paper's existence test (32) asks whether *some* edge pair matches; with
the translation free, a long corridor or a repetitive building matches
somewhere almost always, so (32) alone cannot say whether two maps overlap.
A fixed threshold on the overlay agreement cannot either: it lets a large
look-alike corridor pass (most walls agree at a wrong shift) and turns away a
small overlap that is crisp but short.

The decision here compares the winner with its rivals on the same pair.
Every finalist hypothesis is refined and scored by the overlay evidence
``E = agree - w * disagree`` (walls on walls, walls on clear free space, both
ways, on one subsample of wall cells, each few-metre square of the overlap
re-aligned by a few cells first: :func:`pgvd.agreement.local_agreement`).
The *rival* is the best of the finalists whose pose differs from the
winner's (a look-alike corridor, the other side of a symmetric building, a
quarter turn) and of the winner shifted by a few metres (a corridor that
looks alike along its length).  The
statistic is the winner's evidence beyond the rival's, per wall cell of the
overlap::

    margin = (E_win - max(E_rival, 0)) / n - noise / sqrt(n),   n = agree_win + disagree_win

measured on the pose that is returned: the winner after its last refinement
on all its wall cells, scored again (:func:`restate`).  The first term is a
mean over the ``n`` walls of the overlap; the second lowers it by about its
sampling error, so that a small overlap (a few hundred walls, whose margin
swings most from one scoring to the next) must stand out more than a large
one to pass the same threshold (``DecisionParams.margin_noise``, measured there).

It scales with the evidence of the pair itself, not with fixed floors: a
rival that scores as well as the winner drives its first term to 0 whatever
the size of the overlap (a look-alike corridor), while a small overlap whose
every other pose is contradicted by the maps can pass however short it is.
A rival with negative evidence (the maps contradict that pose) counts as no
rival, evidence 0, the empty overlay: being contradicted less than a rival
is no evidence for a pose, and a margin taken from a contradicted rival would
hang on which rivals the search happened to find.  Scored so, the largest margin
of a wrong or negative winner is 0.53-0.54 in the default run of the merge bench,
in the two with every candidate heading turned by 0.1 degree either way
(``python -m bench.merge --methods pgvd pgvd-turned+0.1 pgvd-turned-0.1``) and in
two more whose candidate headings moved (their finalists replayed with
``python3 -m bench redecide``).  The threshold is set on the
development negatives of the merge bench (``bench/results/acceptance.md``);
``docs/studies-merge-history.md`` has what scoring rivals otherwise accepted.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pgvd.overlay import Agreement


@dataclass(frozen=True)
class Scored:
    """One refined hypothesis.

    Attributes
    ----------
    matrix : numpy.ndarray
        3x3 B pixel -> A pixel.
    agreement : Agreement
        Its overlay counts (:func:`pgvd.agreement.map_agreement`) on a subsample.
    """

    matrix: np.ndarray
    agreement: Agreement

    def evidence(self, weight: float) -> float:
        """The overlay evidence ``agree - weight * disagree``.

        Parameters
        ----------
        weight : float
            Weight of a wall on clear free space against a wall on a wall.

        Returns
        -------
        float
        """
        return self.agreement.agree - weight * self.agreement.disagree


@dataclass(frozen=True)
class Decision:
    """The winner among the scored hypotheses and its margin over the best rival.

    Attributes
    ----------
    winner : Scored
        The hypothesis of largest evidence.
    margin : float
        The statistic of the module docstring (0 or below when a rival scores as
        well as the winner, when the maps contradict the winner, or without overlap).
    other : float
        Best evidence of a finalist with another pose (a look-alike, a turn); ``-inf``
        when there is none.
    shifted : float
        Best evidence of the winner's shifted copies (the probes); ``-inf`` without
        probes.  Close to the winner's, the overlap does not pin the pose along that shift.
    best : Scored or None
        The rival of evidence :attr:`rival`, None without rivals.
    """

    winner: Scored
    margin: float
    other: float = -np.inf
    shifted: float = -np.inf
    best: Scored | None = None

    @property
    def rival(self) -> float:
        """Best evidence of a hypothesis with another pose (``-inf`` when there is none)."""
        return max(self.other, self.shifted)


def pose_difference(m1: np.ndarray, m2: np.ndarray, centre: np.ndarray) -> tuple[float, float]:
    """Heading difference (degrees, absolute) and displacement of ``centre`` (pixels).

    Parameters
    ----------
    m1, m2 : numpy.ndarray
        3x3 B pixel -> A pixel.
    centre : numpy.ndarray
        A point of B, ``(x, y)``, where the two are compared.

    Returns
    -------
    tuple of float
    """
    dpsi = np.arctan2(m1[0, 1], m1[0, 0]) - np.arctan2(m2[0, 1], m2[0, 0])
    c = np.array([centre[0], centre[1], 1.0])
    return abs(float(np.degrees(np.angle(np.exp(1j * dpsi))))), float(
        np.hypot(*((m1 - m2) @ c)[:2])
    )


def same_pose(m1: np.ndarray, m2: np.ndarray, centre: np.ndarray, deg: float, px: float) -> bool:
    """Whether two B->A matrices are one pose.

    Parameters
    ----------
    m1, m2, centre : numpy.ndarray
        As in :func:`pose_difference`.
    deg, px : float
        Largest heading difference (degrees) and displacement of ``centre`` (pixels).

    Returns
    -------
    bool
        True when both differences are within bounds.
    """
    turn, move = pose_difference(m1, m2, centre)
    return turn <= deg and move <= px


def shifted(matrix: np.ndarray, steps: tuple[float, ...]) -> list[np.ndarray]:
    """The pose ``matrix`` (B->A pixels) moved by each step along A's x and y axes, both ways.

    Parameters
    ----------
    matrix : numpy.ndarray
        3x3 B pixel -> A pixel.
    steps : tuple of float
        Shifts in pixels.

    Returns
    -------
    list of numpy.ndarray
        ``4 len(steps)`` matrices.
    """
    out = []
    for step in steps:
        for dx, dy in ((step, 0.0), (-step, 0.0), (0.0, step), (0.0, -step)):
            m = matrix.copy()
            m[:2, 2] += (dx, dy)
            out.append(m)
    return out


def decide(
    scored: list[Scored],
    weight: float,
    centre: np.ndarray,
    deg: float = 2.0,
    px: float = 20.0,
    probes: list[Scored] | None = None,
    noise: float = 0.0,
) -> Decision:
    """Pick the best-evidence hypothesis and measure it against its best rival.

    Parameters
    ----------
    scored : list of Scored
        Refined hypotheses with their subsample counts (at least one).
    weight : float
        The disagreement weight ``w`` of the evidence.
    centre : numpy.ndarray
        A point of B (pixels) at which two poses are compared, e.g. its wall centroid.
    deg, px : float, optional
        Hypotheses within this heading and displacement of the winner are the
        winner's own (they converged to it in the refinement), not rivals.
    probes : list of Scored, optional
        Poses that are rivals only (never the winner): the winner shifted by a
        few metres (:func:`shifted`).  Along a corridor that looks alike over
        its length they score nearly as well as the winner, and the margin
        drops; where the overlap pins the pose they score far less.
    noise : float, optional
        The margin is lowered by ``noise / sqrt(agree_win + disagree_win)`` (see
        :func:`margin_against`).

    Returns
    -------
    Decision

    Raises
    ------
    ValueError
        If ``scored`` is empty.
    """
    if not scored:
        raise ValueError("decide needs at least one scored hypothesis")
    ranked = sorted(scored, key=lambda s: (-s.evidence(weight), -s.agreement.ratio))
    win = ranked[0]

    def best(group: list[Scored]) -> Scored | None:
        rivals = [s for s in group if not same_pose(s.matrix, win.matrix, centre, deg, px)]
        return max(rivals, key=lambda s: s.evidence(weight), default=None)

    other, shift = best(ranked[1:]), best(probes or [])
    other_ev, shift_ev = (-np.inf if s is None else s.evidence(weight) for s in (other, shift))
    top = other if other_ev >= shift_ev else shift
    margin = margin_against(win, max(other_ev, shift_ev), weight, noise)
    return Decision(win, margin, other_ev, shift_ev, top)


def margin_against(win: Scored, rival: float, weight: float, noise: float) -> float:
    """The margin of the module docstring: ``(E_win - max(E_rival, 0)) / n - noise / sqrt(n)``.

    ``n = agree_win + disagree_win``; ``E_rival`` 0 without a rival, and a rival the maps
    contradict (``E_rival < 0``) counts as none.

    Parameters
    ----------
    win : Scored
        The winner.
    rival : float
        The evidence it is measured against (``-inf``: none).
    weight : float
        The disagreement weight ``w`` of the evidence.
    noise : float
        The sampling-noise term's coefficient.

    Returns
    -------
    float
        0 without overlap.
    """
    points = win.agreement.agree + win.agreement.disagree
    if not points:
        return 0.0
    return float((win.evidence(weight) - max(rival, 0.0)) / points - noise / np.sqrt(points))


def restate(decision: Decision, final: Scored, weight: float, noise: float = 0.0) -> Decision:
    """The decision measured on the pose that is returned: the winner after its last refinement.

    The finalists are compared after a quick refinement on a subsample; the
    winner is then refined on all its wall cells, which can move it by a
    cell or two and by tenths of a degree (most on a drifted map, which has no
    single rigid fit).  The margin that accepts the merge is that of the pose
    the merge returns, against the same best rival.

    Parameters
    ----------
    decision : Decision
        The decision among the finalists (:func:`decide`).
    final : Scored
        The winner after its last refinement, scored as the finalists were.
    weight : float
        The disagreement weight ``w`` of the evidence.
    noise : float, optional
        As in :func:`decide`.

    Returns
    -------
    Decision
        ``final`` as the winner, the same rivals, and its margin.
    """
    margin = margin_against(final, decision.rival, weight, noise)
    return Decision(final, margin, decision.other, decision.shifted, decision.best)


def describe_rival(decision: Decision, centre: np.ndarray, res: float) -> str:
    """Where the best rival lies from the winner, for the reason of a rejection.

    Parameters
    ----------
    decision : Decision
        A decision with its rivals (:func:`decide`, :func:`restate`).
    centre : numpy.ndarray
        The point of B, ``(x, y)`` pixels, at which the poses were compared.
    res : float
        Cell size (m).

    Returns
    -------
    str
        ``"none"``; ``"the pose shifted 1.5 m"`` when a shifted copy of the winner is the
        best rival (the overlap does not pin the pose along that shift); otherwise
        ``"another pose 12.3 m and 91 deg away"`` (a look-alike or a turn).
    """
    if decision.best is None:
        return "none"
    turn, move = pose_difference(decision.winner.matrix, decision.best.matrix, centre)
    if decision.shifted > decision.other:
        return f"the pose shifted {move * res:.1f} m"
    return f"another pose {move * res:.1f} m and {turn:.0f} deg away"
