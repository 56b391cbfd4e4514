"""Stayed put: instances whose points lie where the recent keyframes saw a surface too.

It breaks the loop where a static surface once labelled dynamic is never mapped and so always
looks 'in front of the map': :func:`stayed_put` is what :meth:`MotionModule.check_and_update
<dynslam_cli.motion.module.MotionModule.check_and_update>` takes as ``stationary``.
"""

from __future__ import annotations

from typing import Optional

import numpy as np

from dynslam_cli.geometry.camera import pixel_dirs, transform
from dynslam_cli.motion.checkable import depth_cell, project_into

# The frame rate that turns ``run.still_seconds`` into frames is measured over this many of the last frames.
RATE_FRAMES = 31


def stationary_instances(depth: np.ndarray, ids: np.ndarray, pose_c2w: np.ndarray, intr, keyframes,
                         tolerance: float = 0.3, min_seen: float = 0.5, min_agree: float = 0.8,
                         step: int = 4) -> np.ndarray:
    """(K,) bool for instance ids 1..K: the instance's 3-D points (at ``pose_c2w``) are where every
    one of ``keyframes`` that looked at them saw a surface too, i.e. it has stayed put since the
    oldest of them.

    A keyframe looked at the instance when at least ``min_seen`` of its points project inside it
    onto a valid raw depth (``depth_raw_small``) not nearer than the point by more than
    ``tolerance`` (m; nearer = something in front hid it); of those at least ``min_agree`` must then
    lie within ``tolerance`` of that depth (a keyframe that saw past the point saw the place empty).
    Keyframes that did not look at it neither confirm nor refute; two that did are needed,
    otherwise False."""
    k = int(ids.max(initial=0))
    out = np.zeros(k, bool)
    kfs = [kf for kf in keyframes if kf.depth_raw_small is not None]
    if k == 0 or len(kfs) < 2:
        return out
    d = np.asarray(depth, np.float32)[::step, ::step]
    lab = np.asarray(ids)[::step, ::step]
    vs, us = np.mgrid[0:depth.shape[0]:step, 0:depth.shape[1]:step]
    m = (d > 0) & (lab > 0)
    if not m.any():
        return out
    z = d[m]
    world = transform(pose_c2w, pixel_dirs(us[m], vs[m], intr.fx, intr.fy, intr.cx, intr.cy) * z[:, None])
    lab = lab[m] - 1
    n = np.bincount(lab, minlength=k)[:k]
    ok = n > 0
    looked = np.zeros(k, np.int64)
    H, W = depth.shape
    for kf in kfs:
        pc, u, v, inside = project_into(world, kf.pose_c2w, intr, W, H)
        small = kf.depth_raw_small
        iv, iu = depth_cell(np.where(inside, u, 0), np.where(inside, v, 0), small.shape)
        d_kf = small[iv, iu].astype(np.float32)
        seen = inside & (d_kf > 0) & (d_kf >= pc[:, 2] - tolerance)  # not hidden behind something nearer
        agree = seen & (np.abs(d_kf - pc[:, 2]) <= tolerance)
        n_seen = np.bincount(lab[seen], minlength=k)[:k]
        n_agree = np.bincount(lab[agree], minlength=k)[:k]
        saw = n_seen >= min_seen * n
        ok &= ~saw | (n_agree >= min_agree * np.maximum(n_seen, 1))
        looked += saw
    return ok & (looked >= 2)


def window_frames(seconds: float, stamps) -> int:
    """How many frames ``seconds`` span at the sequence's frame rate: the median interval between the
    last :data:`RATE_FRAMES` ``stamps`` (s; the frames seen so far); 0 before two frames."""
    t = np.asarray(stamps[-RATE_FRAMES:], np.float64)
    dt = np.diff(t)
    dt = dt[dt > 0]
    if seconds <= 0 or len(dt) == 0:
        return 0
    return int(round(float(seconds) / float(np.median(dt))))


def stayed_put(depth: np.ndarray, ids: np.ndarray, pose_c2w: np.ndarray, intr, keyframes, frame_id: int,
               still_frames: int, still_tolerance: float, depth_threshold: float,
               centre_feature: bool) -> Optional[np.ndarray]:
    """Instances of frame ``frame_id`` whose points stayed within ``still_tolerance`` (``run.still_tolerance``;
    0 = ``depth_threshold``) of the depth every keyframe of the last ``still_frames`` frames saw there (see
    :func:`stationary_instances`; the caller turns ``run.still_seconds`` into frames with :func:`window_frames`);
    None when that window is under 2 frames (``run.still_seconds`` 0 turns it off).  With ``centre_feature``
    (``motion.centre_feature``), where 'static' is learnt at the place only, the window is half as long."""
    frames = still_frames // 2 if centre_feature else still_frames
    if frames < 2:
        return None
    window = [kf for kf in keyframes if frame_id - frames <= kf.frame_id < frame_id]
    tol = still_tolerance if still_tolerance > 0 else depth_threshold
    return stationary_instances(depth, ids, pose_c2w, intr, window, tol)
