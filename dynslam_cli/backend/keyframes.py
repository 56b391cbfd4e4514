"""The backend's keyframes: which frames they are, their bundle-adjusted poses and the landmarks
they made and observe (:class:`LandmarkKeyframes`, held by the run's keyframe store beside the
neural map's ray keyframes); and when a tracked frame becomes one (:func:`need_keyframe`: by
overlap with the reference keyframe, ORB-SLAM2's rule for RGB-D, or when too few of its close
keypoints are tracked, or after a maximum gap)."""

from __future__ import annotations

import numpy as np

from dynslam_cli.backend.bundle import BundleResult, local_bundle_adjustment
from dynslam_cli.backend.features import SCALE, in_image, project
from dynslam_cli.backend.landmarks import LandmarkMap

# A landmark a keyframe observed is in view again (ORB-SLAM's isInFrustum) when it projects into the image in front of
# the camera, at a camera distance within this factor of the keyframe's (the ORB pyramid's scale range, both ways)
# and seen from a direction within 60 degrees of the keyframe's.
IN_VIEW_DISTANCE_RATIO = SCALE ** 4
IN_VIEW_MIN_COS = 0.5
# Levenberg-Marquardt iterations of the two passes of the bundle adjustment of every keyframe after the last frame
# (the local one's are 5 and 10).
ADJUST_ALL_ITERS = (10, 20)


def _read_only(a: np.ndarray) -> np.ndarray:
    v = a.view()
    v.flags.writeable = False
    return v


