"""Two robots' maps with a known truth: two segments of one real log, each in its own frame.

A segment of a corrected CARMEN log, ray-cast in a random frame (random yaw in
[0, 2 pi) and random shift), is one robot's partial map.  Two segments give a
pair whose true relative transform -- the B-pixel -> A-pixel matrix of eqs.
(1)-(2) -- follows from the two frames.  Everything is a pure function of the
log and the seed.

Overlap of a pair is ``|cells known in both| / min(|known in A|, |known in B|)``,
where "known" means log-odds != 0 and B's known cells are carried into A by the
true matrix (rounded to the nearest cell).  1 means the smaller map lies
entirely inside the larger one; 0 means no cell was seen by both robots.
"""

from __future__ import annotations

import json
import zlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy import ndimage

from bench.data.drift import Drift, overlap_fit
from pgvd.carmen import LaserScan
from pgvd.grid import Grid, heading, rigid_matrix, world_pose_to_pixel_matrix
from pgvd.integrate import (
    DEFAULT_MODEL,
    InverseSensorModel,
    frame_for,
    integrate,
    integrate_scan,
    perturb_odometry,
    se2,
    select_segment,
)
from pgvd.io import write_map
from pgvd.map_shades import FREE_THRESH, OCCUPIED_THRESH, P_FREE, P_OCCUPIED

#: Segment lengths (fractions of the log) drawn for overlapping pairs.
OVERLAP_LENGTHS = (0.05, 0.5)
#: Segment lengths drawn for disjoint pairs: short, so that two can see disjoint parts.
DISJOINT_LENGTHS = (0.03, 0.12)
#: Overlapping pairs below this overlap are redrawn: they are rejection cases, not merges.
MIN_OVERLAP = 0.1
#: Resolution (m) of the cheap footprints used to find disjoint segments before rendering.
FOOTPRINT_RESOLUTION = 0.5
#: Random shift of each robot's frame, metres (any value works; it only moves the origin).
MAX_SHIFT = 100.0
MAX_DRAWS = 400


@dataclass
class MapPair:
    """Two partial maps and their true relation.

    Attributes
    ----------
    a, b : the two log-odds grids, each in its own frame.
    truth : 3x3 B-pixel -> A-pixel matrix (eqs. (1)-(2)), or None if unknown.
    overlap : fraction of shared known cells (see the module docstring).
    name : a label, e.g. ``"intel-ov03"``.
    info : how the pair was made (segments, seed, frames), JSON-serialisable.
    """

    a: Grid
    b: Grid
    truth: np.ndarray | None
    overlap: float
    name: str
    info: dict = field(default_factory=dict)


def painted_free(grid: Grid) -> Grid:
    """``grid`` as a map image with no unknown cell: every cell a saved map draws unknown
    (between map_saver's thresholds, :data:`pgvd.map_shades.FREE_THRESH` and
    :data:`pgvd.map_shades.OCCUPIED_THRESH`) reads free (:data:`pgvd.map_shades.P_FREE`), as when an
    editor or an export paints the unexplored area white."""
    p = grid.probability()
    unknown = (p >= FREE_THRESH) & (p <= OCCUPIED_THRESH)
    return Grid.from_probability(np.where(unknown, np.asarray(P_FREE, p.dtype), p), grid.resolution)


def painted_pair(pair: MapPair) -> MapPair:
    """``pair`` with both maps :func:`painted_free`; truth, overlap and name unchanged."""
    return MapPair(
        painted_free(pair.a), painted_free(pair.b), pair.truth, pair.overlap, pair.name, pair.info
    )


def speckled(grid: Grid, density: float, rng: np.random.Generator) -> Grid:
    """``grid`` as a raw, uncleaned map: ``density`` of its free cells (below map_saver's
    :data:`pgvd.map_shades.FREE_THRESH`), drawn at random, are walls
    (:data:`pgvd.map_shades.P_OCCUPIED`): spurious returns that a cleaned map would have lost
    (one drawn beside a wall thickens it rather than standing alone)."""
    if not 0 <= density < 1:
        raise ValueError(f"speckle density must be in [0, 1), got {density}")
    p = grid.probability()
    free = np.flatnonzero(p < FREE_THRESH)
    picked = rng.choice(free, size=round(density * free.size), replace=False)
    out = p.copy()
    out.flat[picked] = P_OCCUPIED
    return Grid.from_probability(out, grid.resolution, grid.origin)


