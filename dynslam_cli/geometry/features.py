"""Feature-based RGB-D odometry: ORB keypoints of a reference frame, lifted to 3-D with its depth,
matched to the current frame's keypoints and solved by PnP with RANSAC.

Where the static depth is nearly degenerate for ICP (Bonn crowd: floor, one wall and a chair
within the depth cut) the image texture still fixes the pose; keypoints whose depth lies beyond
the map's depth cut still constrain rotation.  The tracker uses it as the initial guess that the
dense tracking refines (``tracking.feature_init``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional, Sequence

import numpy as np


def _pixel_index(uv: np.ndarray, h: int, w: int) -> tuple[np.ndarray, np.ndarray]:
    """Row and column of the pixel nearest each keypoint ``uv`` (N×2, x then y), inside h×w."""
    u = np.clip(np.round(uv[:, 0]).astype(np.int64), 0, w - 1)
    v = np.clip(np.round(uv[:, 1]).astype(np.int64), 0, h - 1)
    return v, u


@dataclass
class FeatureSet:
    """Keypoints of one frame: pixel positions ``uv`` (N×2 float32), ORB descriptors ``des``
    (N×32 uint8) and the depth at each keypoint ``depth`` (N float32, 0 = none)."""

    uv: np.ndarray
    des: np.ndarray
    depth: np.ndarray

    def __len__(self) -> int:
        return int(len(self.uv))

    def subset(self, keep: np.ndarray) -> FeatureSet:
        return FeatureSet(self.uv[keep], self.des[keep], self.depth[keep])

    def masked(self, mask: Optional[np.ndarray]) -> FeatureSet:
        """The keypoints on pixels where ``mask`` (H×W bool) is true."""
        if mask is None or len(self) == 0:
            return self
        return self.subset(mask[_pixel_index(self.uv, *mask.shape)])

    def to_dict(self) -> dict:
        return {"uv": self.uv.copy(), "des": self.des.copy(), "depth": self.depth.copy()}

    @classmethod
    def from_dict(cls, d: dict) -> FeatureSet:
        return cls(np.asarray(d["uv"], np.float32), np.asarray(d["des"], np.uint8), np.asarray(d["depth"], np.float32))

    @classmethod
    def empty(cls) -> FeatureSet:
        return cls(np.zeros((0, 2), np.float32), np.zeros((0, 32), np.uint8), np.zeros(0, np.float32))


@dataclass
class PnPResult:
    """``T``: the current camera's pose in the reference camera's frame (4×4, ref ← cur), or in
    the world frame the references' poses are given in (``estimate_multi``); ``ok`` when at least
    ``min_inliers`` matches agree; ``ref_inliers``: the inliers on each reference's keypoints."""

    T: np.ndarray
    matches: int
    inliers: int
    ok: bool
    ref_inliers: tuple = ()


