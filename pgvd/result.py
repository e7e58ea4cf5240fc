"""What a merge returns: :class:`MergeResult`, its JSON, and the stage clock that times it."""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from pgvd.diagnostics import MergeDiagnostics
from pgvd.grid import matrix_to_pose
from pgvd.stage_clock import StageClock


@dataclass
class MergeResult:
    """Outcome of :func:`pgvd.merge.merge`; ``matrix`` maps B pixels to A pixels.

    Attributes
    ----------
    margin : float
        The acceptance statistic of :mod:`pgvd.decision`: the winner's overlay
        evidence beyond its best rival's, per overlapping wall cell; NaN when no
        hypothesis reached the full-resolution stage.
    distortion_px : float
        Largest local misfit of the overlap after the rigid fit, pixels
        (:func:`pgvd.alignment.residual_distortion`): a drifted map has no single
        rigid fit.  NaN when no hypothesis reached the full-resolution stage.
    headings_deg : tuple of float
        The candidate headings (degrees) that went through the PGVD/Gamma stages.
    candidate : bool
        A rejection whose best pose (``matrix``) has a margin in the grey zone
        ``[DecisionParams.GREY_MARGIN, min_margin)``: worth a look, not a merge.

    A rejection whose best pose reached the decision keeps that pose in ``matrix``,
    ``rotation_deg`` and ``translation_px`` (its ``margin`` is finite); one rejected
    before has the identity.
    """

    accepted: bool
    matrix: np.ndarray
    rotation_deg: float
    translation_px: tuple[float, float]
    covariance: np.ndarray
    score: float
    timings_ms: dict[str, float]
    reason: str
    diagnostics: MergeDiagnostics | None = field(default=None, repr=False)
    margin: float = float("nan")
    distortion_px: float = float("nan")
    headings_deg: tuple[float, ...] = ()
    candidate: bool = False

    def with_time(self, step: str, ms: float) -> MergeResult:
        """This result with ``ms`` milliseconds of work done beside its stages (a check
        before the search, a retry's first try) as ``timings_ms[step]``, in the total."""
        total = self.timings_ms["total"] + ms
        return replace(self, timings_ms={**self.timings_ms, step: ms, "total": total})

    def to_json(self) -> dict:
        """The object ``pgvd merge --json`` prints, plus ``reason``.

        A rejected result has no covariance: its entries are ``None`` (JSON null).
        ``candidate`` is true when a rejected best pose lies in the grey zone.
        """
        return {
            "accepted": bool(self.accepted),
            "matrix": [[float(v) for v in row] for row in self.matrix],
            "rotation_deg": float(self.rotation_deg),
            "translation_px": [float(self.translation_px[0]), float(self.translation_px[1])],
            "covariance": [
                [float(v) if np.isfinite(v) else None for v in row] for row in self.covariance
            ],
            "score": float(self.score),
            "timings_ms": {k: round(float(v), 3) for k, v in self.timings_ms.items()},
            "reason": self.reason,
            "margin": float(self.margin) if np.isfinite(self.margin) else None,
            "distortion_px": float(self.distortion_px) if np.isfinite(self.distortion_px) else None,
            "candidate": bool(self.candidate),
        }


def merge_result(
    accepted: bool,
    reason: str,
    clock: StageClock,
    matrix: np.ndarray,
    score: float,
    covariance: np.ndarray,
    diagnostics: MergeDiagnostics | None = None,
    **extra: object,
) -> MergeResult:
    """A :class:`MergeResult` of the pose ``matrix`` (B pixel -> A pixel), timed by ``clock``;
    ``extra`` sets its optional fields (``margin``, ``distortion_px``, ``headings_deg``)."""
    psi, tx, ty = matrix_to_pose(matrix)
    return MergeResult(
        accepted=accepted,
        matrix=matrix,
        rotation_deg=float(np.degrees(psi)),
        translation_px=(tx, ty),
        covariance=covariance,
        score=score,
        timings_ms=clock.total(),
        reason=reason,
        diagnostics=diagnostics,
        **extra,
    )


def rejected(
    reason: str,
    clock: StageClock,
    matrix: np.ndarray | None = None,
    score: float = 0.0,
    **extra: object,
) -> MergeResult:
    """A rejection: ``matrix`` (the identity when no pose reached the decision), no
    covariance (NaN)."""
    m = np.eye(3) if matrix is None else matrix
    return merge_result(False, reason, clock, m, score, np.full((3, 3), np.nan), **extra)
