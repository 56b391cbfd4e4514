"""Coarse-to-fine projective point-to-plane ICP between two depth images (numpy).

Used as the initial guess of tracking: the current frame's depth is aligned to the previous
frame's depth on downsampled images (KinectFusion-style projective data association, Gauss-Newton
on the point-to-plane residual with Huber weights).  Rotation and translation are estimated
jointly from geometry, which the photometric/SDF tracking cannot do well from a poor guess.

Conventions: depth in metres (0 = invalid), pinhole intrinsics of the full-resolution image,
the result ``T_ref_cur`` maps points of the current camera frame into the reference camera frame.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np


@dataclass
class ICPResult:
    T: np.ndarray          # 4x4 reference <- current
    inliers: int           # associated points at the last iteration of the finest level
    fraction: float        # inliers / valid current points at the finest level
    rmse: float            # point-to-plane RMSE of the inliers (m)
    ok: bool


def downsample_depth(depth: np.ndarray, factor: int, max_rel_jump: float = 0.1) -> np.ndarray:
    """Block mean of the valid depths of each ``factor``×``factor`` block; blocks with fewer than
    half valid pixels or a depth spread above ``max_rel_jump``·mean (an edge) become 0."""
    if factor <= 1:
        return np.asarray(depth, np.float32)
    d = np.asarray(depth, np.float32)
    h, w = d.shape[0] // factor, d.shape[1] // factor
    parts = [d[i:h * factor:factor, j:w * factor:factor] for i in range(factor) for j in range(factor)]
    n = np.zeros((h, w), np.int32)
    tot = np.zeros((h, w), np.float32)
    hi = np.zeros((h, w), np.float32)
    lo = np.full((h, w), np.inf, np.float32)
    for p in parts:
        v = p > 0
        n += v
        tot += p
        np.maximum(hi, p, out=hi)
        np.minimum(lo, np.where(v, p, np.inf), out=lo)
    mean = tot / np.maximum(n, 1)
    ok = (n * 2 >= factor * factor) & ((hi - lo) <= max_rel_jump * mean)
    return np.where(ok, mean, 0.0).astype(np.float32)


def depth_pyramid(depth: np.ndarray, factors) -> dict:
    """Downsampled depths for each factor, each level built from the next finer one when the
    factors divide (block means of block means: cheaper than from full resolution every time)."""
    out = {}
    prev_f, prev = 1, np.asarray(depth, np.float32)
    for f in sorted(set(int(f) for f in factors)):
        if f % prev_f == 0:
            prev = downsample_depth(prev, f // prev_f)
        else:
            prev = downsample_depth(depth, f)
        prev_f = f
        out[f] = prev
    return out


def level_intrinsics(fx, fy, cx, cy, factor: int):
    """Intrinsics of an image downsampled by block averaging with ``factor``."""
    s = float(factor)
    off = (s - 1) / 2
    return fx / s, fy / s, (cx - off) / s, (cy - off) / s


def _vertices(depth, fx, fy, cx, cy):
    h, w = depth.shape
    vv, uu = np.mgrid[0:h, 0:w]
    z = depth.astype(np.float64)
    return np.stack([(uu - cx) / fx * z, (vv - cy) / fy * z, z], -1)


def _normals(vert, depth, max_rel_jump=0.1):
    """Central-difference normals (h, w, 3) and validity (h, w)."""
    h, w = depth.shape
    n = np.zeros_like(vert)
    ok = np.zeros((h, w), bool)
    if h < 3 or w < 3:
        return n, ok
    dx = vert[1:-1, 2:] - vert[1:-1, :-2]
    dy = vert[2:, 1:-1] - vert[:-2, 1:-1]
    c = np.cross(dx, dy)
    norm = np.linalg.norm(c, axis=-1)
    d = depth[1:-1, 1:-1]
    nb = np.stack([depth[1:-1, 2:], depth[1:-1, :-2], depth[2:, 1:-1], depth[:-2, 1:-1]], -1)
    good = (d > 0) & np.all(nb > 0, -1) & np.all(np.abs(nb - d[..., None]) <= max_rel_jump * d[..., None], -1)
    good &= norm > 1e-12
    n[1:-1, 1:-1] = c / np.maximum(norm, 1e-12)[..., None]
    ok[1:-1, 1:-1] = good
    return n, ok


def _rot(w):
    th = float(np.linalg.norm(w))
    k = np.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]])
    if th < 1e-10:
        return np.eye(3) + k
    return np.eye(3) + np.sin(th) / th * k + (1 - np.cos(th)) / th ** 2 * (k @ k)


def icp_depth(ref_depth: np.ndarray, cur_depth: np.ndarray, intr, init: Optional[np.ndarray] = None,
              factors=(8, 4), iters=(8, 5), max_dist: float = 0.1, huber: float = 0.02,
              min_points: int = 100, min_fraction: float = 0.2, max_depth: float = 0.0,
              depth_weight: float = 0.0, max_points: int = 0) -> ICPResult:
    """Align ``cur_depth`` to ``ref_depth`` (both full resolution or both already downsampled by
    ``factors[-1]`` when ``intr`` is given for that resolution: callers pass full-resolution
    images and intrinsics ``(fx, fy, cx, cy)``).  Returns T (ref <- cur).

    ``max_depth`` > 0 ignores depth beyond it; ``depth_weight`` > 0 down-weights residuals by
    ``z^(-2 depth_weight)`` (noise of structured-light depth grows with z^2).  Both off by default.
    ``max_points`` > 0: at each level at most about this many current points take part (an even
    stride over them); the reference keeps its full resolution for the association."""
    fx, fy, cx, cy = intr
    T = np.eye(4) if init is None else np.array(init, np.float64)
    inl, frac, rmse = 0, 0.0, float("inf")
    ref_pyr, cur_pyr = depth_pyramid(ref_depth, factors), depth_pyramid(cur_depth, factors)
    for factor, n_it in zip(factors, iters, strict=False):
        lfx, lfy, lcx, lcy = level_intrinsics(fx, fy, cx, cy, factor)
        rd, cd = ref_pyr[int(factor)], cur_pyr[int(factor)]
        if max_depth > 0:
            rd = np.where(rd <= max_depth, rd, 0).astype(np.float32)
            cd = np.where(cd <= max_depth, cd, 0).astype(np.float32)
        h, w = rd.shape
        rv = _vertices(rd, lfx, lfy, lcx, lcy)
        rn, rok = _normals(rv, rd)
        cv = _vertices(cd, lfx, lfy, lcx, lcy)[cd > 0]
        if len(cv) < min_points or rok.sum() < min_points:
            return ICPResult(T, 0, 0.0, float("inf"), False)
        if max_points > 0 and len(cv) > max_points:
            cv = cv[:: int(np.ceil(len(cv) / max_points))]
        for _ in range(n_it):
            q = cv @ T[:3, :3].T + T[:3, 3]
            z = q[:, 2]
            front = z > 1e-6
            zs = np.where(front, z, 1.0)
            u = np.rint(q[:, 0] / zs * lfx + lcx).astype(np.int64)
            v = np.rint(q[:, 1] / zs * lfy + lcy).astype(np.int64)
            inside = front & (u >= 0) & (u < w) & (v >= 0) & (v < h)
            ui, vi = np.where(inside, u, 0), np.where(inside, v, 0)
            m = inside & rok[vi, ui]
            p = rv[vi[m], ui[m]]
            nrm = rn[vi[m], ui[m]]
            qm = q[m]
            diff = qm - p
            close = np.linalg.norm(diff, axis=1) < max_dist
            p, nrm, qm, diff = p[close], nrm[close], qm[close], diff[close]
            inl = len(qm)
            frac = inl / max(len(cv), 1)
            if inl < min_points:
                return ICPResult(T, inl, frac, float("inf"), False)
            r = (nrm * diff).sum(1)
            a = np.abs(r)
            wgt = np.where(a <= huber, 1.0, huber / np.maximum(a, 1e-12))
            if depth_weight > 0:  # noise of structured-light depth grows with z^2: weight 1/z^4 (relative to 1 m)
                wgt = wgt / np.maximum(p[:, 2], 0.3) ** (2 * depth_weight)
            J = np.concatenate([nrm, np.cross(qm, nrm)], 1)  # d r / d (t, w) for a left increment
            Jw = J * wgt[:, None]
            H = J.T @ Jw
            g = Jw.T @ r
            H += np.eye(6) * (1e-6 * np.trace(H) / 6 + 1e-12)
            try:
                delta = -np.linalg.solve(H, g)
            except np.linalg.LinAlgError:
                return ICPResult(T, inl, frac, float("inf"), False)
            D = np.eye(4)
            D[:3, :3] = _rot(delta[3:])
            D[:3, 3] = delta[:3]
            T = D @ T
            rmse = float(np.sqrt(np.mean(r * r)))
            if np.linalg.norm(delta[:3]) < 1e-5 and np.linalg.norm(delta[3:]) < 1e-5:
                break
    ok = inl >= min_points and frac >= min_fraction and np.all(np.isfinite(T))
    return ICPResult(T, inl, frac, rmse, bool(ok))
