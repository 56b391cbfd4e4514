"""Forgetting: what makes keyframe rays unusable, for now or for good (the map stops replaying them).

- :func:`refresh_keyframes`: after a classifier update, every keyframe's usable rays are
  recomputed from the instances now called dynamic (within the mask dilation, :func:`near_ids`),
  and the backend drops the landmarks made on them; reclassified static rays are usable again.
- ``gone`` (never usable again): rays on the surface of what the backward check saw leave
  (:func:`forget_departed` with :func:`forget_near`), and rays along which the newest keyframe
  sees the scene changed (:func:`carve` with :func:`forget_seen_through` and :func:`forget_overtaken`).
"""

from __future__ import annotations

import numpy as np

from dynslam_cli.geometry.camera import pixel_dirs, transform
from dynslam_cli.motion.checkable import project_into
from dynslam_cli.slam.keyframes import DEPTH_STRIDE, depth_edges


def refresh_keyframes(keyframes, motion) -> int:
    """Re-classify the registered instances of every keyframe in ``keyframes`` (a
    :class:`~dynslam_cli.slam.keyframes.KeyframeStore`) with the current classifier of ``motion``
    (a :class:`~dynslam_cli.motion.module.MotionModule`) and let the store forget the dynamic ones
    (rays masked, backend landmarks dropped); returns rays masked."""
    dynamic = {fid: motion.dynamic_ids(r["feats"], r["prior"]) for fid, r in keyframes.instances().items()}
    return keyframes.forget(dynamic)


def near_ids(ids: np.ndarray, pixels: np.ndarray, mask_dilation: float) -> np.ndarray:
    """(M, 2) int32: the largest and smallest instance id within the mask dilation radius
    (``motion.mask_dilation``) of each keyframe ray ``pixels`` (u, v), so that re-masking a
    keyframe after a classifier update dilates dynamic instances as the live mask does."""
    import cv2

    from dynslam_cli.motion.module import dilation_radius

    r = dilation_radius(mask_dilation, ids.shape[1])
    u, v = pixels[:, 0].astype(np.int64), pixels[:, 1].astype(np.int64)
    own = ids[v, u].astype(np.int32)
    if r <= 0:
        return np.stack([own, own], 1)
    k = np.ones((2 * r + 1, 2 * r + 1), np.uint8)
    f = ids.astype(np.float32)  # exact for ids < 2^24
    hi = cv2.dilate(f, k)[v, u].astype(np.int32)
    lo = cv2.erode(f, k)[v, u].astype(np.int32)
    return np.stack([hi, lo], 1)


def _gone(kf) -> np.ndarray:
    """The keyframe's ``gone`` flags, created (all False) on first use."""
    if kf.gone is None:
        kf.gone = np.zeros(len(kf), bool)
    return kf.gone


def _mark_gone(kf, hit) -> int:
    """Mark rays ``hit`` (bool mask or indices) gone for good and unusable; returns how many were new."""
    gone = _gone(kf)
    before = int(gone.sum())
    gone[hit] = True
    kf.usable &= ~gone
    return int(gone.sum()) - before


def forget_near(keyframes, points: np.ndarray, intr, radius: float) -> int:
    """Mark as ``gone`` (never usable again) the keyframe rays whose surface point lies within
    ``radius`` (m) of any of ``points`` (N, 3; world): geometry a later frame saw has left.
    Returns the number of rays newly marked."""
    from scipy.spatial import cKDTree

    if len(points) == 0 or not keyframes:
        return 0
    tree = cKDTree(points)
    # only rays inside the points' box grown by the radius (a little more, for rounding) can be within it, and
    # rays already gone stay gone: the tree is asked about the rest alone
    slack = radius * (1 + 1e-6) + 1e-9
    lo, hi = points.min(0) - slack, points.max(0) + slack
    newly = 0
    for kf in keyframes:
        wp = kf.world_points(intr)
        cand = np.flatnonzero(((wp >= lo) & (wp <= hi)).all(1) & ~_gone(kf))
        if len(cand):
            d, _ = tree.query(wp[cand], distance_upper_bound=radius)
            newly += _mark_gone(kf, cand[np.isfinite(d)])
    return newly