def cluttered(p: np.ndarray, density: float, resolution: float, seed: int) -> np.ndarray:
    """Probabilities ``p`` of a map image with furniture drawn in: filled discs of radius
    0.1-0.35 m, ``density`` of them per square metre of free space on average (a Poisson
    count), centred on free cells drawn at random.  Only free cells become walls
    (:data:`pgvd.map_shades.P_OCCUPIED`): nothing is drawn into the unexplored space.  Applied to a
    whole image before its parts are cut, both robots see the same furniture.

    Raises
    ------
    ValueError
        If ``density`` is negative or ``resolution`` not positive.
    """
    import cv2

    if not density >= 0 or not resolution > 0:
        raise ValueError(
            f"clutter needs density >= 0 and resolution > 0, got {density} and {resolution}"
        )
    rng = np.random.default_rng(seed)
    free = p < FREE_THRESH
    cells = np.flatnonzero(free)
    count = min(cells.size, rng.poisson(density * cells.size * resolution**2))
    drawn = np.zeros(p.shape, np.uint8)
    for cell in rng.choice(cells, size=count, replace=False):
        row, col = divmod(int(cell), p.shape[1])
        radius = round(rng.uniform(0.1, 0.35) / resolution)
        cv2.circle(drawn, (col, row), radius, 1, thickness=-1)
    return np.where(free & drawn.astype(bool), np.asarray(P_OCCUPIED, p.dtype), p)


def speckled_pair(pair: MapPair, density: float, seed: int) -> MapPair:
    """``pair`` with both maps :func:`speckled`, each with its own draw (two robots' raw
    maps do not share their speckle); the draws depend on ``seed`` and the pair's name."""
    rng = np.random.default_rng([seed, zlib.crc32(pair.name.encode())])
    return MapPair(
        speckled(pair.a, density, rng),
        speckled(pair.b, density, rng),
        pair.truth,
        pair.overlap,
        pair.name,
        pair.info,
    )


def turn_about(
    degrees: float, centre: np.ndarray, shift: tuple[float, float] | np.ndarray = (0.0, 0.0)
) -> np.ndarray:
    """3x3 pixel transform: a turn of ``degrees`` (eq. (2)) about ``centre``, then ``shift``."""
    m = rigid_matrix(np.radians(degrees), 0.0, 0.0)
    m[:2, 2] = centre - m[:2, :2] @ centre + shift
    return m


def random_frame(rng: np.random.Generator) -> np.ndarray:
    """A random 3x3 SE(2) world-to-map transform: yaw in [0, 2 pi), shift up to MAX_SHIFT."""
    yaw = rng.uniform(0.0, 2.0 * np.pi)
    tx, ty = rng.uniform(-MAX_SHIFT, MAX_SHIFT, 2)
    return se2(tx, ty, yaw)


def true_matrix(a: Grid, a_from_world: np.ndarray, b: Grid, b_from_world: np.ndarray) -> np.ndarray:
    """B-pixel -> A-pixel matrix of two maps rendered from one log in two frames.

    ``a_from_world`` / ``b_from_world`` are the frames' 3x3 world-to-map transforms.
    """
    return (
        world_pose_to_pixel_matrix(a)
        @ a_from_world
        @ np.linalg.inv(b_from_world)
        @ np.linalg.inv(world_pose_to_pixel_matrix(b))
    )


def overlap_fraction(a: Grid, b: Grid, truth: np.ndarray) -> float:
    """Shared known cells over the smaller map's known cells (module docstring)."""
    known_a = a.logodds != 0
    rows, cols = np.nonzero(b.logodds != 0)
    n_a, n_b = int(known_a.sum()), rows.size
    if n_a == 0 or n_b == 0:
        return 0.0
    pts = truth @ np.vstack([cols, rows, np.ones_like(rows)]).astype(np.float64)
    x = np.rint(pts[0]).astype(np.int64)
    y = np.rint(pts[1]).astype(np.int64)
    inside = (x >= 0) & (x < a.shape[1]) & (y >= 0) & (y < a.shape[0])
    shared = int(known_a[y[inside], x[inside]].sum())
    return shared / min(n_a, n_b)


def render(
    part: list[LaserScan],
    rng: np.random.Generator,
    resolution: float,
    model: InverseSensorModel = DEFAULT_MODEL,
) -> tuple[Grid, np.ndarray]:
    """One robot's map of ``part`` in a random frame, and the frame's world -> map transform."""
    transform = random_frame(rng)
    frame = frame_for(part, resolution, transform, model=model)
    return integrate(part, frame, model), transform


def drift(
    part: list[LaserScan], odom_noise: Drift | tuple[float, float], seed: int
) -> list[LaserScan]:
    """The scans as a drifting robot places them: a :class:`bench.data.drift.Drift` model, or
    ``(sigma_t, sigma_r)`` of :func:`pgvd.integrate.perturb_odometry`."""
    if isinstance(odom_noise, Drift):
        return odom_noise.apply(part, seed)
    return perturb_odometry(part, odom_noise, seed)


