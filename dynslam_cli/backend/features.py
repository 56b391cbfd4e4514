"""Keypoints of one frame for the backend: ORB on static pixels spread over an image grid, with
depth and pyramid level; Hamming distances; projection of world points into a camera."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np

from dynslam_cli.geometry import camera
from dynslam_cli.geometry.camera import pixel_index

SCALE = 1.2  # ORB pyramid scale factor
LEVELS = 8
# A keypoint lies on a depth discontinuity when at least OCCLUSION_SHARE of the valid depths within the radius of its
# FAST circle (3 px at its pyramid level) lie more than OCCLUSION_JUMP (relative) in front of or behind its own depth.
FAST_RADIUS = 3
OCCLUSION_JUMP = 0.05
OCCLUSION_SHARE = 0.1


@dataclass
class Keypoints:
    """``uv`` (N×2 float64 px), ``des`` (N×32 uint8 ORB), ``depth`` (N float64 m, 0 = none),
    ``octave`` (N int pyramid level), ``dsig`` (N float64 m: the standard deviation of each
    depth, 0 = none; :func:`depth_sigma`)."""

    uv: np.ndarray
    des: np.ndarray
    depth: np.ndarray
    octave: np.ndarray
    dsig: np.ndarray

    def __len__(self) -> int:
        return int(len(self.uv))

    def subset(self, keep) -> Keypoints:
        return Keypoints(self.uv[keep], self.des[keep], self.depth[keep], self.octave[keep], self.dsig[keep])

    @classmethod
    def empty(cls) -> Keypoints:
        return cls(np.zeros((0, 2)), np.zeros((0, 32), np.uint8), np.zeros(0), np.zeros(0, np.int64), np.zeros(0))


def hamming(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise Hamming distance of two N×32 uint8 descriptor arrays."""
    x = np.bitwise_xor(np.ascontiguousarray(a).view(np.uint64), np.ascontiguousarray(b).view(np.uint64))
    return np.bitwise_count(x).sum(-1, dtype=np.int64)


