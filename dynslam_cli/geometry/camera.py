"""Pinhole camera: pixel rays, back-projection and projection (OpenCV optical frame:
x right, y down, z forward).  Ray directions have z = 1 in the camera frame, so a distance
``z`` along a ray equals the depth value of the pixel (as in Co-SLAM)."""

from __future__ import annotations

import numpy as np
import torch


def pixel_index(uv: np.ndarray, h: int, w: int) -> tuple[np.ndarray, np.ndarray]:
    """Row and column (int64) of the pixel nearest to each point ``uv`` (N×2, u = column), clipped
    into an h×w image."""
    u = np.clip(np.round(uv[:, 0]).astype(np.int64), 0, w - 1)
    v = np.clip(np.round(uv[:, 1]).astype(np.int64), 0, h - 1)
    return v, u


def pixel_dirs(u, v, fx: float, fy: float, cx: float, cy: float):
    """Camera-frame directions (N, 3) with z = 1 for pixel coordinates u (column), v (row).

    Works on numpy arrays or torch tensors (returns the same kind). Pixel (u, v) is the integer
    pixel index, matching the TUM/Bonn intrinsics convention."""
    if isinstance(u, torch.Tensor):
        u = u.to(torch.float32)
        v = v.to(torch.float32)
        return torch.stack([(u - cx) / fx, (v - cy) / fy, torch.ones_like(u)], dim=-1)
    u = np.asarray(u, dtype=np.float32)
    v = np.asarray(v, dtype=np.float32)
    return np.stack([(u - cx) / fx, (v - cy) / fy, np.ones_like(u)], axis=-1).astype(np.float32)


def backproject(depth: np.ndarray, fx: float, fy: float, cx: float, cy: float) -> np.ndarray:
    """H×W depth (m) -> H×W×3 camera-frame points (zeros where depth is 0)."""
    h, w = depth.shape
    vv, uu = np.mgrid[0:h, 0:w]
    d = pixel_dirs(uu.ravel(), vv.ravel(), fx, fy, cx, cy).reshape(h, w, 3)
    return d * depth[..., None].astype(np.float32)


def project(points: np.ndarray, fx: float, fy: float, cx: float, cy: float):
    """(N, 3) camera-frame points -> (N, 2) pixel coordinates (u, v) and (N,) depth."""
    p = np.asarray(points, dtype=np.float64)
    z = p[:, 2]
    zs = np.where(np.abs(z) < 1e-12, 1e-12, z)
    return np.stack([fx * p[:, 0] / zs + cx, fy * p[:, 1] / zs + cy], axis=-1), z


def transform(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply a 4×4 transform to (N, 3) points."""
    T = np.asarray(T)
    return points @ T[:3, :3].T + T[:3, 3]