def make_pair(
    scans: list[LaserScan],
    seg_a: tuple[float, float] | slice,
    seg_b: tuple[float, float] | slice,
    seed: int,
    resolution: float = 0.05,
    odom_noise: Drift | tuple[float, float] | None = None,
    model: InverseSensorModel = DEFAULT_MODEL,
    name: str = "pair",
) -> MapPair:
    """Render two segments of a log as two robots' maps, each in its own random frame.

    Parameters
    ----------
    scans : the whole log (see :func:`pgvd.carmen.read_carmen`).
    seg_a, seg_b : segments, as for :func:`pgvd.integrate.select_segment`.
    seed : makes the frames and the odometry noise; same seed, same pair.
    resolution : metres per cell of both maps.
    odom_noise : optional odometry drift on both robots (see :func:`drift`).  A drifted
        pair has no exact rigid truth; its truth is then the rigid alignment on the
        overlap (:func:`bench.data.drift.overlap_fit`), and ``info`` holds the residual
        distortion (``drift_rms_m``) no rigid transform removes.
    model : inverse sensor model.
    name : label of the pair.
    """
    rng = np.random.default_rng(seed)
    parts, grids, frames = [], [], []
    for k, segment in enumerate((seg_a, seg_b)):
        part = select_segment(scans, segment)
        if not part:
            raise ValueError(f"segment {segment} of a {len(scans)}-scan log is empty")
        # The frame is drawn first, so a drifted pair has the frames of its noise-free twin.
        transform = random_frame(rng)
        seen = part if odom_noise is None else drift(part, odom_noise, seed * 2 + k)
        frame = frame_for(seen, resolution, transform, model=model)
        grids.append(integrate(seen, frame, model))
        frames.append(transform)
        parts.append((part, seen))
    info = {
        "seg_a": _segment_json(seg_a),
        "seg_b": _segment_json(seg_b),
        "seed": seed,
        "resolution": resolution,
        "odom_noise": None
        if odom_noise is None
        else (odom_noise.json() if isinstance(odom_noise, Drift) else list(odom_noise)),
    }
    between = np.eye(3)
    if odom_noise is not None:
        (true_a, drift_a), (true_b, drift_b) = parts
        between, rms, n = overlap_fit(true_a, drift_a, true_b, drift_b, model.max_range)
        info.update(drift_rms_m=rms, drift_fit_points=n)
    # A's map metres = frame_A @ (B's drifted world -> A's drifted world) @ frame_B^-1.
    truth = true_matrix(grids[0], frames[0] @ between, grids[1], frames[1])
    return MapPair(
        grids[0], grids[1], truth, overlap_fraction(grids[0], grids[1], truth), name, info
    )


def _segment_json(segment: tuple[float, float] | slice) -> list:
    if isinstance(segment, slice):
        return ["scans", segment.start, segment.stop]
    return ["fraction", float(segment[0]), float(segment[1])]


def _draw_segment(rng: np.random.Generator, lengths: tuple[float, float]) -> tuple[float, float]:
    length = rng.uniform(*lengths)
    start = rng.uniform(0.0, 1.0 - length)
    return (round(start, 4), round(start + length, 4))


class Footprints:
    """Coarse known-cell masks of segments in the log's world frame, to screen candidates.

    The cells every scan touches are found once; a segment's mask is the union
    of its scans' cells (a cell is known once any ray has touched it).
    """

    def __init__(self, scans: list[LaserScan], model: InverseSensorModel) -> None:
        self.frame = frame_for(scans, FOOTPRINT_RESOLUTION, model=model)
        canvas = self.frame.empty()
        self.cells: list[np.ndarray] = []
        for scan in scans:
            rows, cols = integrate_scan(canvas, scan, self.frame, model)
            r, c = np.nonzero(canvas[rows, cols])
            self.cells.append(
                ((r + rows.start) * canvas.shape[1] + c + cols.start).astype(np.int32)
            )
            canvas[rows, cols] = 0.0

    def mask(self, segment: tuple[float, float] | slice) -> np.ndarray:
        """Known cells of one segment (same selection as :func:`pgvd.integrate.select_segment`)."""
        out = np.zeros(self.frame.shape, bool)
        parts = select_segment(self.cells, segment)
        if parts:
            out.reshape(-1)[np.concatenate(parts)] = True
        return out

    def _masks(
        self, seg_a: tuple[float, float] | slice, seg_b: tuple[float, float] | slice
    ) -> list[np.ndarray]:
        return [self.mask(seg_a), self.mask(seg_b)]

    def disjoint(
        self, seg_a: tuple[float, float] | slice, seg_b: tuple[float, float] | slice
    ) -> bool:
        a, b = self._masks(seg_a, seg_b)
        # One coarse cell of slack: a full-resolution overlap can sit across a coarse border.
        return not np.any(ndimage.binary_dilation(a) & b)

    def overlap(
        self, seg_a: tuple[float, float] | slice, seg_b: tuple[float, float] | slice
    ) -> float:
        """The overlap fraction of the module docstring, on the coarse masks."""
        a, b = self._masks(seg_a, seg_b)
        return float((a & b).sum() / max(1, min(a.sum(), b.sum())))


