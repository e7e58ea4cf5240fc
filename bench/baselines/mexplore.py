"""m-explore's ``multirobot_map_merge`` pairwise estimation, rebuilt with OpenCV's Python bindings.

The ROS package (hrnr/m-explore, ``map_merge/src/combine_grids/merging_pipeline.cpp``):

1. each ``nav_msgs/OccupancyGrid`` becomes an 8-bit image of its raw cell values
   (free 0, occupied 100, unknown -1 read as 255);
2. AKAZE features (its default ``FeatureType``) via ``computeImageFeatures``;
3. ``cv::detail::AffineBestOf2NearestMatcher(full_affine=false, try_use_gpu=false,
   match_conf=0.3)``: best-of-2-nearest matching, then ``estimateAffinePartial2D``
   with RANSAC; its confidence is ``inliers / (8 + 0.3 * matches)``;
4. ``leaveBiggestComponent`` keeps the pair only if that confidence reaches the
   node's ``estimation_confidence`` parameter, default 1.0.

The affine bundle adjustment the node runs afterwards only polishes accepted
transforms of many maps; for one pair it is left out.  ``estimateAffinePartial2D``
allows a uniform scale; the result is projected onto a rotation (SVD) so that it
is comparable with the rigid truth, which can only help this baseline.
"""

from __future__ import annotations

import cv2
import numpy as np

from bench.baselines.common import OCCUPIED, BaselineResult, classes
from pgvd.grid import Grid

#: ``estimation_confidence`` default of the map_merge node.
CONFIDENCE = 1.0


def ros_image(grid: Grid) -> np.ndarray:
    """The OccupancyGrid data as the node's cv::Mat: free 0, occupied 100, unknown 255."""
    labels = classes(grid)
    img = np.full(grid.shape, 255, np.uint8)
    img[labels > 0] = 0
    img[labels == OCCUPIED] = 100
    return img


def _rigid(h: np.ndarray) -> np.ndarray:
    u, _, vt = np.linalg.svd(h[:2, :2])
    r = u @ vt
    if np.linalg.det(r) < 0:
        u[:, -1] *= -1
        r = u @ vt
    m = np.eye(3)
    m[:2, :2] = r
    m[:2, 2] = h[:2, 2]
    return m


def _akaze() -> cv2.Feature2D:
    if not hasattr(cv2, "AKAZE_create"):
        # OpenCV 5 moved AKAZE out of the main modules; the [bench] extra pins < 5.
        raise RuntimeError(f"OpenCV {cv2.__version__} has no AKAZE; install opencv<5")
    return cv2.AKAZE_create()


def merge(a: Grid, b: Grid, confidence: float = CONFIDENCE) -> BaselineResult:
    """Estimate the B-pixel -> A-pixel transform the way m-explore does."""
    finder = _akaze()
    fb = cv2.detail.computeImageFeatures2(finder, ros_image(b))
    fa = cv2.detail.computeImageFeatures2(finder, ros_image(a))
    # apply(features1, features2) estimates H taking image-1 points to image-2 points.
    matcher = cv2.detail_AffineBestOf2NearestMatcher(False, False, 0.3)
    info = matcher.apply(fb, fa)
    matcher.collectGarbage()
    h = np.asarray(info.H, dtype=np.float64) if info.H is not None else None
    if h is None or h.shape != (3, 3) or not np.all(np.isfinite(h)):
        return BaselineResult(False, np.eye(3), 0.0)
    conf = float(info.confidence)
    return BaselineResult(conf >= confidence, _rigid(h), conf)