class FeatureOdometry:
    """ORB + ratio-test matching + EPnP/RANSAC + Levenberg-Marquardt refinement on the inliers.

    ``fx, fy, cx, cy``: the (undistorted) intrinsics.  ``n_features``: ORB keypoints per frame;
    ``ratio``: Lowe's ratio test; ``ransac_px``: the inlier reprojection error (px, at 640 px
    width; scaled with the image width); ``min_inliers``: fewer and the result is not ok.
    """

    def __init__(self, fx: float, fy: float, cx: float, cy: float, width: int, n_features: int = 2000,
                 ratio: float = 0.8, ransac_px: float = 2.0, min_inliers: int = 20, ransac_iters: int = 200):
        import cv2

        self.K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]], np.float64)
        self.orb = cv2.ORB_create(int(n_features))
        self.matcher = cv2.BFMatcher(cv2.NORM_HAMMING)
        self.ratio = float(ratio)
        self.ransac_px = float(ransac_px) * max(width, 1) / 640.0
        self.min_inliers = int(min_inliers)
        self.ransac_iters = int(ransac_iters)

    def detect(self, rgb: np.ndarray, depth: np.ndarray, mask: Optional[np.ndarray] = None) -> FeatureSet:
        """Keypoints of ``rgb`` (H×W×3 uint8) on pixels where ``mask`` is true (all when None),
        with the ``depth`` (metres, 0 = invalid) at each."""
        import cv2

        gray = cv2.cvtColor(np.ascontiguousarray(rgb), cv2.COLOR_RGB2GRAY)
        m = None if mask is None else np.asarray(mask, np.uint8) * 255
        kps, des = self.orb.detectAndCompute(gray, m)
        if des is None or not kps:
            return FeatureSet.empty()
        uv = np.array([k.pt for k in kps], np.float32)
        d = np.asarray(depth, np.float32)[_pixel_index(uv, *depth.shape)]
        d = np.where(np.isfinite(d) & (d > 0), d, 0).astype(np.float32)
        return FeatureSet(uv, np.asarray(des, np.uint8), d)

    def match(self, ref: FeatureSet, cur: FeatureSet) -> tuple[np.ndarray, np.ndarray]:
        """Indices (into ``ref``, into ``cur``) of the matches that pass the ratio test, among
        reference keypoints with depth."""
        has = np.flatnonzero(ref.depth > 0)
        if len(has) < 4 or len(cur) < 2:
            return np.zeros(0, np.int64), np.zeros(0, np.int64)
        pairs = self.matcher.knnMatch(ref.des[has], cur.des, k=2)
        qi, ti = [], []
        for p in pairs:
            if len(p) == 2 and p[0].distance < self.ratio * p[1].distance:
                qi.append(p[0].queryIdx)
                ti.append(p[0].trainIdx)
        return has[np.asarray(qi, np.int64)], np.asarray(ti, np.int64)

    def lift(self, fs: FeatureSet, pose: np.ndarray) -> np.ndarray:
        """The keypoints of ``fs`` back-projected with their depth and moved by ``pose`` (N×3;
        rows of keypoints without depth are meaningless)."""
        z = fs.depth.astype(np.float64)
        uv = fs.uv.astype(np.float64)
        X = np.stack([(uv[:, 0] - self.K[0, 2]) / self.K[0, 0] * z, (uv[:, 1] - self.K[1, 2]) / self.K[1, 1] * z, z], 1)
        return X @ np.asarray(pose, np.float64)[:3, :3].T + np.asarray(pose, np.float64)[:3, 3]

    def estimate(self, ref: FeatureSet, cur: FeatureSet) -> PnPResult:
        """The pose of the current camera in the reference camera's frame."""
        return self.estimate_multi([(np.eye(4), ref)], cur)

    def estimate_multi(self, refs: Sequence[tuple[np.ndarray, FeatureSet]], cur: FeatureSet) -> PnPResult:
        """The pose of the current camera (camera-to-world) from its keypoints matched to those of
        several reference frames at poses ``refs[i][0]`` (camera-to-world): one PnP over the
        union of their 3-D points (a local map: fewer reference switches, so less drift)."""
        import cv2

        eye = np.eye(4)
        none = tuple(0 for _ in refs)
        if not refs:
            return PnPResult(eye, 0, 0, False, none)
        allf = FeatureSet(np.concatenate([f.uv for _, f in refs]), np.concatenate([f.des for _, f in refs]),
                          np.concatenate([f.depth for _, f in refs]))
        src = np.concatenate([np.full(len(f), i) for i, (_, f) in enumerate(refs)])
        qi, ti = self.match(allf, cur)
        if len(qi) < max(self.min_inliers, 6):
            return PnPResult(eye, len(qi), 0, False, none)
        X = np.concatenate([self.lift(f, T) for T, f in refs])[qi]
        x = cur.uv[ti].astype(np.float64)
        ok, rvec, tvec, inl = cv2.solvePnPRansac(X, x, self.K, None, iterationsCount=self.ransac_iters,
                                                 reprojectionError=self.ransac_px, confidence=0.999,
                                                 flags=cv2.SOLVEPNP_EPNP)
        if not ok or inl is None or len(inl) < self.min_inliers:
            return PnPResult(eye, len(qi), 0 if inl is None else len(inl), False, none)
        inl = inl[:, 0]
        rvec, tvec = cv2.solvePnPRefineLM(X[inl], x[inl], self.K, None, rvec, tvec)
        if not (np.all(np.isfinite(rvec)) and np.all(np.isfinite(tvec))):
            return PnPResult(eye, len(qi), len(inl), False, none)
        R, _ = cv2.Rodrigues(rvec)
        T = np.eye(4)  # world <- cur: the inverse of the world -> camera(cur) transform PnP returns
        T[:3, :3] = R.T
        T[:3, 3] = -R.T @ tvec[:, 0]
        per = np.bincount(src[qi[inl]], minlength=len(refs))
        return PnPResult(T, len(qi), len(inl), True, tuple(int(v) for v in per))
