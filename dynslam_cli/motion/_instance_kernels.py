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


@njit(cache=True, nogil=True)
def seen_through(depth: np.ndarray, where: np.ndarray, c2w: np.ndarray, fx: float, fy: float, cx: float, cy: float,
                 kf_w2c: np.ndarray, kf_depth: np.ndarray, stride: int, margin: float) -> np.ndarray:
    """(H, W) bool: the pixels ``where`` with a depth > 0 whose point (camera ``c2w``, 4×4) lands, in front of and
    inside the image of one of the keyframes (``kf_w2c``: (K, 4, 4) world-to-camera; ``kf_depth``: (K, h, w) float32
    depth maps every ``stride`` pixels, nearest), on a depth > 0 more than ``margin`` behind it: the kernel of
    :func:`dynslam_cli.motion.checkable.seen_through`, with the arithmetic of the numpy expression it replaces
    (ray directions in float32, transforms in float64, :func:`~dynslam_cli.motion.checkable.project_into`)."""
    H, W = depth.shape
    out = np.zeros((H, W), np.bool_)
    nk, hs, ws = kf_depth.shape
    fx32, fy32, cx32, cy32 = np.float32(fx), np.float32(fy), np.float32(cx), np.float32(cy)
    for y in range(H):
        for x in range(W):
            if not where[y, x]:
                continue
            z = depth[y, x]
            if not z > 0:
                continue
            px = np.float64((np.float32(x) - cx32) / fx32 * z)
            py = np.float64((np.float32(y) - cy32) / fy32 * z)
            pz = np.float64(np.float32(1.0) * z)
            wx = px * c2w[0, 0] + py * c2w[0, 1] + pz * c2w[0, 2] + c2w[0, 3]
            wy = px * c2w[1, 0] + py * c2w[1, 1] + pz * c2w[1, 2] + c2w[1, 3]
            wz = px * c2w[2, 0] + py * c2w[2, 1] + pz * c2w[2, 2] + c2w[2, 3]
            for k in range(nk - 1, -1, -1):
                T = kf_w2c[k]
                qz = wx * T[2, 0] + wy * T[2, 1] + wz * T[2, 2] + T[2, 3]
                if not qz > 0.05:
                    continue
                qx = wx * T[0, 0] + wy * T[0, 1] + wz * T[0, 2] + T[0, 3]
                qy = wx * T[1, 0] + wy * T[1, 1] + wz * T[1, 2] + T[1, 3]
                u = fx * qx / qz + cx
                v = fy * qy / qz + cy
                if u < 0 or u > W - 1 or v < 0 or v > H - 1:
                    continue
                iu = min(max(int(np.rint(u / stride)), 0), ws - 1)
                iv = min(max(int(np.rint(v / stride)), 0), hs - 1)
                d_kf = kf_depth[k, iv, iu]
                if d_kf > 0 and d_kf > qz + margin:
                    out[y, x] = True
                    break
    return out