class Detector:
    """ORB keypoints spread over a grid of about 40 px cells: cv2 finds twice the budget, then the
    strongest keypoint of every cell is taken first, the second strongest next, and so on (ORB-SLAM
    distributes its keypoints over the image for the same reason: clustered keypoints constrain
    the pose poorly)."""

    def __init__(self, n_features: int, width: int, height: int, depth_noise: float, cell: int = 40):
        import cv2

        self.depth_noise = float(depth_noise)
        self.n = int(n_features)
        self.orb = cv2.ORB_create(2 * self.n, scaleFactor=SCALE, nlevels=LEVELS, fastThreshold=12)
        self.cols = max(1, int(round(width / cell)))
        self.rows = max(1, int(round(height / cell)))
        self.w, self.h = int(width), int(height)

    def detect(self, rgb: np.ndarray, depth: np.ndarray, static: Optional[np.ndarray] = None) -> Keypoints:
        """Keypoints of ``rgb`` (H×W×3 uint8) on pixels where ``static`` (H×W bool) is true, with
        the ``depth`` (m, 0 = invalid) at each and its standard deviation (:func:`depth_sigma`)."""
        import cv2

        gray = cv2.cvtColor(np.ascontiguousarray(rgb), cv2.COLOR_RGB2GRAY)
        mask = None if static is None else np.ascontiguousarray(static, np.uint8) * 255
        kps, des = self.orb.detectAndCompute(gray, mask)
        if des is None or not kps:
            return Keypoints.empty()
        uv = np.array([k.pt for k in kps], np.float64)
        resp = np.array([k.response for k in kps], np.float64)
        octave = np.array([k.octave for k in kps], np.int64)
        v, u = pixel_index(uv, *gray.shape)
        if static is not None:  # the mask test of cv2 is on the scaled pyramid level: test again
            ok = np.asarray(static, bool)[v, u]
            uv, resp, octave, des, v, u = uv[ok], resp[ok], octave[ok], des[ok], v[ok], u[ok]
        cell = (v * self.rows // self.h) * self.cols + (u * self.cols // self.w)
        order = np.lexsort((-resp, cell))  # by cell, strongest first
        cs = cell[order]
        start = np.r_[0, np.flatnonzero(np.diff(cs)) + 1]
        rank = np.arange(len(cs)) - np.repeat(start, np.diff(np.r_[start, len(cs)]))
        keep = order[np.lexsort((-resp[order], rank))][: self.n]
        keep = np.sort(keep)
        d = np.asarray(depth, np.float64)[v[keep], u[keep]]
        d = np.where(np.isfinite(d) & (d > 0), d, 0.0)
        sig = depth_sigma(depth, v[keep], u[keep], d, octave[keep], self.depth_noise)
        return Keypoints(uv[keep], np.asarray(des, np.uint8)[keep], d, octave[keep], sig)


def on_depth_discontinuity(depth: np.ndarray, v: np.ndarray, u: np.ndarray, octave: np.ndarray) -> np.ndarray:
    """Which keypoints (at pixels ``v``, ``u``, pyramid level ``octave``) see two surfaces: at least
    :data:`OCCLUSION_SHARE` of the valid depths within the radius of the keypoint's FAST circle
    (:data:`FAST_RADIUS` px at its level, a square window) differ from the keypoint's own depth by
    more than :data:`OCCLUSION_JUMP` of it.  Such a corner is made by an occluding contour, not by
    a point on one surface: it slides along the contour as the camera moves, so it fails to
    reproject without anything moving.  Keypoints without depth are not judged (False)."""
    D = np.asarray(depth, np.float32)
    h, w = D.shape
    n = len(v)
    if n == 0:
        return np.zeros(0, bool)
    d = D[v, u]
    has = np.isfinite(d) & (d > 0)
    rad = np.round(FAST_RADIUS * SCALE ** np.asarray(octave, np.float64)).astype(np.int64)
    R = int(rad.max())
    off = np.arange(-R, R + 1)
    dv, du = np.meshgrid(off, off, indexing="ij")
    dv, du = dv.ravel(), du.ravel()
    inside = np.maximum(np.abs(dv), np.abs(du))[None, :] <= rad[:, None]  # (n, M)
    nb = D[np.clip(v[:, None] + dv[None, :], 0, h - 1), np.clip(u[:, None] + du[None, :], 0, w - 1)]
    valid = inside & np.isfinite(nb) & (nb > 0)
    other = valid & (np.abs(nb - d[:, None]) > OCCLUSION_JUMP * d[:, None])
    share = other.sum(1) / np.maximum(valid.sum(1), 1)
    return has & (share >= OCCLUSION_SHARE)


def depth_sigma(depth: np.ndarray, v: np.ndarray, u: np.ndarray, d: np.ndarray, octave: np.ndarray,
                noise: float) -> np.ndarray:
    """Standard deviation (m) of the depth ``d`` read at pixels (``v``, ``u``) of ``depth`` for
    keypoints at pyramid level ``octave``: the sensor's noise, ``noise`` × d² (structured light),
    and the depth's change over the keypoint's position uncertainty (SCALE^octave px, the largest
    step to a valid 4-neighbour per pixel), added in quadrature; 0 where ``d`` is 0.  A keypoint on
    a depth edge so gets a loose depth and constrains the pose mostly through its pixel."""
    D = np.asarray(depth, np.float64)
    h, w = D.shape
    step = np.zeros(len(d))
    for dv, du in ((0, 1), (0, -1), (1, 0), (-1, 0)):
        nb = D[np.clip(v + dv, 0, h - 1), np.clip(u + du, 0, w - 1)]
        ok = np.isfinite(nb) & (nb > 0)
        step = np.maximum(step, np.where(ok, np.abs(nb - d), 0.0))
    sig = np.hypot(noise * d * d, step * SCALE ** np.asarray(octave, np.float64))
    return np.where(d > 0, sig, 0.0)


def project(T_c2w: np.ndarray, X: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pixels (N×2) and depths (N) of world points ``X`` (N×3) in the camera at ``T_c2w``."""
    R, t = T_c2w[:3, :3], T_c2w[:3, 3]
    pc = (X - t) @ R  # R^T (X - t)
    return camera.project(pc, K[0, 0], K[1, 1], K[0, 2], K[1, 2])


def in_image(uv: np.ndarray, z: np.ndarray, width: int, height: int) -> np.ndarray:
    """Which projections (pixels ``uv`` N×2, depths ``z``, as :func:`project` gives them) land in a
    ``width`` × ``height`` image in front of the camera."""
    return (z > 0.05) & (uv[:, 0] >= 0) & (uv[:, 0] < width) & (uv[:, 1] >= 0) & (uv[:, 1] < height)


def backproject(kp: Keypoints, K: np.ndarray, T_c2w: np.ndarray) -> np.ndarray:
    """World points (N×3) of keypoints with depth."""
    z = kp.depth
    pc = np.stack([(kp.uv[:, 0] - K[0, 2]) / K[0, 0] * z, (kp.uv[:, 1] - K[1, 2]) / K[1, 1] * z, z], 1)
    return pc @ T_c2w[:3, :3].T + T_c2w[:3, 3]
