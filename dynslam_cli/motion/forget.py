"""Forgetting: what makes keyframe rays unusable, for now or for good (the map stops replaying them).

- :func:`refresh_keyframes`: after a classifier update, every keyframe's usable rays are
  recomputed from the instances now called dynamic (within the mask dilation, :func:`near_ids`),
  and the backend drops the landmarks made on them; reclassified static rays are usable again.
- ``gone`` (never usable again): rays on the surface of what the backward check saw leave
  (:func:`departed_points` with :func:`forget_near`).
- The exported mesh: surfaces the newest keyframe looking at them saw through
  (:func:`departed_surface`), where what the map still holds was not seen to leave; near the places
  where the check saw something leave (:class:`DepartedPlaces`) with a tighter margin.
"""

from __future__ import annotations

import numpy as np

from dynslam_cli.geometry.camera import pixel_dirs, transform
from dynslam_cli.motion.checkable import depth_cell, project_into


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


def departed_points(res, observed: np.ndarray, rendered: np.ndarray, pose_c2w: np.ndarray, intr,
                    depth_threshold: float) -> np.ndarray:
    """(N, 3) world points: the rendered surface of what the backward check (``res``, a
    :class:`~dynslam_cli.motion.types.CheckResult`) saw leave: the pixels of flagged rendered segments where
    the ``observed`` depth lies more than ``depth_threshold`` (t_d) behind the ``rendered`` one, at the
    rendered depth (the check's resolution)."""
    if res is None or res.rendered_ids is None or not len(res.rendered_flagged):
        return np.zeros((0, 3))
    import cv2

    rids = res.rendered_ids
    h, w = rids.shape
    ren = cv2.resize(rendered.astype(np.float32), (w, h), interpolation=cv2.INTER_NEAREST)
    obs = cv2.resize(observed.astype(np.float32), (w, h), interpolation=cv2.INTER_NEAREST)
    left = np.isin(rids, res.rendered_flagged) & (ren > 0) & (obs > 0) & (obs - ren > depth_threshold)
    if not left.any():
        return np.zeros((0, 3))
    sx, sy = w / observed.shape[1], h / observed.shape[0]
    fx, fy, cx, cy = intr.fx * sx, intr.fy * sy, (intr.cx + 0.5) * sx - 0.5, (intr.cy + 0.5) * sy - 0.5
    vs, us = np.nonzero(left)
    return transform(pose_c2w, pixel_dirs(us, vs, fx, fy, cx, cy) * ren[vs, us][:, None])


class DepartedPlaces:
    """Where the backward check saw something leave over a run: the :func:`departed_points`, kept as the
    cells (``CELL`` m) they fall in, so that the store stays small on long runs."""

    CELL = 0.05

    def __init__(self):
        self._keys: set[tuple[int, int, int]] = set()

    def __len__(self) -> int:
        return len(self._keys)

    def add(self, points: np.ndarray) -> None:
        pts = np.asarray(points, np.float64).reshape(-1, 3)
        if len(pts):
            self._keys.update(map(tuple, np.unique(np.floor(pts / self.CELL).astype(np.int64), axis=0).tolist()))

    def near(self, points: np.ndarray, radius: float) -> np.ndarray:
        """(N,) bool: the ``points`` within ``radius`` (m) of a departed place (of its cell's centre, so up to
        half a cell's diagonal more)."""
        pts = np.asarray(points, np.float64).reshape(-1, 3)
        if not self._keys or not len(pts):
            return np.zeros(len(pts), bool)
        from scipy.spatial import cKDTree

        centres = (np.array(sorted(self._keys), np.float64) + 0.5) * self.CELL
        return np.isfinite(cKDTree(centres).query(pts, distance_upper_bound=radius)[0])

    def state(self) -> np.ndarray:
        return np.array(sorted(self._keys), np.int64).reshape(-1, 3)

    def load(self, keys) -> None:
        self._keys = set(map(tuple, np.asarray(keys, np.int64).reshape(-1, 3).tolist()))


def departed_surface(points: np.ndarray, keyframes, intr, margin, reach: int = 1) -> np.ndarray:
    """(N,) bool: the world ``points`` (a mesh's vertices) that the newest keyframe deciding about them saw
    through: a departed surface, which the mesh should not show.

    The keyframes are asked newest first, each with its whole depth map (``depth_raw_small``, movers
    included, within the sensor's usable range).  Where a point lands in a keyframe's
    image, a reading within ``margin`` of the point's depth says the surface is there (kept); readings at
    and around the pixel (``reach`` cells of the subsampled map on every side) that all lie more than
    ``margin`` behind it say the keyframe saw through it (departed); otherwise something stood in front
    or nothing was read, and older keyframes decide.  Points no keyframe decides are kept: only the
    newest observation of a place overrules the map.  ``margin``: one for all points, or one each (N,)."""
    pts = np.asarray(points, np.float64).reshape(-1, 3)
    margins = np.broadcast_to(np.asarray(margin, np.float64), (len(pts),))
    departed = np.zeros(len(pts), bool)
    todo = np.arange(len(pts))
    W, H = int(intr.width), int(intr.height)
    for kf in reversed(list(keyframes)):
        if not len(todo):
            break
        if kf.depth_raw_small is None:
            continue
        small = np.asarray(kf.depth_raw_small, np.float32)
        valid = small > 0
        pc, u, v, inside = project_into(pts[todo], kf.pose_c2w, intr, W, H)
        iv, iu = depth_cell(np.where(inside, u, 0), np.where(inside, v, 0), small.shape)
        z = pc[:, 2]
        m = margins[todo]
        d = np.where(valid, small, 0.0)[iv, iu]
        there = inside & (d > 0) & (np.abs(d - z) <= m)
        pad = np.pad(np.where(valid, small, np.inf), reach, constant_values=np.inf)
        nearest = np.full(len(todo), np.inf, np.float32)
        for dy in range(2 * reach + 1):
            for dx in range(2 * reach + 1):
                nearest = np.minimum(nearest, pad[iv + dy, iu + dx])
        through = inside & ~there & np.isfinite(nearest) & (nearest - z > m)
        departed[todo[through]] = True
        todo = todo[~(there | through)]
    return departed