def forget_seen_through(keyframes, depth: np.ndarray, pose_c2w: np.ndarray, intr, margin: float,
                        window: int = 3) -> int:
    """Mark as ``gone`` (never usable again) the keyframe rays whose surface point a camera at
    ``pose_c2w`` with (static) ``depth`` (H, W; 0 = none) sees through: the point projects into the
    image and every valid depth within ``window`` pixels lies more than ``margin`` (m) behind it
    (camera z). A pixel with an invalid neighbour judges nothing, so depth edges, holes and masked
    movers carve nothing and a small pose error next to a thin object does not either.
    Returns the number of rays newly marked."""
    import cv2

    d = np.where(np.isfinite(depth), depth, 0).astype(np.float32)
    if not keyframes or margin <= 0 or not (d > 0).any():
        return 0
    H, W = d.shape
    near = cv2.erode(d, np.ones((2 * window + 1, 2 * window + 1), np.uint8), borderType=cv2.BORDER_CONSTANT,
                     borderValue=0) if window > 0 else d
    newly = 0
    for kf in keyframes:
        pc, u, v, inside = project_into(kf.world_points(intr), pose_c2w, intr, W, H)
        idx = np.flatnonzero(inside & ~_gone(kf))
        if len(idx) == 0:
            continue
        dn = near[np.round(v[idx]).astype(np.int64), np.round(u[idx]).astype(np.int64)]
        newly += _mark_gone(kf, idx[(dn > 0) & (dn > pc[idx, 2] + margin)])
    return newly


