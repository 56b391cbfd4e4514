"""Numba kernel of :func:`dynslam_cli.motion.module.instance_centres`: the per-instance sums of
back-projected points in one pass over the image, instead of numpy's masks, gathers and four
``bincount`` passes.  float64 arithmetic in numpy's order (``(u - cx) / fx * z``, summed pixel by
pixel in row-major order as ``bincount`` sums), so the sums are numpy's bit for bit
(tests/test_motion_module.py)."""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def instance_sums(depth: np.ndarray, ids: np.ndarray, k: int, fx: float, fy: float, cx: float, cy: float,
                  step: int) -> tuple[np.ndarray, np.ndarray]:
    """((k, 3) float64 sums of the camera-frame points, (k,) float64 pixel counts) of the instances
    1..k of ``ids`` over every ``step``-th pixel of ``depth`` that holds a finite depth > 0."""
    h, w = depth.shape
    sums = np.zeros((k, 3), np.float64)
    cnt = np.zeros(k, np.float64)
    for y in range(0, h, step):
        for x in range(0, w, step):
            d = depth[y, x]
            i = ids[y, x]
            if not (d > 0 and np.isfinite(d)) or i <= 0 or i > k:
                continue
            z = np.float64(d)
            sums[i - 1, 0] += (x - cx) / fx * z
            sums[i - 1, 1] += (y - cy) / fy * z
            sums[i - 1, 2] += z
            cnt[i - 1] += 1.0
    return sums, cnt