class LandmarkKeyframes:
    """Keyframe ``k`` (0, 1, ... in insertion order) is frame ``frames[k]`` at camera-to-world pose
    ``poses[k]``; ``landmarks`` (a :class:`~dynslam_cli.backend.landmarks.LandmarkMap`) refers to
    keyframes by ``k``.  ``frames`` and ``poses`` are read-only views: they change through
    :meth:`add` and :meth:`set_pose`; :meth:`forget` leaves out the landmarks a keyframe made on
    instances found to move."""

    def __init__(self):
        self.landmarks = LandmarkMap()
        self._frames = np.zeros(0, np.int64)
        self._poses = np.zeros((0, 4, 4))

    def __len__(self) -> int:
        return len(self._frames)

    @property
    def frames(self) -> np.ndarray:
        return _read_only(self._frames)

    @property
    def poses(self) -> np.ndarray:
        return _read_only(self._poses)

    def add(self, frame_index: int, pose_c2w: np.ndarray) -> int:
        """A new keyframe at frame ``frame_index``; returns its number ``k``."""
        self._frames = np.append(self._frames, int(frame_index))
        self._poses = np.concatenate([self._poses, np.asarray(pose_c2w, np.float64)[None]])
        return len(self._frames) - 1

    def set_pose(self, k: int, pose_c2w: np.ndarray) -> None:
        self._poses[int(k)] = pose_c2w

    def index_of(self, frame_index: int) -> int:
        """The keyframe number of frame ``frame_index``, -1 when that frame is no keyframe."""
        k = np.flatnonzero(self._frames == int(frame_index))
        return int(k[0]) if len(k) else -1

    def in_view(self, pose_c2w: np.ndarray, K: np.ndarray, width: int, height: int, n: int, min_count: int,
                exclude=()) -> list[int]:
        """Up to ``n`` keyframes (not in ``exclude``), most first, that each observed at least
        ``min_count`` landmarks a camera at ``pose_c2w`` (intrinsics ``K``, image ``width`` ×
        ``height``) would see again: in its image, at a distance and from a direction close to the
        keyframe's (:data:`IN_VIEW_DISTANCE_RATIO`, :data:`IN_VIEW_MIN_COS`).  Covisibility links
        keyframes that matched the same landmarks; these are the keyframes of a place the camera
        comes back to, whose landmarks it made again because nothing linked them to the newer ones."""
        lm = self.landmarks
        skip = np.unique(np.asarray(list(exclude), np.int64))
        if len(self) <= len(skip) or n <= 0 or len(lm.obs_lm) == 0:  # no keyframe left to add (a short sequence)
            return []
        use = (lm.alive & ~lm.moving)[lm.obs_lm]
        okf, olm = lm.obs_kf[use], lm.obs_lm[use]
        X = lm.pos[olm]
        uv, z = project(pose_c2w, X, K)
        v_now = X - pose_c2w[:3, 3]
        v_kf = X - self._poses[okf, :3, 3]
        d_now, d_kf = np.linalg.norm(v_now, axis=1), np.linalg.norm(v_kf, axis=1)
        cos = (v_now * v_kf).sum(1) / np.maximum(d_now * d_kf, 1e-12)
        ratio = d_now / np.maximum(d_kf, 1e-12)
        seen = (in_image(uv, z, width, height) & (cos >= IN_VIEW_MIN_COS) & (ratio <= IN_VIEW_DISTANCE_RATIO)
                & (ratio >= 1.0 / IN_VIEW_DISTANCE_RATIO))
        counts = np.bincount(okf[seen], minlength=len(self))
        counts[skip] = 0
        order = np.lexsort((-np.arange(len(self)), -counts))  # most first; ties: newest first
        return [int(k) for k in order[:n] if counts[k] >= max(1, min_count)]

    def adjust_all(self, cam, huber: float) -> BundleResult | None:
        """Bundle adjustment of every keyframe but the first (the gauge) and every landmark in use
        (alive, not found to move), as the local one does it (camera ``cam``, Huber width ``huber``
        px); the poses and positions are replaced.  None with fewer than two keyframes or no landmark."""
        lm = self.landmarks
        ids = np.flatnonzero(lm.alive & ~lm.moving)
        if len(self) < 2 or len(ids) == 0:
            return None
        poses = {k: self._poses[k].copy() for k in range(len(self))}
        res = local_bundle_adjustment(cam, poses, list(range(1, len(self))), [0], ids, lm.pos[ids], lm.obs_kf,
                                      lm.obs_lm, lm.obs_uv, lm.obs_depth, lm.obs_octave, lm.obs_dsig, huber,
                                      iters=ADJUST_ALL_ITERS)
        for k, T in res.poses.items():
            self.set_pose(k, T)
        lm.pos[res.ids] = res.pos
        return res

    def forget(self, frame_index: int, instance_ids) -> int:
        """Leave out of tracking and bundle adjustment the landmarks that the keyframe of frame
        ``frame_index`` made on instances ``instance_ids`` (the ones called dynamic now; its other
        landmarks come back); returns how many are left out (0 when that frame is no keyframe)."""
        k = self.index_of(frame_index)
        return 0 if k < 0 else self.landmarks.set_moving(k, instance_ids)

    def state_dict(self) -> dict:
        """Numpy arrays only: the landmark map's (prefixed ``lm.``), ``kf_frame`` and ``kf_pose``."""
        d = {f"lm.{k}": v for k, v in self.landmarks.state_dict().items()}
        d.update({"kf_frame": self._frames.copy(), "kf_pose": self._poses.copy()})
        return d

    def load_state_dict(self, d: dict) -> None:
        self.landmarks.load_state_dict({k[3:]: v for k, v in d.items() if k.startswith("lm.")})
        self._frames = np.array(d["kf_frame"], np.int64)
        self._poses = np.array(d["kf_pose"], np.float64).reshape(-1, 4, 4)


def need_keyframe(inliers: int, ref_tracked: int, since_last: int, untracked_depth: int, n_keyframes: int,
                  ratio: float, max_gap: int) -> tuple[bool, str]:
    """``inliers``: landmarks the frame tracked; ``ref_tracked``: landmarks of the reference
    keyframe observed by at least two keyframes (one while there is one keyframe);
    ``since_last``: frames since the last keyframe; ``untracked_depth``: the frame's keypoints
    with depth that matched no landmark.  Returns (new keyframe?, why)."""
    if n_keyframes == 0:
        return True, "first"
    th = ratio if n_keyframes >= 2 else 0.4  # ORB-SLAM2: 0.4 while the map has one keyframe
    if inliers < th * ref_tracked and inliers > 15:
        return True, f"overlap {inliers}/{ref_tracked} < {th:g}"
    if inliers < 100 and untracked_depth > 70:  # few tracked close points, many new ones
        return True, f"few tracked ({inliers}), {untracked_depth} new points with depth"
    if since_last >= max_gap:
        return True, f"gap {since_last} frames"
    return False, ""