def forget_overtaken(keyframes, depth: np.ndarray, pose_c2w: np.ndarray, intr, margin: float,
                     step: int = 2) -> int:
    """Mark as ``gone`` the keyframe rays whose free space a surface has since moved into: a camera
    at ``pose_c2w`` sees (static ``depth``, 0 = none, depth edges left out) a point that the
    keyframe saw past (its raw depth, the nearest within one stored cell around the point's pixel,
    lies more than ``margin`` behind it), and the keyframe's ray at that pixel (within about
    ``step`` px: the points are splatted on a ``step`` px grid, then spread by one cell) ends more
    than ``margin`` behind the point. That ray's free space is no longer free, so
    replaying it would carve the newcomer (a box set down) out of the map. Keyframes without
    ``depth_raw_small`` are skipped. Returns the number of rays newly marked."""
    import cv2

    d = np.where(np.isfinite(depth), depth, 0).astype(np.float32)
    if not keyframes or margin <= 0:
        return 0
    d = np.where(depth_edges(d, 0.05, 2), 0, d)
    H, W = d.shape
    vs, us = np.mgrid[0:H:step, 0:W:step]
    z = d[::step, ::step]
    ok = z > 0
    if not ok.any():
        return 0
    world = transform(pose_c2w, pixel_dirs(us[ok], vs[ok], intr.fx, intr.fy, intr.cx, intr.cy) * z[ok][:, None])
    k3 = np.ones((3, 3), np.uint8)
    hz, wz = (H + step - 1) // step, (W + step - 1) // step
    newly = 0
    for kf in keyframes:
        raw = kf.depth_raw_small
        if raw is None:
            continue
        pc, u, v, inside = project_into(world, kf.pose_c2w, intr, W, H)
        idx = np.flatnonzero(inside)
        if len(idx) == 0:
            continue
        seen = cv2.erode(raw.astype(np.float32), k3, borderType=cv2.BORDER_CONSTANT, borderValue=0)
        hs, ws = seen.shape
        iu = np.clip(np.round(u[idx] / DEPTH_STRIDE).astype(np.int64), 0, ws - 1)
        iv = np.clip(np.round(v[idx] / DEPTH_STRIDE).astype(np.int64), 0, hs - 1)
        zc = pc[idx, 2]
        arrived = seen[iv, iu] > zc + margin  # the keyframe saw past where this surface now is
        if not arrived.any():
            continue
        idx, zc = idx[arrived], zc[arrived].astype(np.float32)
        zbuf = np.full((hz, wz), np.inf, np.float32)
        np.minimum.at(zbuf, (np.clip(np.round(v[idx]).astype(np.int64) // step, 0, hz - 1),
                             np.clip(np.round(u[idx]).astype(np.int64) // step, 0, wz - 1)), zc)
        zbuf = cv2.erode(zbuf, k3, borderType=cv2.BORDER_CONSTANT, borderValue=float(np.inf))
        cand = np.flatnonzero(~_gone(kf))
        px = kf.pixels[cand]
        zn = zbuf[np.minimum(px[:, 1] // step, hz - 1), np.minimum(px[:, 0] // step, wz - 1)]
        newly += _mark_gone(kf, cand[zn < kf.depth[cand] - margin])
    return newly


def forget_departed(res, observed: np.ndarray, rendered: np.ndarray, pose_c2w: np.ndarray, keyframes, intr,
                    depth_threshold: float, radius: float) -> int:
    """With ``radius`` (``run.forget_radius``) > 0: the keyframe rays on the surface of what the
    backward check (``res``, a :class:`~dynslam_cli.motion.types.CheckResult`) saw leave (flagged
    rendered segments, where the ``observed`` depth lies more than ``depth_threshold`` (t_d) behind
    the ``rendered`` one) are marked gone, so the map stops replaying a departed object even when
    the classifier does not recognise its keyframe crops.  Returns the rays newly marked."""
    if radius <= 0 or res is None or res.rendered_ids is None or not len(res.rendered_flagged):
        return 0
    import cv2

    rids = res.rendered_ids
    h, w = rids.shape
    ren = cv2.resize(rendered.astype(np.float32), (w, h), interpolation=cv2.INTER_NEAREST)
    obs = cv2.resize(observed.astype(np.float32), (w, h), interpolation=cv2.INTER_NEAREST)
    left = np.isin(rids, res.rendered_flagged) & (ren > 0) & (obs > 0) & (obs - ren > depth_threshold)
    if not left.any():
        return 0
    sx, sy = w / observed.shape[1], h / observed.shape[0]
    fx, fy, cx, cy = intr.fx * sx, intr.fy * sy, (intr.cx + 0.5) * sx - 0.5, (intr.cy + 0.5) * sy - 0.5
    vs, us = np.nonzero(left)
    pw = transform(pose_c2w, pixel_dirs(us, vs, fx, fy, cx, cy) * ren[vs, us][:, None])
    return forget_near(keyframes, pw, intr, radius)


def carve(keyframes, intr, depth: np.ndarray, static_mask: np.ndarray, margin: float, width: int) -> int:
    """With ``margin`` (``run.carve_margin``) > 0, judged on the newest keyframe's static pixels, the
    earlier keyframes' rays are marked gone where the scene changed along them: the newest keyframe
    sees through their surface point (it has left: a picked-up box, a person who walked on),
    or sees a surface in the free space they crossed (something arrived: the box set down
    elsewhere).  ``width``: the frame width (px), which scales the windows.  Returns the rays newly marked."""
    if margin <= 0 or len(keyframes) < 2:
        return 0
    d = np.where(static_mask, np.asarray(depth, np.float32), 0).astype(np.float32)
    window = max(1, int(round(3 * width / 640)))
    pose = keyframes[-1].pose_c2w
    n = forget_seen_through(keyframes[:-1], d, pose, intr, margin, window)
    return n + forget_overtaken(keyframes[:-1], d, pose, intr, margin, max(1, int(round(2 * width / 320))))
