"""Tracking one frame against the local map: landmarks projected from a predicted pose and
matched to the frame's keypoints by descriptor within a search radius, a robust pose-only
Gauss-Newton (pixel and disparity residuals, each under its own noise: :func:`information`; Huber
kernel, chi-square outlier rounds), a wider
search and PnP relocalisation when too few inliers remain, and a clear ``lost`` otherwise.

The pose-only step is a hand-written numpy Gauss-Newton rather than gtsam: it has 6 unknowns and a
few hundred residuals, so building a factor graph (a Python loop over the matches) would cost more
than solving it; vectorised it takes about a millisecond per round."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from dynslam_cli.backend.features import SCALE, Keypoints, hamming, in_image, project
from dynslam_cli.data.types import Intrinsics
from dynslam_cli.geometry.lie import so3_exp_np

CHI2_STEREO = 7.815  # 95 % gate of a 3-dof residual (u, v, u_R)
CHI2_MONO = 5.991  # 2 dof


@dataclass(frozen=True)
class Camera(Intrinsics):
    """The camera's pinhole intrinsics and the virtual stereo focal-baseline product ``bf`` (px·m)."""

    bf: float


def stereo_residuals(cam: Camera, Tcw: np.ndarray, X: np.ndarray, uv: np.ndarray, depth: np.ndarray):
    """Camera points and the residual observed - predicted (N×3): pixel (u, v) and the virtual
    stereo disparity bf/depth (the last is meaningless where ``depth`` is 0)."""
    pc = X @ Tcw[:3, :3].T + Tcw[:3, 3]
    return pc, residuals(cam, pc, uv, depth)


def residuals(cam: Camera, pc: np.ndarray, uv: np.ndarray, depth: np.ndarray) -> np.ndarray:
    """Observed - predicted (N×3) of camera points ``pc`` seen at ``uv`` with ``depth``: pixel
    (u, v) and disparity bf/depth (meaningless where ``depth`` is 0)."""
    z = np.where(pc[:, 2] > 1e-6, pc[:, 2], 1e-6)
    u = cam.fx * pc[:, 0] / z + cam.cx
    v = cam.fy * pc[:, 1] / z + cam.cy
    disp = cam.bf / np.where(depth > 0, depth, 1.0)
    return np.stack([uv[:, 0] - u, uv[:, 1] - v, disp - cam.bf / z], 1)


def information(cam: Camera, depth: np.ndarray, dsig: np.ndarray, octave: np.ndarray) -> np.ndarray:
    """(N, 3) inverse variances of the residuals of :func:`stereo_residuals`: the pixel's
    sigma is SCALE^octave px; the disparity's, the depth's standard deviation ``dsig`` carried to
    bf/depth (bf·dsig/depth² px); 0 where there is no depth."""
    info = np.empty((len(depth), 3))
    info[:, :2] = (SCALE ** (-2.0 * np.asarray(octave, np.float64)))[:, None]
    has = depth > 0
    sd = np.where(has, cam.bf * np.asarray(dsig, np.float64) / np.where(has, depth, 1.0) ** 2, 1.0)
    info[:, 2] = np.where(has, 1.0 / np.maximum(sd, 1e-3) ** 2, 0.0)
    return info


def chi2(cam: Camera, Tcw: np.ndarray, X, uv, depth, octave, dsig) -> np.ndarray:
    """Whitened squared error of each observation (:func:`information`)."""
    return whitened_chi2(cam, X @ Tcw[:3, :3].T + Tcw[:3, 3], uv, depth, octave, dsig)


def whitened_chi2(cam: Camera, pc: np.ndarray, uv, depth, octave, dsig) -> np.ndarray:
    """:func:`chi2` of camera points ``pc``: infinite behind the camera."""
    e = residuals(cam, pc, uv, depth)
    out = (e * e * information(cam, depth, dsig, octave)).sum(1)
    out[pc[:, 2] <= 1e-6] = np.inf
    return out


