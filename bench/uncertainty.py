"""Bench of eq. (8) and fusion on a real 1000x1000 map: our blurs against direct baselines.

    python3 -m bench uncertainty [--size 1000] [--repeat 5]

Rotation blur (tangential, sigma = r sigma_psi) against the direct way: a
Gaussian-weighted sum of the map rotated about the centre by many angles
(one rotation per ~0.5 px of arc at the far corner).  Translation blur
against ``scipy.ndimage.convolve`` with the same 2-D kernel.  Then
propagate (warp + both blurs), fuse (33)-(37), and fuse_maps on the bundled
example pair (B's uncertainty propagated into the union canvas, then fused).  Times are the best of
``--repeat`` runs in one process (``cold`` = first call, polar tables not
yet cached), so the ratios are what counts, not the absolute milliseconds.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
from scipy import ndimage

from pgvd.fusion import fuse, fuse_maps
from pgvd.grid import rigid_matrix
from pgvd.io import read_map
from pgvd.transform import warp
from pgvd.uncertainty import _polar_geometry, propagate, rotation_blur, translation_blur

SHARED = Path(__file__).resolve().parents[2] / "shared"


def best_ms(fn: Callable[[], object], repeat: int) -> float:
    times = []
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        times.append(1e3 * (time.perf_counter() - t))
    return min(times)


def rotation_blur_direct(img: np.ndarray, sigma_psi: float) -> np.ndarray:
    """The baseline: sum over angles of the map rotated about its centre, Gaussian weights."""
    h, w = img.shape
    c = np.array([(w - 1) / 2.0, (h - 1) / 2.0])
    r_max = math.hypot(*c)
    step = 0.5 / r_max
    angles = np.arange(-3 * sigma_psi, 3 * sigma_psi + step / 2, step)
    weights = np.exp(-0.5 * (angles / sigma_psi) ** 2)
    weights /= weights.sum()
    out = np.zeros_like(img, dtype=np.float64)
    for a, wt in zip(angles, weights, strict=True):
        m = rigid_matrix(a, 0.0, 0.0)
        m[:2, 2] = c - m[:2, :2] @ c
        out += wt * warp(img, m, img.shape, order=1, cval=0.0)
    return out.astype(np.float32)


def translation_blur_direct(img: np.ndarray, cov: np.ndarray) -> np.ndarray:
    half = math.ceil(4.0 * math.sqrt(np.linalg.eigvalsh(cov).max()))
    ys, xs = np.mgrid[-half : half + 1, -half : half + 1].astype(np.float64)
    inv = np.linalg.inv(cov + 1e-2 * np.eye(2))
    k = np.exp(-0.5 * (inv[0, 0] * xs**2 + 2 * inv[0, 1] * xs * ys + inv[1, 1] * ys**2))
    return ndimage.convolve(img, (k / k.sum()).astype(np.float32), mode="reflect")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=1000)
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--sigma-deg", type=float, default=1.0)
    args = ap.parse_args(argv)
    g = read_map(SHARED / "maps/ritsumeikan_cc4f/cc4.1.yaml")
    n = args.size
    r0, c0 = (g.shape[0] - n) // 2, (g.shape[1] - n) // 2
    if r0 < 0 or c0 < 0:
        print(f"map {g.shape} is smaller than {n}", file=sys.stderr)
        return 2
    lo = g.logodds[r0 : r0 + n, c0 : c0 + n]
    p = 1.0 / (1.0 + np.exp(-lo))
    s = math.radians(args.sigma_deg)
    cov_t = np.array([[4.0, 1.5], [1.5, 2.0]])
    cov3 = np.diag([4.0, 2.0, s * s])
    cov3[0, 1] = cov3[1, 0] = 1.5
    m = rigid_matrix(0.3, 50.0, -80.0)
    rows: list[tuple[str, float, float | None, str]] = []
    print(f"ritsumeikan_cc4f, {n}x{n} cells, sigma_psi {args.sigma_deg} deg", file=sys.stderr)

    _polar_geometry.cache_clear()
    t = time.perf_counter()
    ours = rotation_blur(p, s)
    cold = 1e3 * (time.perf_counter() - t)
    warm = best_ms(lambda: rotation_blur(p, s), args.repeat)
    direct_ms = best_ms(lambda: rotation_blur_direct(p, s), 1)
    direct = rotation_blur_direct(p, s)
    # compare inside the inscribed disc: beyond it the rotated copies bring in cells from
    # outside the map, which ours (a normalised convolution over the map's cells) does not
    yy, xx = np.mgrid[:n, :n]
    disc = np.hypot(xx - (n - 1) / 2, yy - (n - 1) / 2) < (n / 2) * (1 - 3 * s)
    err = np.abs(ours - direct)[disc]
    rows.append(("rotation_blur (cold)", cold, direct_ms, ""))
    rows.append(
        (
            "rotation_blur (warm)",
            warm,
            direct_ms,
            f"vs direct (disc): mean |diff| {err.mean():.4f}, p99 {np.quantile(err, 0.99):.3f}",
        )
    )
    ours_t = translation_blur(p, cov_t)
    t_ms = best_ms(lambda: translation_blur(p, cov_t), args.repeat)
    direct_t_ms = best_ms(lambda: translation_blur_direct(p, cov_t), args.repeat)
    diff_t = np.abs(ours_t - translation_blur_direct(p, cov_t)).max()
    rows.append(("translation_blur", t_ms, direct_t_ms, f"max |diff| {diff_t:.1e}"))
    w_ms = best_ms(lambda: warp(p, m, (n, n), cval=0.5), args.repeat)
    rows.append(("warp (bilinear)", w_ms, None, ""))
    prop = best_ms(lambda: propagate(p, m, cov3, (n, n), cval=0.5), args.repeat)
    rows.append(("propagate (8)", prop, None, "warp + rotation + translation blur"))
    ex = Path(__file__).resolve().parents[1] / "examples"
    ga, gb = read_map(ex / "intel_a.yaml"), read_map(ex / "intel_b.yaml")
    truth = np.array(json.loads((ex / "truth.json").read_text())["matrix"])
    cov_m = np.diag([0.5, 0.5, math.radians(0.5) ** 2])
    fm_ms = best_ms(lambda: fuse_maps(ga, gb, truth, cov_m), args.repeat)
    canvas = fuse_maps(ga, gb, truth, cov_m).shape
    rows.append(
        ("fuse_maps (examples)", fm_ms, None, f"{gb.shape} B into {ga.shape} A, canvas {canvas}")
    )
    other = lo[::-1].copy()
    f_ms = best_ms(lambda: fuse(lo, other), args.repeat)
    rows.append(("fuse (33)-(37)", f_ms, None, ""))

    print(f"{'stage':24} {'ours ms':>9} {'baseline ms':>12} {'speed-up':>9}  notes")
    for name, ms, base, note in rows:
        b = f"{base:12.1f}" if base is not None else f"{'-':>12}"
        r = f"{base / ms:8.1f}x" if base is not None else f"{'-':>9}"
        print(f"{name:24} {ms:9.1f} {b} {r}  {note}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