def make_pairs(
    scans: list[LaserScan],
    n_overlap: int,
    n_disjoint: int,
    seed: int,
    name: str,
    resolution: float = 0.05,
    odom_noise: Drift | tuple[float, float] | None = None,
    model: InverseSensorModel = DEFAULT_MODEL,
    overlap_band: tuple[float, float] = (MIN_OVERLAP, 1.0),
    max_draws: int = MAX_DRAWS,
) -> list[MapPair]:
    """Overlapping pairs (overlap within ``overlap_band``), then disjoint pairs (overlap 0).

    Segments are drawn from the seed: overlapping ones with lengths in
    :data:`OVERLAP_LENGTHS`, disjoint ones in :data:`DISJOINT_LENGTHS`.  Both
    are screened on coarse footprints before rendering (a band narrower than
    the default is rare in real logs, where short segments tend to lie inside
    long ones) and verified at full resolution (disjoint: ``overlap == 0``).
    Disjoint pairs keep their true matrix: it is the transform nothing should find.

    Raises
    ------
    RuntimeError
        If the log does not yield enough pairs of a kind within ``max_draws`` draws.
    """
    lo, hi = overlap_band
    if not 0.0 < lo < hi <= 1.0:
        raise ValueError(f"overlap band must satisfy 0 < lo < hi <= 1, got {overlap_band}")
    rng = np.random.default_rng(seed)
    screen = lo > MIN_OVERLAP or hi < 1.0
    footprints = Footprints(scans, model) if n_disjoint or screen else None
    overlapping: list[MapPair] = []
    draws = 0
    while len(overlapping) < n_overlap and draws < max_draws:
        seg_a, seg_b = _draw_segment(rng, OVERLAP_LENGTHS), _draw_segment(rng, OVERLAP_LENGTHS)
        if screen:
            # Coarse cells inflate the overlap; only rule out what is clearly outside the band.
            coarse = footprints.overlap(seg_a, seg_b)
            if not lo - 0.05 <= coarse <= hi + 0.3:
                draws += 1
                continue
        label = f"{name}-ov{len(overlapping):02d}"
        pair = make_pair(
            scans, seg_a, seg_b, seed * 1000 + draws, resolution, odom_noise, model, label
        )
        draws += 1
        if lo <= pair.overlap <= hi:
            overlapping.append(pair)
    if len(overlapping) < n_overlap:
        raise RuntimeError(f"{name}: only {len(overlapping)} of {n_overlap} overlapping pairs")
    disjoint: list[MapPair] = []
    draws = 0
    while len(disjoint) < n_disjoint and draws < max_draws:
        seg_a, seg_b = _draw_segment(rng, DISJOINT_LENGTHS), _draw_segment(rng, DISJOINT_LENGTHS)
        draws += 1
        if not footprints.disjoint(seg_a, seg_b):
            continue
        label = f"{name}-dj{len(disjoint):02d}"
        pair = make_pair(
            scans, seg_a, seg_b, seed * 1000 + 500 + draws, resolution, odom_noise, model, label
        )
        if pair.overlap == 0.0:
            disjoint.append(pair)
    if len(disjoint) < n_disjoint:
        raise RuntimeError(f"{name}: only {len(disjoint)} of {n_disjoint} disjoint pairs")
    return overlapping + disjoint


def write_pair(
    pair: MapPair, a_path: str | Path, b_path: str | Path, truth_path: str | Path
) -> None:
    """Write both maps as map_server YAML + PGM and the truth as JSON.

    The JSON holds the B-pixel -> A-pixel ``matrix``, ``rotation_deg``,
    ``overlap`` and how the pair was made (segments, seed, resolution).
    """
    write_map(a_path, pair.a)
    write_map(b_path, pair.b)
    doc = {
        "matrix": None if pair.truth is None else np.round(pair.truth, 9).tolist(),
        "rotation_deg": None if pair.truth is None else float(np.degrees(heading(pair.truth))),
        "overlap": pair.overlap,
        "name": pair.name,
        **pair.info,
    }
    Path(truth_path).write_text(json.dumps(doc, indent=2) + "\n")