def pose_jacobian(cam: Camera, pc: np.ndarray, stereo: np.ndarray) -> np.ndarray:
    """(N, 3, 6) derivative of the predicted (u, v, disparity) of camera points ``pc`` with respect
    to the left perturbation (rho, phi) of the world-to-camera transform; the disparity row is 0
    where ``stereo`` is False (no depth)."""
    n = len(pc)
    x, y, z = pc[:, 0], pc[:, 1], pc[:, 2]
    Jp = np.zeros((n, 3, 3))
    Jp[:, 0, 0] = cam.fx / z
    Jp[:, 0, 2] = -cam.fx * x / z ** 2
    Jp[:, 1, 1] = cam.fy / z
    Jp[:, 1, 2] = -cam.fy * y / z ** 2
    Jp[:, 2, 2] = -cam.bf / z ** 2
    Jp[~stereo, 2, :] = 0
    skew = np.zeros((n, 3, 3))  # -[pc]x
    skew[:, 0, 1], skew[:, 0, 2], skew[:, 1, 2] = z, -y, x
    skew[:, 1, 0], skew[:, 2, 0], skew[:, 2, 1] = -z, y, -x
    return np.concatenate([Jp, Jp @ skew], 2)


def pose_covariance(cam: Camera, T_c2w: np.ndarray, X: np.ndarray, kp: Keypoints) -> np.ndarray:
    """Covariance (6x6) of the pose-only estimate ``T_c2w`` from world points ``X`` seen at
    keypoints ``kp`` (its inliers), in :func:`optimize_pose`'s parametrisation: the inverse of the
    Gauss-Newton information under :func:`information`'s noise.  Infinite where the points do not
    fix the pose (fewer than 3, or a rank-deficient information)."""
    Tcw = np.linalg.inv(np.asarray(T_c2w, np.float64))
    pc = X @ Tcw[:3, :3].T + Tcw[:3, 3]
    front = pc[:, 2] > 1e-6
    if int(front.sum()) < 3:
        return np.full((6, 6), np.inf)
    stereo = kp.depth[front] > 0
    J = pose_jacobian(cam, pc[front], stereo)
    info = information(cam, kp.depth[front], kp.dsig[front], kp.octave[front])
    H = np.einsum("nki,nk,nkj->ij", J, info, J)
    if np.linalg.matrix_rank(H) < 6:
        return np.full((6, 6), np.inf)
    return np.linalg.inv(H)


def optimize_pose(cam: Camera, T_c2w: np.ndarray, X: np.ndarray, kp: Keypoints, huber: float,
                  rounds: int = 4, iters: int = 10) -> tuple[np.ndarray, np.ndarray]:
    """Robust pose-only optimisation of camera ``T_c2w`` observing world points ``X`` at keypoints
    ``kp`` (same order); ORB-SLAM's scheme: ``rounds`` rounds of Gauss-Newton, after each the
    observations over the chi-square gate are left out of the next (and may come back), Huber
    kernel in all but the last.  Returns the pose and the inlier mask."""
    n = len(X)
    if n < 3:
        return T_c2w.copy(), np.zeros(n, bool)
    stereo = kp.depth > 0
    th = np.where(stereo, huber ** 2, huber ** 2 * CHI2_MONO / CHI2_STEREO)
    info = information(cam, kp.depth, kp.dsig, kp.octave)
    Tcw = np.linalg.inv(T_c2w)
    inl = np.ones(n, bool)
    for r in range(rounds):
        robust = r < rounds - 1
        for _ in range(iters):
            pc, e = stereo_residuals(cam, Tcw, X, kp.uv, kp.depth)
            z = pc[:, 2]
            front = z > 1e-6
            w = info * (inl & front)[:, None]
            e[~stereo, 2] = 0
            c2 = (e * e * info).sum(1)
            if robust:
                s = np.sqrt(np.maximum(c2, 1e-18))
                w = w * np.where(s <= np.sqrt(th), 1.0, np.sqrt(th) / s)[:, None]
            J = pose_jacobian(cam, np.where(front[:, None], pc, [0.0, 0.0, 1.0]), stereo)
            Jw = (J * w[:, :, None]).reshape(-1, 6)
            H = Jw.T @ J.reshape(-1, 6)
            g = Jw.T @ e.reshape(-1)
            if w[:, 0].sum() <= 0 or np.linalg.matrix_rank(H) < 6:
                break
            d = np.linalg.solve(H, g)
            R = so3_exp_np(d[3:])
            Tcw = np.block([[R @ Tcw[:3, :3], (R @ Tcw[:3, 3] + d[:3])[:, None]], [np.zeros((1, 3)), np.ones((1, 1))]])
            if np.linalg.norm(d) < 1e-8:
                break
        inl = chi2(cam, Tcw, X, kp.uv, kp.depth, kp.octave, kp.dsig) <= th
    return np.linalg.inv(Tcw), inl


