"""Keyframe ray store: each keyframe keeps a random subset of its pixels as rays for replay.

Per stored ray: pixel (u, v), colour, depth, instance id (int32, -1 = none) and a mutable
``usable`` flag (False = the dynamic module excluded the ray; bundle adjustment skips it).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from dynslam_cli.geometry.camera import pixel_dirs, project, transform
from dynslam_cli.geometry.lie import inv_np


@dataclass
class Keyframe:
    frame_id: int            # index of the frame in the SLAM's own stream (0, 5, 10, ...)
    timestamp: float
    pixels: np.ndarray       # (M, 2) int32 (u, v)
    rgb: np.ndarray          # (M, 3) uint8
    depth: np.ndarray        # (M,) float32 metres (> 0)
    instance_ids: np.ndarray  # (M,) int32, -1 = none
    usable: np.ndarray       # (M,) bool, mutable
    pose_c2w: np.ndarray = field(default_factory=lambda: np.eye(4))  # refined by BA
    # the keyframe's depth map on its static pixels (0 elsewhere) every DEPTH_STRIDE pixels (float16;
    # None = not kept): what the map was taught from it, for keyframe_visibility
    depth_small: np.ndarray | None = None
    # (M, 2) int32: the largest and smallest instance id within the dynamic mask's dilation radius
    # of each ray (None = not kept); a ray is unusable when any of its ids is dynamic
    near_ids: np.ndarray | None = None
    # the keyframe's whole depth map (movers included) every DEPTH_STRIDE pixels (float16; None = not
    # kept): what the camera saw, for stationary_instances
    depth_raw_small: np.ndarray | None = None
    # (M,) bool: rays whose surface point a later frame saw gone (a departed object); never usable
    gone: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.depth)

    def world_points(self, intr) -> np.ndarray:
        """(M, 3) world points of the stored rays (pixels back-projected at their depth, posed)."""
        dirs = pixel_dirs(self.pixels[:, 0], self.pixels[:, 1], intr.fx, intr.fy, intr.cx, intr.cy)
        return transform(self.pose_c2w, dirs * self.depth[:, None])

    def to_dict(self) -> dict:
        return {k: getattr(self, k) for k in ("frame_id", "timestamp", "pixels", "rgb", "depth",
                                              "instance_ids", "usable", "pose_c2w", "depth_small", "near_ids",
                                              "depth_raw_small", "gone")}

    @staticmethod
    def from_dict(d: dict) -> "Keyframe":
        def opt_array(key):
            v = d.get(key)
            return None if v is None else np.asarray(v)

        return Keyframe(int(d["frame_id"]), float(d["timestamp"]), np.asarray(d["pixels"]), np.asarray(d["rgb"]),
                        np.asarray(d["depth"]), np.asarray(d["instance_ids"]), np.array(d["usable"], bool),
                        np.array(d["pose_c2w"], np.float64), opt_array("depth_small"), opt_array("near_ids"),
                        opt_array("depth_raw_small"), opt_array("gone"))


DEPTH_STRIDE = 4


def subsample_depth(depth: np.ndarray) -> np.ndarray:
    """The depth map every DEPTH_STRIDE pixels (nearest), float16, as keyframes keep it."""
    return np.asarray(depth, np.float32)[::DEPTH_STRIDE, ::DEPTH_STRIDE].astype(np.float16)


def valid_pixels(depth: np.ndarray, mask: np.ndarray | None, border: int, need_depth: bool = True) -> np.ndarray:
    """Flat indices of pixels that may be sampled: inside the border, mask True, depth > 0."""
    h, w = depth.shape
    ok = np.zeros((h, w), bool)
    b = max(0, int(border))
    if h > 2 * b and w > 2 * b:
        ok[b:h - b, b:w - b] = True
    if need_depth:
        ok &= depth > 0
    if mask is not None:
        m = np.asarray(mask)
        if m.shape != (h, w):
            from dynslam_cli.errors import DynslamError
            raise DynslamError(f"mask shape {m.shape} does not match the frame {h}x{w}")
        ok &= m.astype(bool)
    return np.flatnonzero(ok)


def depth_edges(depth: np.ndarray, rel_jump: float = 0.05, dilate: int = 2) -> np.ndarray:
    """Pixels within ``dilate`` px of a depth discontinuity: a relative step > ``rel_jump``
    between 4-neighbours, or a valid pixel next to a missing one.  (H, W) bool."""
    import cv2

    d = np.asarray(depth, np.float32)
    valid = d > 0
    pad = np.pad(d, 1, mode="edge")
    jump = np.zeros_like(valid)
    for dy, dx in ((0, 1), (1, 0), (1, 2), (2, 1)):
        nb = pad[dy:dy + d.shape[0], dx:dx + d.shape[1]]
        jump |= (np.abs(nb - d) > rel_jump * np.maximum(d, nb)) & (nb > 0) & valid
        jump |= valid & (nb <= 0)
    if dilate <= 0:
        return jump
    k = 2 * int(dilate) + 1
    return cv2.dilate(jump.astype(np.uint8), np.ones((k, k), np.uint8)) > 0


def _project(world: np.ndarray, pose_c2w: np.ndarray, intr, W: int, H: int):
    """World points into a camera: camera-frame points, pixel u, v and whether each lands inside
    the W×H image in front of the camera."""
    pc = transform(inv_np(pose_c2w), world)
    uv, z = project(pc, intr.fx, intr.fy, intr.cx, intr.cy)
    u, v = uv[:, 0], uv[:, 1]
    inside = (z > 0.05) & (u >= 0) & (u <= W - 1) & (v >= 0) & (v <= H - 1)
    return pc, u, v, inside


def keyframe_visibility(depth: np.ndarray, pose_c2w: np.ndarray, intr, keyframes, step: int = 4,
                        occlusion_margin: float = 0.3) -> tuple[np.ndarray, np.ndarray]:
    """What the keyframes saw of the current frame's back-projected points (at ``pose_c2w``).

    Returns two (H, W) bool masks, evaluated every ``step``-th pixel and upsampled (nearest):

    - ``in_frustum``: the point lies inside the view frustum of at least one keyframe;
    - ``observed``: for at least one keyframe the point is inside its frustum and the keyframe's
      measured depth there (``depth_small``) does not stop more than ``occlusion_margin`` in front
      of it: that keyframe saw the point, or the free space where it now is, not an occluder.
      Keyframes without ``depth_small`` count their whole frustum as observed.

    Both are all False when there are no keyframes.
    """
    import cv2

    d = np.asarray(depth, np.float32)
    H, W = d.shape
    if not keyframes:
        return np.zeros((H, W), bool), np.zeros((H, W), bool)
    vs, us = np.mgrid[0:H:step, 0:W:step]
    z = d[::step, ::step]
    pts = pixel_dirs(us.ravel(), vs.ravel(), intr.fx, intr.fy, intr.cx, intr.cy) * z.reshape(-1, 1)
    world = transform(pose_c2w, pts)
    frustum = np.zeros(len(world), bool)
    observed = np.zeros(len(world), bool)
    for kf in keyframes:
        pc, u, v, inside = _project(world, kf.pose_c2w, intr, W, H)
        frustum |= inside
        small = kf.depth_small
        if small is not None and inside.any():
            hs, ws = small.shape
            idx = np.flatnonzero(inside)
            iu = np.clip(np.round(u[idx] / DEPTH_STRIDE).astype(np.int64), 0, ws - 1)
            iv = np.clip(np.round(v[idx] / DEPTH_STRIDE).astype(np.int64), 0, hs - 1)
            d_kf = small[iv, iu].astype(np.float32)
            inside[idx[(d_kf <= 0) | (d_kf < pc[idx, 2] - occlusion_margin)]] = False
        observed |= inside

    def up(m):
        return cv2.resize(m.reshape(z.shape).astype(np.uint8), (W, H), interpolation=cv2.INTER_NEAREST) > 0

    return up(frustum), up(observed)


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
        pc, u, v, inside = _project(world, kf.pose_c2w, intr, W, H)
        small = kf.depth_raw_small
        hs, ws = small.shape
        iu = np.clip(np.round(np.where(inside, u, 0) / DEPTH_STRIDE).astype(np.int64), 0, ws - 1)
        iv = np.clip(np.round(np.where(inside, v, 0) / DEPTH_STRIDE).astype(np.int64), 0, hs - 1)
        d_kf = small[iv, iu].astype(np.float32)
        seen = inside & (d_kf > 0) & (d_kf >= pc[:, 2] - tolerance)  # not hidden behind something nearer
        agree = seen & (np.abs(d_kf - pc[:, 2]) <= tolerance)
        n_seen = np.bincount(lab[seen], minlength=k)[:k]
        n_agree = np.bincount(lab[agree], minlength=k)[:k]
        saw = n_seen >= min_seen * n
        ok &= ~saw | (n_agree >= min_agree * np.maximum(n_seen, 1))
        looked += saw
    return ok & (looked >= 2)


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
    newly = 0
    for kf in keyframes:
        d, _ = tree.query(kf.world_points(intr), distance_upper_bound=radius)
        newly += _mark_gone(kf, np.isfinite(d))
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
        pc, u, v, inside = _project(kf.world_points(intr), pose_c2w, intr, W, H)
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
        pc, u, v, inside = _project(world, kf.pose_c2w, intr, W, H)
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
