"""The finished trajectory, each frame solved again against the finished map.

While a sequence runs, a frame's pose comes from the landmarks as they were when it was tracked,
fused with the motion model's prediction, and is kept relative to its reference keyframe, so later
bundle adjustment moves it with that keyframe only.  The landmarks it matched move too, each on its
own, as later keyframes see them.  Once the sequence is finished, :func:`refine_poses` solves every
frame that is not a keyframe again, pose only and robustly (as tracking does:
:func:`~dynslam_cli.backend.tracking.optimize_pose`), from its own matched keypoints
(:class:`FrameMatches`) against the final positions of the landmarks they matched, those still
alive and not found to move since, starting from its keyframe-relative pose.  A frame left with
fewer than ``min_matches`` of them, or with fewer inliers after the solve, keeps that pose;
keyframes (whose matches the backend drops when it inserts them) keep their bundle-adjusted ones.
The poses so come without the motion model's prior, and their errors are independent from frame
to frame: the white noise the smoother (:mod:`~dynslam_cli.backend.smoothing`) then takes off the
centres, as its model assumes.
"""

from __future__ import annotations

import numpy as np

from dynslam_cli.backend.features import Keypoints
from dynslam_cli.backend.tracking import Camera, optimize_pose


class FrameMatches:
    """Each tracked frame's matched landmark ids and their keypoints (pixel, depth, octave, depth
    sigma; no descriptors), by the frame's row in the trajectory; the ids follow the landmark map's
    compaction (:meth:`remap`)."""

    def __init__(self):
        self._by_frame: dict[int, tuple[np.ndarray, Keypoints]] = {}

    def __len__(self) -> int:
        return len(self._by_frame)

    def set(self, frame: int, lm_ids: np.ndarray, kp: Keypoints) -> None:
        """Row ``frame`` matched landmarks ``lm_ids`` at keypoints ``kp`` (same order); replaces
        what it had (a frame tracked again)."""
        ids = np.asarray(lm_ids, np.int64).copy()
        if len(ids) != len(kp):
            raise ValueError(f"{len(ids)} landmark ids for {len(kp)} keypoints")
        kept = Keypoints(np.array(kp.uv, np.float64), np.zeros((len(kp), 0), np.uint8),
                         np.array(kp.depth, np.float64), np.array(kp.octave, np.int64), np.array(kp.dsig, np.float64))
        self._by_frame[int(frame)] = (ids, kept)

    def get(self, frame: int) -> tuple[np.ndarray, Keypoints] | None:
        return self._by_frame.get(int(frame))

    def drop(self, frame: int) -> None:
        """Forget row ``frame``'s matches (it became a keyframe: bundle adjustment holds its pose)."""
        self._by_frame.pop(int(frame), None)

    def frames(self) -> list[int]:
        return sorted(self._by_frame)

    def remap(self, remap: np.ndarray | None) -> None:
        """Landmark ids through the map's compaction (old id → new id, -1 = dropped; None: none)."""
        if remap is None:
            return
        for f, (ids, kp) in self._by_frame.items():
            self._by_frame[f] = (np.where(ids >= 0, remap[np.maximum(ids, 0)], -1) if len(ids) else ids, kp)

    # -- checkpoints ------------------------------------------------------------------------------
    def state_dict(self) -> dict:
        frames = self.frames()
        parts = [self._by_frame[f] for f in frames]
        cat = lambda xs, shape: np.concatenate(xs) if xs else np.zeros(shape)  # noqa: E731
        return {"frames": np.array(frames, np.int64), "counts": np.array([len(p[0]) for p in parts], np.int64),
                "ids": cat([p[0] for p in parts], (0,)).astype(np.int64),
                "uv": cat([p[1].uv for p in parts], (0, 2)), "depth": cat([p[1].depth for p in parts], (0,)),
                "octave": cat([p[1].octave for p in parts], (0,)).astype(np.int64),
                "dsig": cat([p[1].dsig for p in parts], (0,))}

    def load_state_dict(self, d: dict) -> None:
        self._by_frame = {}
        ends = np.cumsum(np.asarray(d["counts"], np.int64))
        for f, a, b in zip(np.asarray(d["frames"], np.int64), ends - np.asarray(d["counts"], np.int64), ends,
                           strict=True):
            kp = Keypoints(np.asarray(d["uv"])[a:b], np.zeros((b - a, 0), np.uint8), np.asarray(d["depth"])[a:b],
                           np.asarray(d["octave"])[a:b], np.asarray(d["dsig"])[a:b])
            self._by_frame[int(f)] = (np.asarray(d["ids"], np.int64)[a:b].copy(), kp)


def refine_poses(cam: Camera, poses: np.ndarray, matches: FrameMatches, positions: np.ndarray,
                 usable: np.ndarray, min_matches: int, huber: float) -> tuple[np.ndarray, int]:
    """``poses`` (F×4×4 camera-to-world, one row per tracked frame) with each row that has
    ``matches`` solved again against the landmark ``positions`` (L×3) of its matches still
    ``usable`` (L bool: alive and not moving), from its pose in ``poses``; a row keeps its pose
    with fewer than ``min_matches`` usable matches or inliers.  Returns the poses and how many
    changed."""
    out = np.array(poses, np.float64, copy=True)
    changed = 0
    for row in matches.frames():
        if row >= len(out):
            continue
        ids, kp = matches.get(row)
        ok = ids >= 0
        ok[ok] = usable[ids[ok]]
        if int(ok.sum()) < min_matches:
            continue
        rows = np.flatnonzero(ok)
        pose, inliers = optimize_pose(cam, out[row], positions[ids[rows]], kp.subset(rows), huber)
        if int(inliers.sum()) >= min_matches and np.all(np.isfinite(pose)):
            out[row] = pose
            changed += 1
    return out, changed