def search_by_projection(cam: Camera, T_c2w: np.ndarray, X: np.ndarray, des: np.ndarray, scale: np.ndarray,
                         kp: Keypoints, radius: float, ratio: float = 0.8, max_dist: int = 100):
    """Match landmarks (world points ``X``, descriptors ``des``, expected ORB scale factor
    ``scale``) projected into the camera at ``T_c2w`` to keypoints ``kp`` within ``radius`` px ×
    the scale, by Hamming distance (at most ``max_dist``, best below ``ratio`` × second best), one
    landmark per keypoint.  Returns (landmark rows, keypoint rows, visible mask over landmarks)."""
    from scipy.spatial import cKDTree

    uv, z = project(T_c2w, X, cam.K)
    vis = in_image(uv, z, cam.width, cam.height)
    none = np.zeros(0, np.int64)
    if not vis.any() or len(kp) == 0:
        return none, none, vis
    li = np.flatnonzero(vis)
    rad = radius * np.clip(scale[li], 1.0, SCALE ** 7)
    pairs = cKDTree(uv[li]).sparse_distance_matrix(cKDTree(kp.uv), float(rad.max()), output_type="ndarray")
    a, b = pairs["i"].astype(np.int64), pairs["j"].astype(np.int64)
    level = np.log(np.clip(scale[li[a]], 1e-3, None)) / np.log(SCALE)
    ok = (pairs["v"] <= rad[a]) & (np.abs(kp.octave[b] - level) <= 2)
    a, b = a[ok], b[ok]
    if len(a) == 0:
        return none, none, vis
    dist = hamming(des[li[a]], kp.des[b])
    order = np.lexsort((b, dist, a))  # per landmark, best first
    a, b, dist = a[order], b[order], dist[order]
    first = np.r_[True, a[1:] != a[:-1]]
    nxt = np.r_[dist[1:], 10 ** 6]  # where the next row has the same landmark: its second best
    has2 = np.r_[a[1:] == a[:-1], False]
    best_ok = first & (dist <= max_dist) & ~(has2 & (dist >= ratio * nxt))
    a, b, dist = a[best_ok], b[best_ok], dist[best_ok]
    order = np.lexsort((a, dist))  # one landmark per keypoint: the closest descriptor
    a, b = a[order], b[order]
    _, keep = np.unique(b, return_index=True)
    keep = np.sort(keep)
    return li[a[keep]], b[keep], vis


def pnp_relocalise(cam: Camera, X: np.ndarray, des: np.ndarray, kp: Keypoints, seed: int, min_inliers: int,
                   ratio: float = 0.8, px: float = 4.0):
    """Pose (camera-to-world) from the frame's keypoints matched to landmarks ``X``/``des`` by
    descriptor alone and PnP with RANSAC (cv2, seeded); None when fewer than ``min_inliers``."""
    import cv2

    if len(X) < 6 or len(kp) < 6:
        return None
    pairs = cv2.BFMatcher(cv2.NORM_HAMMING).knnMatch(kp.des, des, k=2)
    q, t = [], []
    for p in pairs:
        if len(p) == 2 and p[0].distance < ratio * p[1].distance and p[0].distance <= 100:
            q.append(p[0].queryIdx)
            t.append(p[0].trainIdx)
    if len(q) < max(min_inliers, 6):
        return None
    q, t = np.asarray(q), np.asarray(t)
    cv2.setRNGSeed(int(seed))
    ok, rvec, tvec, inl = cv2.solvePnPRansac(X[t].astype(np.float64), kp.uv[q].astype(np.float64), cam.K, None,
                                             iterationsCount=300, reprojectionError=px * cam.width / 640.0,
                                             confidence=0.999, flags=cv2.SOLVEPNP_EPNP)
    if not ok or inl is None or len(inl) < min_inliers:
        return None
    R, _ = cv2.Rodrigues(rvec)
    T = np.eye(4)
    T[:3, :3] = R.T
    T[:3, 3] = -R.T @ tvec[:, 0]
    return T if np.all(np.isfinite(T)) else None


@dataclass
class FrameTrack:
    """What tracking one frame found: ``pose`` (camera-to-world), the matched landmark ids and
    keypoint rows that are inliers, the landmark ids that projected into the frame, ``lost``,
    ``reason`` (motion | wide | relocalised | lost: ...); ``matched`` (keypoint rows of every match
    of the search around the motion model's guess, inliers or not), ``matched_lm`` (their landmark
    ids) and ``reprojects`` (whether each reprojects at ``pose`` within the 95 % gate of its pixel
    noise: :func:`reprojects`)."""

    pose: np.ndarray
    lm: np.ndarray
    kp: np.ndarray
    visible: np.ndarray
    lost: bool
    reason: str
    matched: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    reprojects: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))
    matched_lm: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))


