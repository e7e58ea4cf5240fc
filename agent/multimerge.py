"""Offline merge of three or more maps on the agents' code path (``pgvd merge A B C ...``).

Every pair of maps is registered with the agents' own registration
(:func:`agent.worker.merge_registration`: the merge of Saeedi et al., IROS 2012, rho test
(32) plus the global check), and the maps are placed and fused by
:func:`agent.globalmap.build_components`, as a fleet would with one robot per map: the
robust pose graph drops links inconsistent around cycles, each component is anchored at
its first input, and maps are fused into it in input order, eqs. (33)-(37).

Maps are registered at the first map's resolution; every matrix reported maps pixels of
the files *as read*, so a resampled map's matrix includes its scale.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from agent.globalmap import Component, build_components
from agent.links import LinkRecord
from agent.worker import RegisterFn, merge_registration
from pgvd.grid import Grid
from pgvd.posegraph import PoseGraphParams
from pgvd.transform import resample, scale_matrix


@dataclass(frozen=True)
class ManyMerge:
    """The outcome of :func:`merge_many`.

    Attributes
    ----------
    ids : the robot id given to each input, in input order (sorting them keeps it).
    scales : per input, file px -> working px (identity unless resampled).
    frames : per input, the map as registered (resampling keeps its metric origin, so its
        map frame is the file's); the components' transforms map their pixels.
    links : every pair tried, ``a`` before ``b`` in input order.
    components : :func:`agent.globalmap.build_components` of the working maps.
    """

    ids: tuple[str, ...]
    scales: tuple[np.ndarray, ...]
    frames: tuple[Grid, ...]
    links: tuple[LinkRecord, ...]
    components: tuple[Component, ...]

    @property
    def merged(self) -> bool:
        """True when at least two maps were merged."""
        return any(len(c.members) > 1 for c in self.components)

    def largest(self) -> Component:
        """The component with the most maps; the first such one on a tie."""
        return max(self.components, key=lambda c: len(c.members))

    def report(self, files: Sequence[str]) -> dict[str, object]:
        """The ``--json`` object of ``pgvd merge A B C ...`` (docs/architecture.md)."""
        index = {r: i for i, r in enumerate(self.ids)}
        comp_of = {r: k for k, c in enumerate(self.components) for r in c.members}
        maps = []
        for i, robot in enumerate(self.ids):
            comp = self.components[comp_of[robot]]
            back = np.linalg.inv(self.scales[index[comp.anchor]])
            scale = back[0, 0]  # working px -> anchor file px, isotropic
            jac = np.diag([scale, scale, 1.0])
            maps.append(
                {
                    "file": str(files[i]),
                    "component": comp_of[robot],
                    "matrix": _rows(back @ comp.transforms[robot] @ self.scales[i]),
                    "covariance": _rows(jac @ comp.covariances[robot] @ jac),
                }
            )
        used = {p for c in self.components for p in c.used}
        links = [
            {
                "a": index[ln.a],
                "b": index[ln.b],
                "accepted": ln.accepted,
                "used": ln.pair in used,
                "matrix": _rows(
                    np.linalg.inv(self.scales[index[ln.a]]) @ ln.matrix @ self.scales[index[ln.b]]
                ),
                "score": ln.score,
            }
            for ln in self.links
        ]
        return {"maps": maps, "links": links}


def _rows(m: np.ndarray) -> list[list[float]]:
    return [[float(v) for v in row] for row in m]


def _working_maps(grids: Sequence[Grid]) -> tuple[list[Grid], list[np.ndarray]]:
    """Every map at the first map's resolution, and file px -> working px per map."""
    res = grids[0].resolution
    out, scales = [], []
    for g in grids:
        if math.isclose(g.resolution, res, rel_tol=1e-6):
            out.append(g)
            scales.append(np.eye(3))
            continue
        r = resample(g, res)
        out.append(r)
        scales.append(scale_matrix(g.resolution, res, g.shape[0], r.shape[0]))
    return out, scales


def merge_many(
    grids: Sequence[Grid],
    register: RegisterFn | None = None,
    params: PoseGraphParams | None = None,
    progress: Callable[[str], None] | None = None,
) -> ManyMerge:
    """Register every pair of ``grids``, place them jointly and fuse each component.

    Parameters
    ----------
    grids : two or more maps, in input order (the first of a component is its anchor).
    register : pairwise registration; the agents' :func:`agent.worker.merge_registration`
        by default.
    params : the pose graph's floors and threshold.
    progress : called with one line per registration.

    Raises
    ------
    ValueError
        With fewer than two maps.
    """
    if len(grids) < 2:
        raise ValueError(f"merging needs two or more maps, got {len(grids)}")
    register = register or merge_registration()
    say = progress or (lambda line: None)
    work, scales = _working_maps(grids)
    width = len(str(len(grids) - 1))
    ids = tuple(f"m{i:0{width}d}" for i in range(len(grids)))  # sorted as the inputs
    links = []
    for i, j in itertools.combinations(range(len(grids)), 2):
        res = register(work[i], work[j])
        outcome = "accepted" if res.accepted else "rejected"
        why = f" ({res.rejection})" if res.rejection else ""
        say(f"maps {i} and {j}: {outcome}, score {res.score:.3f}{why}")
        links.append(
            LinkRecord(
                ids[i], 0, ids[j], 0, res.accepted, res.matrix, res.covariance, res.score, "merge"
            )
        )
    maps = {r: (0, g) for r, g in zip(ids, work, strict=True)}
    comps = build_components(maps, links, params)
    return ManyMerge(ids, tuple(scales), tuple(work), tuple(links), tuple(comps))