def reprojects(cam: Camera, T_c2w: np.ndarray, X: np.ndarray, kp: Keypoints) -> np.ndarray:
    """Whether each world point ``X[i]`` projects at ``T_c2w`` onto its keypoint ``kp[i]`` within the
    95 % chi-square gate of the keypoint's pixel noise (SCALE^octave px; depth left out: a thing
    that moves shows in the image, a noisy depth does not)."""
    uv, z = project(T_c2w, X, cam.K)
    e2 = ((uv - kp.uv) ** 2).sum(1) * SCALE ** (-2.0 * np.asarray(kp.octave, np.float64))
    return (z > 1e-6) & (e2 <= CHI2_MONO)


def reprojects_within(cam: Camera, T_c2w: np.ndarray, X: np.ndarray, kp: Keypoints, part: np.ndarray,
                      huber: float, min_matches: int) -> np.ndarray:
    """:func:`reprojects` of the matches ``part`` (bool over them) at the pose solved on those
    alone (robust, from ``T_c2w``): where the rest of the map disagrees with that part (drift),
    a match of it is judged against the part it belongs to.  Fewer than ``min_matches`` in it:
    judged at ``T_c2w``.  The others: False."""
    out = np.zeros(len(X), bool)
    rows = np.flatnonzero(part)
    T = T_c2w
    if len(rows) >= min_matches:
        T, inl = optimize_pose(cam, T_c2w, X[rows], kp.subset(rows), huber)
        T = T if int(inl.sum()) >= min_matches and np.all(np.isfinite(T)) else T_c2w
    out[rows] = reprojects(cam, T, X[rows], kp.subset(rows))
    return out


def track_frame(cam: Camera, guess: np.ndarray, kp: Keypoints, ids: np.ndarray, X: np.ndarray, des: np.ndarray,
                scale_fn, search_px: float, huber: float, min_matches: int, seed: int) -> FrameTrack:
    """Track keypoints ``kp`` against the local map (landmark ``ids``, positions ``X``,
    descriptors ``des``; ``scale_fn(rows, dist)`` their expected ORB scale at camera distance
    ``dist``) from the predicted pose ``guess``."""
    r = search_px * cam.width / 640.0

    # the landmark and keypoint rows matched by the search around the motion model's guess (the wider
    # one where it was needed): a thing that started to move is matched there, and fails to reproject
    matches = [np.zeros(0, np.int64), np.zeros(0, np.int64)]

    def attempt(T, radius, keep=True):
        dist = np.linalg.norm(X - T[:3, 3], axis=1)
        a, b, vis = search_by_projection(cam, T, X, des, scale_fn(np.arange(len(X)), dist), kp, radius)
        if keep:
            matches[:] = [a, b]
        if len(a) < 3:
            return T, a[:0], b[:0], vis
        T2, inl = optimize_pose(cam, T, X[a], kp.subset(b), huber)
        return T2, a[inl], b[inl], vis

    T, a, b, _ = attempt(guess, r)
    reason = "motion"
    if len(a) < min_matches:
        T, a, b, _ = attempt(guess, 3 * r)
        reason = "wide"
    if len(a) < min_matches:
        Tp = pnp_relocalise(cam, X, des, kp, seed, min_matches)
        if Tp is None:
            return FrameTrack(guess.copy(), a[:0], b[:0], np.zeros(0, np.int64), True,
                              f"lost: {len(a)} static matches (< {min_matches}) and no PnP relocalisation")
        T, reason = Tp, "relocalised"
    # the local map from the tracked pose: more, closer matches (a relocalised frame's evidence comes from here)
    T, a, b, vis = attempt(T, max(r / 4, 2.0), keep=reason == "relocalised")
    if len(a) < min_matches:
        return FrameTrack(guess.copy(), a[:0], b[:0], np.zeros(0, np.int64), True,
                          f"lost: {len(a)} static inliers (< {min_matches}) after {reason} tracking")
    a_all, b_all = matches
    return FrameTrack(T, ids[a], b, ids[vis], False, reason, b_all, reprojects(cam, T, X[a_all], kp.subset(b_all)),
                      ids[a_all])
